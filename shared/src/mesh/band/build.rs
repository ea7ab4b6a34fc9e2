//! A brick's samples: each lattice point's closest triangle found among a
//! short list of the triangles that may be closest anywhere in its block of
//! 2³ cells, [`W`] triangles at a time.
//!
//! The distance to a triangle is convex, so the largest distance from a box
//! to a triangle T₀ is at one of the box's corners: every point of the box
//! has a triangle within that distance U, and only triangles within U of
//! the box can be closest to any of its points. The brick's list holds the
//! triangles within U of the brick (T₀ closest to its centre). Every point
//! of a block lies within U = |c − T₀| + h of a triangle T₀ (c the block's
//! centre, h its half-diagonal; T₀ the triangle whose lower bound at c is
//! least), so the block's list holds the chunks of the brick's list with a
//! triangle whose bound at c is within U + h, sorted by the least bound of
//! their triangles at c. A point's
//! search takes the chunks in that order, skips those whose triangles'
//! lower bounds lie beyond the best distance so far, and stops at the first
//! chunk whose bound at the centre lies beyond it by more than the point's
//! distance from the centre.
//!
//! A triangle's lower bound at a point p is the larger of the distance to
//! its box and √(a² + b²), a the distance from p to the slab of the
//! triangle's plane that holds its corners and b the distance from p's
//! component across the plane's normal to a ball about the triangle's box's
//! centre that holds the triangle: any x of the triangle lies within the
//! slab and the ball, and |p − x|² is the sum of its squares along and
//! across the normal.
//!
//! A block whose centre lies farther from the soft region than its
//! half-diagonal has ±∞ samples, the side of its centre. A lower bound on
//! the centre's distance settles "far" without the closest triangle: a
//! point known to lie farther than r from the surface (the brick's centre,
//! an exact centre, a far block's centre with its lower bound) bounds the
//! distance at every point within r by the triangle inequality, and else
//! the least of the triangles' lower bounds. On a closed mesh the side is
//! the pseudo-normal's, the side of the surface (exact on such a mesh), so
//! it is the side of any point whose ball of distance from the surface
//! holds the block's centre; with no such point, the centre's exact sample
//! gives it. On any other mesh the side is the winding number's at the
//! centre, as [`Mesh::closest`] takes it.
//!
//! The result is [`Mesh::closest`]'s to the bit: the squared distance to
//! each triangle is `closest_on_triangle`'s arithmetic lane by lane (the
//! same IEEE operations in the same order), the minimum is unique or its
//! triangles give the same closest point and sign, and otherwise the point
//! takes [`Mesh::closest`] itself, whose visiting order breaks the tie. The
//! bounds are widened by 10⁻⁵ of the lengths involved, far beyond the
//! rounding of a box's or a triangle's distance.

use glam::Vec3;

use super::{BRICK, Grid, SAMPLES, SIDE};
use crate::mesh::{Mesh, Sign, closest_on_triangle};

/// Triangles per chunk: the lanes of the search.
const W: usize = 8;

/// One f32 per triangle of a chunk.
type Lanes = [f32; W];

/// Coordinates of the unused lanes of a chunk: their distances are +∞.
const FAR: f32 = 1e30;

/// Blocks along a brick's edge.
const BLOCKS: usize = BRICK / 2;

/// Blocks in a brick.
const BLOCK_COUNT: usize = BLOCKS * BLOCKS * BLOCKS;

/// [`W`] triangles as structure of arrays (x, y, z per field): the corners
/// and edges as `closest_on_triangle` forms them, their boxes and the data
/// of their lower bounds.
#[derive(Clone, Copy)]
struct Chunk {
    a: [Lanes; 3],
    b: [Lanes; 3],
    c: [Lanes; 3],
    /// b − a.
    ab: [Lanes; 3],
    /// c − a.
    ac: [Lanes; 3],
    /// c − b.
    bc: [Lanes; 3],
    lo: [Lanes; 3],
    hi: [Lanes; 3],
    /// The pseudo-normals of the corners a, b, c, the edges ab, bc, ca and
    /// the face.
    normal: [[Lanes; 3]; 7],
    /// The centre of the box.
    mid: [Lanes; 3],
    /// The largest distance from `mid` to a corner, rounded up.
    radius: Lanes,
    /// The least and the largest of `normal[6]·(corner − mid)` over the
    /// corners, widened by their rounding.
    across: [Lanes; 2],
    /// The triangles' indices ([`u32::MAX`] in unused lanes).
    tri: [u32; W],
}

const EMPTY: Chunk = Chunk {
    a: [[FAR; W]; 3],
    b: [[FAR; W]; 3],
    c: [[FAR; W]; 3],
    ab: [[0.0; W]; 3],
    ac: [[0.0; W]; 3],
    bc: [[0.0; W]; 3],
    lo: [[FAR; W]; 3],
    hi: [[FAR; W]; 3],
    normal: [[[0.0; W]; 3]; 7],
    mid: [[FAR; W]; 3],
    radius: [0.0; W],
    across: [[0.0; W]; 2],
    tri: [u32::MAX; W],
};

/// A list of triangles in chunks.
#[derive(Default)]
struct List {
    chunks: Vec<Chunk>,
    len: usize,
}

impl List {
    /// Appends triangle `i` of `mesh`.
    #[inline(always)]
    fn push(&mut self, mesh: &Mesh, i: u32) {
        let t = &mesh.triangles[i as usize];
        let [a, b, c] = t.v;
        let (ab, ac, bc) = (b - a, c - a, c - b);
        let normal = [
            t.vertex[0],
            t.vertex[1],
            t.vertex[2],
            t.edge[0],
            t.edge[1],
            t.edge[2],
            t.normal,
        ];
        let (lo, hi) = (a.min(b).min(c), a.max(b).max(c));
        let mid = (lo + hi) * 0.5;
        let radius = (a - mid)
            .length_squared()
            .max((b - mid).length_squared())
            .max((c - mid).length_squared())
            .sqrt()
            * (1.0 + 1e-6);
        let across = [a, b, c].map(|v| t.normal.dot(v - mid));
        // The rounding of a dot product of a unit vector: a few units of the
        // last place of the radius.
        let round = radius * 1e-6;
        let across = [
            across[0].min(across[1]).min(across[2]) - round,
            across[0].max(across[1]).max(across[2]) + round,
        ];
        let l = self.len % W;
        if l == 0 {
            self.chunks.push(EMPTY);
        }
        let ch = self.chunks.last_mut().expect("a chunk was pushed");
        for k in 0..3 {
            ch.a[k][l] = a[k];
            ch.b[k][l] = b[k];
            ch.c[k][l] = c[k];
            ch.ab[k][l] = ab[k];
            ch.ac[k][l] = ac[k];
            ch.bc[k][l] = bc[k];
            ch.lo[k][l] = lo[k];
            ch.hi[k][l] = hi[k];
            ch.mid[k][l] = mid[k];
            for (n, v) in ch.normal.iter_mut().zip(normal) {
                n[k][l] = v[k];
            }
        }
        ch.radius[l] = radius;
        ch.across[0][l] = across[0];
        ch.across[1][l] = across[1];
        ch.tri[l] = i;
        self.len += 1;
    }
}

/// The larger of `a` and `b` (`b` when either is NaN): one instruction.
#[inline(always)]
fn max(a: f32, b: f32) -> f32 {
    if a > b { a } else { b }
}

/// The lanes where `test` holds, bit l for lane l.
#[inline(always)]
fn mask(test: impl Fn(usize) -> bool) -> u32 {
    let mut bits = [0u32; W];
    for (l, bit) in bits.iter_mut().enumerate() {
        *bit = u32::from(test(l)) << l;
    }
    bits.iter().fold(0, |m, b| m | b)
}

/// The smallest lane.
#[inline(always)]
fn min_lane(v: &Lanes) -> f32 {
    let mut m = v[0];
    for &x in &v[1..] {
        m = if x < m { x } else { m };
    }
    m
}

/// One lane mask: all ones where true.
type Mask = [u32; W];

/// `f` per lane.
#[inline(always)]
fn each(f: impl Fn(usize) -> f32) -> Lanes {
    let mut out = [0.0; W];
    for (l, o) in out.iter_mut().enumerate() {
        *o = f(l);
    }
    out
}

/// The mask of `test` per lane.
#[inline(always)]
fn when(test: impl Fn(usize) -> bool) -> Mask {
    let mut out = [0; W];
    for (l, o) in out.iter_mut().enumerate() {
        *o = if test(l) { u32::MAX } else { 0 };
    }
    out
}

/// Lane by lane `a` where `m`, else `b`.
#[inline(always)]
fn pick(m: &Mask, a: &Lanes, b: &Lanes) -> Lanes {
    each(|l| f32::from_bits((m[l] & a[l].to_bits()) | (!m[l] & b[l].to_bits())))
}

/// The dot products of `u` and `v`, lane by lane as `Vec3::dot`.
#[inline(always)]
fn dot(u: &[Lanes; 3], v: &[Lanes; 3]) -> Lanes {
    each(|l| u[0][l] * v[0][l] + u[1][l] * v[1][l] + u[2][l] * v[2][l])
}

/// `p − v` per lane.
#[inline(always)]
fn from(p: Vec3, v: &[Lanes; 3]) -> [Lanes; 3] {
    [
        each(|l| p.x - v[0][l]),
        each(|l| p.y - v[1][l]),
        each(|l| p.z - v[2][l]),
    ]
}

/// The closest points of the chunk's triangles to `p`, whether `p` lies
/// outside by each one's pseudo-normal (when `signed`, else all ones), and
/// their squared distances from `p`: lane by lane `closest_on_triangle`'s
/// closest point, [`Mesh::closest`]'s sign and `(p - q).length_squared()`,
/// in the same operations (every case computed, the first that holds
/// taken).
#[inline(always)]
fn closest_lanes(p: Vec3, ch: &Chunk, signed: bool) -> ([Lanes; 3], Mask, Lanes) {
    let (a, b, c, ab, ac, bc) = (&ch.a, &ch.b, &ch.c, &ch.ab, &ch.ac, &ch.bc);
    let ap = from(p, a);
    let d1 = dot(ab, &ap);
    let d2 = dot(ac, &ap);
    let bp = from(p, b);
    let d3 = dot(ab, &bp);
    let d4 = dot(ac, &bp);
    let vc = each(|l| d1[l] * d4[l] - d3[l] * d2[l]);
    let cp = from(p, c);
    let d5 = dot(ab, &cp);
    let d6 = dot(ac, &cp);
    let vb = each(|l| d5[l] * d2[l] - d1[l] * d6[l]);
    let va = each(|l| d3[l] * d6[l] - d5[l] * d4[l]);
    let denom = each(|l| 1.0 / (va[l] + vb[l] + vc[l]));
    let v = each(|l| vb[l] * denom[l]);
    let w = each(|l| vc[l] * denom[l]);
    let w1 = each(|l| (d4[l] - d3[l]) / ((d4[l] - d3[l]) + (d5[l] - d6[l])));
    let w2 = each(|l| d2[l] / (d2[l] - d6[l]));
    let w0 = each(|l| d1[l] / (d1[l] - d3[l]));
    // The cases, the first that holds taken: corner a, corner b, edge ab,
    // corner c, edge ca, edge bc, the face.
    let v0 = when(|l| d1[l] <= 0.0 && d2[l] <= 0.0);
    let v1 = when(|l| d3[l] >= 0.0 && d4[l] <= d3[l]);
    let e0 = when(|l| vc[l] <= 0.0 && d1[l] >= 0.0 && d3[l] <= 0.0);
    let v2 = when(|l| d6[l] >= 0.0 && d5[l] <= d6[l]);
    let e2 = when(|l| vb[l] <= 0.0 && d2[l] >= 0.0 && d6[l] <= 0.0);
    let e1 = when(|l| va[l] <= 0.0 && (d4[l] - d3[l]) >= 0.0 && (d5[l] - d6[l]) >= 0.0);
    let mut q = [[0.0; W]; 3];
    let mut n = [[0.0; W]; 3];
    for k in 0..3 {
        let mut x = each(|l| a[k][l] + ab[k][l] * v[l] + ac[k][l] * w[l]);
        x = pick(&e1, &each(|l| b[k][l] + bc[k][l] * w1[l]), &x);
        x = pick(&e2, &each(|l| a[k][l] + ac[k][l] * w2[l]), &x);
        x = pick(&v2, &c[k], &x);
        x = pick(&e0, &each(|l| a[k][l] + ab[k][l] * w0[l]), &x);
        x = pick(&v1, &b[k], &x);
        q[k] = pick(&v0, &a[k], &x);
        if signed {
            let f = &ch.normal;
            let mut y = f[6][k];
            y = pick(&e1, &f[4][k], &y);
            y = pick(&e2, &f[5][k], &y);
            y = pick(&v2, &f[2][k], &y);
            y = pick(&e0, &f[3][k], &y);
            y = pick(&v1, &f[1][k], &y);
            n[k] = pick(&v0, &f[0][k], &y);
        }
    }
    let d = from(p, &q);
    let outside = if signed {
        let s = dot(&d, &n);
        when(|l| s[l] >= 0.0)
    } else {
        [u32::MAX; W]
    };
    (q, outside, dot(&d, &d))
}

/// Lower bounds of the squared distances from `p` to the chunk's
/// triangles, each bound's lengths shortened by `s` (see the module's
/// doc): the squared distance to the box, or the sum of the squares of the
/// distances to the slab and to the ball across the normal, the larger.
#[inline(always)]
fn bounds2(p: Vec3, ch: &Chunk, s: f32) -> Lanes {
    let n = &ch.normal[6];
    each(|l| {
        let d = [p.x - ch.mid[0][l], p.y - ch.mid[1][l], p.z - ch.mid[2][l]];
        let t = n[0][l] * d[0] + n[1][l] * d[1] + n[2][l] * d[2];
        let r2 = d[0] * d[0] + d[1] * d[1] + d[2] * d[2];
        let slab = max(max(t - ch.across[1][l], ch.across[0][l] - t) - s, 0.0);
        // |d|² − t², less the rounding of both (a few units of the last
        // place of |d|²).
        let sideways = max(r2 * (1.0 - 4e-6) - t * t, 0.0).sqrt();
        let ball = max(sideways - ch.radius[l] - s, 0.0);
        let gap = |k: usize| max(max(ch.lo[k][l] - p[k], p[k] - ch.hi[k][l]), 0.0);
        let (x, y, z) = (gap(0), gap(1), gap(2));
        max(slab * slab + ball * ball, x * x + y * y + z * z)
    })
}

/// What a search of a list found.
enum Found {
    /// The least squared distance, its closest point's bits and the side
    /// (all ones outside) by its pseudo-normal, which all the triangles at
    /// that distance give.
    One(f32, [u32; 3], u32),
    /// Triangles at the least squared distance `m` with different closest
    /// points or sides.
    Tie(f32),
    /// No triangle within the bound.
    None,
}

/// The bounds of a build: the rounding slack of its lengths.
struct Slack {
    /// 10⁻⁵ of the largest coordinate of the grid.
    length: f32,
}

impl Slack {
    /// `r` widened by the slack.
    #[inline(always)]
    fn widen(&self, r: f32) -> f32 {
        r * (1.0 + 1e-5) + self.length
    }

    /// `r` shortened by the slack.
    #[inline(always)]
    fn shrink(&self, r: f32) -> f32 {
        r * (1.0 - 1e-5) - self.length
    }
}

/// A chunk of a block's list: its index in the brick's list and the least
/// lower bound of its triangles' distances from the block's centre.
#[derive(Clone, Copy)]
struct Near {
    key: f32,
    chunk: u32,
}

/// The triangles of `list`'s chunks `near` at the least squared distance
/// from `p`, which is at most `bound` (squared); `off` is at least the
/// distance from `p` to the centre `near`'s keys were measured from;
/// `signed`: the side from the pseudo-normals.
#[inline(always)]
fn search(
    p: Vec3,
    off: f32,
    list: &List,
    near: &[Near],
    bound: f32,
    slack: &Slack,
    signed: bool,
) -> Found {
    let mut best = [f32::INFINITY; W];
    let mut point = [[0u32; W]; 3];
    let mut side = [0u32; W];
    let mut tie = [0u32; W];
    // A bound farther than the least distance so far, widened, holds no
    // triangle as close: (√d·(1 + 10⁻⁵) + s)² ≤ d·(1 + 3·10⁻⁵) + 2s√b + s²
    // for d ≤ b.
    let s = slack.length;
    let pad = 2.0 * s * bound.sqrt() * (1.0 + 1e-5) + s * s;
    let mut least = bound;
    let mut within = bound * (1.0 + 3e-5) + pad;
    let mut radius = within.sqrt() * (1.0 + 1e-6);
    for nr in near {
        // The keys ascend: the triangles of this chunk and the next ones lie
        // farther than `radius` from p.
        if nr.key - off > radius {
            break;
        }
        let ch = &list.chunks[nr.chunk as usize];
        let lower = bounds2(p, ch, s);
        if mask(|l| lower[l] <= within) == 0 {
            continue;
        }
        let (q, outside, d2) = closest_lanes(p, ch, signed);
        let better = when(|l| d2[l] < best[l]);
        let same = when(|l| {
            outside[l] == side[l]
                && q[0][l].to_bits() == point[0][l]
                && q[1][l].to_bits() == point[1][l]
                && q[2][l].to_bits() == point[2][l]
        });
        let equal = when(|l| d2[l] == best[l]);
        for l in 0..W {
            tie[l] = !better[l] & (tie[l] | (equal[l] & !same[l]));
            side[l] = (better[l] & outside[l]) | (!better[l] & side[l]);
        }
        best = pick(&better, &d2, &best);
        for k in 0..3 {
            for l in 0..W {
                point[k][l] = (better[l] & q[k][l].to_bits()) | (!better[l] & point[k][l]);
            }
        }
        let m = min_lane(&d2);
        if m < least {
            least = m;
            within = least * (1.0 + 3e-5) + pad;
            radius = within.sqrt() * (1.0 + 1e-6);
        }
    }
    let m = min_lane(&best);
    if m == f32::INFINITY {
        return Found::None;
    }
    let mut one: Option<usize> = None;
    for l in 0..W {
        if best[l] != m {
            continue;
        }
        if tie[l] != 0 {
            return Found::Tie(m);
        }
        match one {
            None => one = Some(l),
            Some(o) => {
                if side[l] != side[o] || (0..3).any(|k| point[k][l] != point[k][o]) {
                    return Found::Tie(m);
                }
            }
        }
    }
    match one {
        Some(l) => Found::One(m, [point[0][l], point[1][l], point[2][l]], side[l]),
        None => Found::None,
    }
}

/// The sample at `p` from the triangles of `list`'s chunks `near` (which
/// hold every triangle that may be closest to `p`, their keys measured
/// from a point within `off` of `p`), searched within `bound` (squared,
/// at least the squared distance to a triangle).
#[inline(always)]
fn sample(
    mesh: &Mesh,
    p: Vec3,
    off: f32,
    list: &List,
    near: &[Near],
    bound: f32,
    slack: &Slack,
) -> [f32; 4] {
    let signed = mesh.sign == Sign::PseudoNormal;
    match search(p, off, list, near, bound, slack, signed) {
        Found::One(m, q, side) => {
            let outside = if signed {
                side != 0
            } else {
                mesh.winding_number(p) < 0.5
            };
            let d = m.sqrt();
            let q = q.map(f32::from_bits);
            [if outside { d } else { -d }, q[0], q[1], q[2]]
        }
        Found::Tie(m) => first_visited(mesh, p, list, near, m, slack),
        Found::None => reference(mesh, p),
    }
}

/// The sample at `p` from the triangle at the squared distance `m` that
/// [`Mesh::closest`] visits first, among the triangles of `list`'s chunks
/// `near` (which hold every triangle that may be closest to `p`).
#[cold]
#[inline(never)]
fn first_visited(
    mesh: &Mesh,
    p: Vec3,
    list: &List,
    near: &[Near],
    m: f32,
    slack: &Slack,
) -> [f32; 4] {
    let within = slack.widen(m.sqrt()).powi(2);
    let mut first: Option<(u32, Vec3, crate::mesh::Feature)> = None;
    for nr in near {
        let ch = &list.chunks[nr.chunk as usize];
        for &i in &ch.tri {
            if i == u32::MAX {
                continue;
            }
            let [a, b, c] = mesh.triangles[i as usize].v;
            let gap = (a.min(b).min(c) - p)
                .max(p - a.max(b).max(c))
                .max(Vec3::ZERO);
            if gap.length_squared() > within {
                continue;
            }
            let (q, feature) = closest_on_triangle(p, [a, b, c]);
            if (p - q).length_squared() != m {
                continue;
            }
            let earlier = match first {
                None => true,
                Some((j, _, _)) => {
                    mesh.bvh
                        .visits_before(p, i as usize, j as usize, mesh.triangles.len())
                }
            };
            if earlier {
                first = Some((i, q, feature));
            }
        }
    }
    match first {
        Some((i, q, feature)) => {
            let c = mesh.signed(p, m, q, i as usize, feature);
            [c.distance, c.point.x, c.point.y, c.point.z]
        }
        None => reference(mesh, p),
    }
}

/// [`Mesh::closest`]'s sample at `p`.
#[cold]
#[inline(never)]
fn reference(mesh: &Mesh, p: Vec3) -> [f32; 4] {
    let c = mesh.closest(p);
    [c.distance, c.point.x, c.point.y, c.point.z]
}

/// The squared distance from `p` to triangle `i`.
#[inline(always)]
fn distance2(mesh: &Mesh, p: Vec3, i: u32) -> f32 {
    let (q, _) = closest_on_triangle(p, mesh.triangles[i as usize].v);
    (p - q).length_squared()
}

/// About the largest distance from the box `lo`..`hi` to triangle `i` (at
/// a corner; `closest_on_triangle`'s cases for the 8 corners at once, the
/// rounding left to the caller's slack).
#[inline(always)]
fn farthest(mesh: &Mesh, lo: Vec3, hi: Vec3, i: u32) -> f32 {
    let [a, b, c] = mesh.triangles[i as usize].v;
    let (ab, ac) = (b - a, c - a);
    let corner = |k: usize| each(|l| if l >> k & 1 != 0 { hi[k] } else { lo[k] });
    let p = [corner(0), corner(1), corner(2)];
    let rel = |v: Vec3| [0, 1, 2].map(|k| each(|l| p[k][l] - v[k]));
    let dot = |u: Vec3, d: &[Lanes; 3]| each(|l| u.x * d[0][l] + u.y * d[1][l] + u.z * d[2][l]);
    let (ap, bp, cp) = (rel(a), rel(b), rel(c));
    let (d1, d2) = (dot(ab, &ap), dot(ac, &ap));
    let (d3, d4) = (dot(ab, &bp), dot(ac, &bp));
    let (d5, d6) = (dot(ab, &cp), dot(ac, &cp));
    let out = each(|l| {
        let vc = d1[l] * d4[l] - d3[l] * d2[l];
        let vb = d5[l] * d2[l] - d1[l] * d6[l];
        let va = d3[l] * d6[l] - d5[l] * d4[l];
        let (u, v) = if d1[l] <= 0.0 && d2[l] <= 0.0 {
            (0.0, 0.0)
        } else if d3[l] >= 0.0 && d4[l] <= d3[l] {
            (1.0, 0.0)
        } else if vc <= 0.0 && d1[l] >= 0.0 && d3[l] <= 0.0 {
            (d1[l] / (d1[l] - d3[l]), 0.0)
        } else if d6[l] >= 0.0 && d5[l] <= d6[l] {
            (0.0, 1.0)
        } else if vb <= 0.0 && d2[l] >= 0.0 && d6[l] <= 0.0 {
            (0.0, d2[l] / (d2[l] - d6[l]))
        } else if va <= 0.0 && (d4[l] - d3[l]) >= 0.0 && (d5[l] - d6[l]) >= 0.0 {
            let w = (d4[l] - d3[l]) / ((d4[l] - d3[l]) + (d5[l] - d6[l]));
            (1.0 - w, w)
        } else {
            let denom = 1.0 / (va + vb + vc);
            (vb * denom, vc * denom)
        };
        let e = [0, 1, 2].map(|k| ap[k][l] - ab[k] * u - ac[k] * v);
        e[0] * e[0] + e[1] * e[1] + e[2] * e[2]
    });
    if out.iter().any(|d| d.is_nan()) {
        return f32::INFINITY;
    }
    out.iter().fold(0.0f32, |m, &d| m.max(d)).sqrt() * (1.0 + 1e-6)
}

/// The side of `p` by the winding number (−1 inside, 1 outside), as
/// [`Mesh::closest`] takes it.
fn winding_side(mesh: &Mesh, p: Vec3) -> i8 {
    if mesh.winding_number(p) < 0.5 { 1 } else { -1 }
}

/// A point whose distance from the surface is at least `r`, and its side
/// (−1 inside, 1 outside) where known.
#[derive(Clone, Copy)]
struct Anchor {
    p: Vec3,
    r: f32,
    side: i8,
}

/// The samples of the brick in `slot`. The brick is cut into blocks of
/// 2³ cells; a block whose centre lies farther from the soft region than
/// its half-diagonal holds no point of it, and its samples are ±∞ (the
/// centre's side); the samples of the other blocks are exact.
#[inline(always)]
pub(super) fn brick(grid: &Grid, mesh: &Mesh, slot: usize) -> Vec<[f32; 4]> {
    let base = grid.slot_origin(slot);
    let lattice =
        |x: usize, y: usize, z: usize| base + Vec3::new(x as f32, y as f32, z as f32) * grid.voxel;
    let slack = Slack {
        length: 1e-5 * grid.scale,
    };
    let s = slack.length;
    let signed = mesh.sign == Sign::PseudoNormal;
    let half = grid.voxel * 3f32.sqrt();
    // A block's centre lies beyond the band when its exact distance d has
    // |d| − half > reach; `lower` is a lower bound of the true distance.
    let beyond = |lower: f32| slack.shrink(lower) - half > grid.reach;
    // The brick's list, and its centre as the first anchor.
    let (lo, hi) = (lattice(0, 0, 0), lattice(BRICK, BRICK, BRICK));
    let middle = lattice(BRICK / 2, BRICK / 2, BRICK / 2);
    let mut anchors: Vec<Anchor> = Vec::with_capacity(BLOCK_COUNT + 1);
    let hint = if signed {
        let (c, i) = mesh.closest_and_triangle(middle);
        anchors.push(Anchor {
            p: middle,
            r: slack.shrink(c.distance.abs()),
            side: if c.distance < 0.0 { -1 } else { 1 },
        });
        i as u32
    } else {
        let i = mesh.closest_triangle(middle) as u32;
        anchors.push(Anchor {
            p: middle,
            r: slack.shrink(distance2(mesh, middle, i).sqrt()),
            side: 0,
        });
        i
    };
    let reach = slack.widen(farthest(mesh, lo, hi, hint));
    let mut found = Vec::new();
    mesh.bvh.near_box(lo, hi, reach, &mut found);
    let mut all = List::default();
    let r2 = reach * reach;
    for &i in &found {
        let [a, b, c] = mesh.triangles[i as usize].v;
        let gap = (a.min(b).min(c) - hi)
            .max(lo - a.max(b).max(c))
            .max(Vec3::ZERO);
        if gap.length_squared() <= r2 {
            all.push(mesh, i);
        }
    }
    // Per block: far (the side), or near with its list of chunks, the
    // bound of its samples' squared distances, and its centre's sample when
    // computed.
    let mut near: Vec<Near> = Vec::new();
    let mut first = [0usize; BLOCK_COUNT + 1];
    let mut bound = [0f32; BLOCK_COUNT];
    let mut centre: [Option<[f32; 4]>; BLOCK_COUNT] = [None; BLOCK_COUNT];
    let mut far = [0i8; BLOCK_COUNT];
    let mut mins = vec![0f32; all.chunks.len()];
    let side_of = |d: f32| if d < 0.0 { -1 } else { 1 };
    for k in 0..BLOCK_COUNT {
        first[k] = near.len();
        let (x, y, z) = (
            2 * (k % BLOCKS),
            2 * (k / BLOCKS % BLOCKS),
            2 * (k / (BLOCKS * BLOCKS)),
        );
        let c = lattice(x + 1, y + 1, z + 1);
        // The farthest the anchors place the centre from the surface.
        let by_anchor = anchors
            .iter()
            .map(|a| (a.r - (c - a.p).length() * (1.0 + 1e-6) - s, a.side))
            .fold((f32::NEG_INFINITY, 0), |m, a| if a.0 > m.0 { a } else { m });
        if beyond(by_anchor.0) {
            far[k] = if signed {
                by_anchor.1
            } else {
                winding_side(mesh, c)
            };
            continue;
        }
        let mut least = (f32::INFINITY, 0usize);
        for (n, (m, ch)) in mins.iter_mut().zip(&all.chunks).enumerate() {
            *m = min_lane(&bounds2(c, ch, s));
            if *m < least.0 {
                least = (*m, n);
            }
        }
        let least = (least.0, {
            let ch = &all.chunks[least.1];
            let lower = bounds2(c, ch, s);
            let l = (0..W).find(|&l| lower[l] == least.0).unwrap_or(0);
            ch.tri[l]
        });
        let least_bound = least.0.sqrt() * (1.0 - 1e-6);
        if beyond(least_bound) {
            let side = if !signed {
                winding_side(mesh, c)
            } else {
                match anchors
                    .iter()
                    .find(|a| a.side != 0 && (c - a.p).length() * (1.0 + 1e-6) + s < a.r)
                {
                    Some(a) => a.side,
                    None => {
                        let keys: Vec<Near> = (0..all.chunks.len())
                            .map(|n| Near {
                                key: 0.0,
                                chunk: n as u32,
                            })
                            .collect();
                        let b = distance2(mesh, c, least.1);
                        let v = sample(
                            mesh,
                            c,
                            s,
                            &all,
                            &keys,
                            slack.widen(b.sqrt()).powi(2),
                            &slack,
                        );
                        side_of(v[0])
                    }
                }
            };
            far[k] = side;
            anchors.push(Anchor {
                p: c,
                r: least_bound,
                side,
            });
            continue;
        }
        // Every point of the block lies within u of the triangle of least
        // bound (dc from the centre, which lies within `half` of every
        // point): the block's list holds the triangles within u of the
        // block, whose bounds at the centre are within u + half.
        let dc = distance2(mesh, c, least.1).sqrt();
        let u = slack.widen(dc + half);
        let v2 = slack.widen(u + half).powi(2);
        for (n, &m) in mins.iter().enumerate() {
            if m <= v2 {
                near.push(Near {
                    key: m.sqrt() * (1.0 - 1e-6),
                    chunk: n as u32,
                });
            }
        }
        near[first[k]..].sort_unstable_by(|a, b| a.key.total_cmp(&b.key));
        bound[k] = u * u;
        if slack.widen(dc) - half > grid.reach {
            // Not surely near: the centre's exact sample decides.
            let v = sample(mesh, c, s, &all, &near[first[k]..], u * u, &slack);
            if v[0].abs() - half > grid.reach {
                far[k] = side_of(v[0]);
                anchors.push(Anchor {
                    p: c,
                    r: slack.shrink(v[0].abs()),
                    side: if signed { side_of(v[0]) } else { 0 },
                });
                near.truncate(first[k]);
                continue;
            }
            centre[k] = Some(v);
        }
    }
    first[BLOCK_COUNT] = near.len();
    // The blocks a sample's coordinate lies in: one, or two on a face
    // between blocks.
    let blocks = |x: usize| {
        let hi = (x / 2).min(BLOCKS - 1);
        let lo = if x.is_multiple_of(2) && x > 0 {
            x / 2 - 1
        } else {
            hi
        };
        lo..=hi
    };
    // Per sample: the first near block it lies in (computed there), or the
    // side of the last block.
    let mut out = vec![[0.0f32; 4]; SAMPLES];
    let mut owner = [u8::MAX; SAMPLES];
    for z in 0..SIDE {
        for y in 0..SIDE {
            for x in 0..SIDE {
                let mut side = 0;
                let mut first = None;
                for bz in blocks(z) {
                    for by in blocks(y) {
                        for bx in blocks(x) {
                            let b = bx + BLOCKS * (by + BLOCKS * bz);
                            if far[b] == 0 && first.is_none() {
                                first = Some(b);
                            }
                            side = far[b];
                        }
                    }
                }
                let s = x + SIDE * (y + SIDE * z);
                match first {
                    Some(b) => owner[s] = b as u8,
                    None => out[s] = [f32::INFINITY.copysign(f32::from(side)), 0.0, 0.0, 0.0],
                }
            }
        }
    }
    for k in 0..BLOCK_COUNT {
        if far[k] != 0 {
            continue;
        }
        let near = &near[first[k]..first[k + 1]];
        let (bx, by, bz) = (
            2 * (k % BLOCKS),
            2 * (k / BLOCKS % BLOCKS),
            2 * (k / (BLOCKS * BLOCKS)),
        );
        let c = lattice(bx + 1, by + 1, bz + 1);
        for z in bz..=bz + 2 {
            for y in by..=by + 2 {
                for x in bx..=bx + 2 {
                    let i = x + SIDE * (y + SIDE * z);
                    if owner[i] as usize != k {
                        continue;
                    }
                    if let (Some(v), true) = (centre[k], (x, y, z) == (bx + 1, by + 1, bz + 1)) {
                        out[i] = v;
                        continue;
                    }
                    let p = lattice(x, y, z);
                    let off = (p - c).length() * (1.0 + 1e-6) + s;
                    out[i] = sample(mesh, p, off, &all, near, bound[k], &slack);
                }
            }
        }
    }
    out
}
