//! A brick's samples: each lattice point's closest triangle found among a
//! short list of the triangles that may be closest anywhere in its block of
//! 2³ cells, [`W`] triangles at a time.
//!
//! The distance to a triangle is convex, so the largest distance from a box
//! to a triangle T₀ is at one of the box's corners: every point of the box
//! has a triangle within that distance U, and only triangles within U of
//! the box can be closest to any of its points. The brick's list holds the
//! triangles within U of the brick (T₀ closest to its centre), a block's
//! list those of the brick's list within U of the block (T₀ closest to the
//! block's centre). A point's search skips the triangles whose box lies
//! farther than the best distance so far, starting from its neighbour's
//! closest triangle.
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

/// [`W`] triangles as structure of arrays (x, y, z per field): the corners
/// and edges as `closest_on_triangle` forms them, and their boxes.
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
            for (n, v) in ch.normal.iter_mut().zip(normal) {
                n[k][l] = v[k];
            }
        }
        ch.tri[l] = i;
        self.len += 1;
    }

    /// Appends to `out` the indices of the chunks with a triangle whose box
    /// lies within `r` of the box `lo`..`hi`.
    #[inline(always)]
    fn near(&self, lo: Vec3, hi: Vec3, r: f32, out: &mut Vec<u16>) {
        let r2 = r * r;
        for (n, ch) in self.chunks.iter().enumerate() {
            let mut d2 = [0.0; W];
            for (l, d2) in d2.iter_mut().enumerate() {
                let gap = |k: usize| max(max(ch.lo[k][l] - hi[k], lo[k] - ch.hi[k][l]), 0.0);
                let (x, y, z) = (gap(0), gap(1), gap(2));
                *d2 = x * x + y * y + z * z;
            }
            if mask(|l| d2[l] <= r2) != 0 {
                out.push(n as u16);
            }
        }
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

/// The squared distances from `p` to the chunk's boxes.
#[inline(always)]
fn box_distances2(p: Vec3, ch: &Chunk) -> Lanes {
    let mut out = [0.0; W];
    for (l, out) in out.iter_mut().enumerate() {
        let gap = |k: usize| max(max(ch.lo[k][l] - p[k], p[k] - ch.hi[k][l]), 0.0);
        let (x, y, z) = (gap(0), gap(1), gap(2));
        *out = x * x + y * y + z * z;
    }
    out
}

/// What a search of a list found.
enum Found {
    /// The least squared distance, its closest point's bits and the side
    /// (all ones outside) by its pseudo-normal, which all the triangles at
    /// that distance give, and one of them.
    One(f32, [u32; 3], u32, u32),
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
}

/// The triangles of `list`'s chunks `near` at the least squared distance
/// from `p`, which is at most `bound` (a triangle's squared distance from
/// `p`); `signed`: the side from the pseudo-normals.
#[inline(always)]
fn search(p: Vec3, list: &List, near: &[u16], bound: f32, slack: &Slack, signed: bool) -> Found {
    let mut best = [f32::INFINITY; W];
    let mut tri = [u32::MAX; W];
    let mut point = [[0u32; W]; 3];
    let mut side = [0u32; W];
    let mut tie = [0u32; W];
    // A box farther than the least distance so far, widened, holds no
    // triangle as close: (√d·(1 + 10⁻⁵) + s)² ≤ d·(1 + 3·10⁻⁵) + 2s√b + s²
    // for d ≤ b.
    let s = slack.length;
    let pad = 2.0 * s * bound.sqrt() * (1.0 + 1e-5) + s * s;
    let mut least = bound;
    let mut within = bound * (1.0 + 3e-5) + pad;
    for &n in near {
        let ch = &list.chunks[n as usize];
        let boxes = box_distances2(p, ch);
        if mask(|l| boxes[l] <= within) == 0 {
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
            tri[l] = (better[l] & ch.tri[l]) | (!better[l] & tri[l]);
            side[l] = (better[l] & outside[l]) | (!better[l] & side[l]);
        }
        best = pick(&better, &d2, &best);
        for k in 0..3 {
            for l in 0..W {
                point[k][l] = (better[l] & q[k][l].to_bits()) | (!better[l] & point[k][l]);
            }
        }
        least = least.min(min_lane(&d2));
        within = least * (1.0 + 3e-5) + pad;
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
        Some(l) => Found::One(m, [point[0][l], point[1][l], point[2][l]], side[l], tri[l]),
        None => Found::None,
    }
}

/// The sample at `p` from the triangles of `list`'s chunks `near` (which
/// hold every triangle that may be closest to `p`), searched within `bound`
/// (a triangle's squared distance from `p`), and a closest triangle.
#[inline(always)]
fn sample(
    mesh: &Mesh,
    p: Vec3,
    list: &List,
    near: &[u16],
    bound: f32,
    slack: &Slack,
) -> ([f32; 4], u32) {
    let signed = mesh.sign == Sign::PseudoNormal;
    match search(p, list, near, bound, slack, signed) {
        Found::One(m, q, side, i) => {
            let outside = if signed {
                side != 0
            } else {
                mesh.winding_number(p) < 0.5
            };
            let d = m.sqrt();
            let q = q.map(f32::from_bits);
            ([if outside { d } else { -d }, q[0], q[1], q[2]], i)
        }
        Found::Tie(m) => first_visited(mesh, p, list, near, m, slack),
        Found::None => (reference(mesh, p), mesh.closest_triangle(p) as u32),
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
    near: &[u16],
    m: f32,
    slack: &Slack,
) -> ([f32; 4], u32) {
    let within = slack.widen(m.sqrt()).powi(2);
    let mut first: Option<(u32, Vec3, crate::mesh::Feature)> = None;
    for &n in near {
        let ch = &list.chunks[n as usize];
        let boxes = box_distances2(p, ch);
        for (&i, &b) in ch.tri.iter().zip(&boxes) {
            if b > within || i == u32::MAX {
                continue;
            }
            let (q, feature) = closest_on_triangle(p, mesh.triangles[i as usize].v);
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
            ([c.distance, c.point.x, c.point.y, c.point.z], i)
        }
        None => (reference(mesh, p), mesh.closest_triangle(p) as u32),
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

/// The largest distance from the box `lo`..`hi` to triangle `i` (at a
/// corner).
#[inline(always)]
fn farthest(mesh: &Mesh, lo: Vec3, hi: Vec3, i: u32) -> f32 {
    (0..8)
        .map(|k| {
            let pick = |bit: usize, a: f32, b: f32| if k & bit != 0 { b } else { a };
            let corner = Vec3::new(
                pick(1, lo.x, hi.x),
                pick(2, lo.y, hi.y),
                pick(4, lo.z, hi.z),
            );
            distance2(mesh, corner, i)
        })
        .fold(0.0, f32::max)
        .sqrt()
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
    let half = grid.voxel * 3f32.sqrt();
    // The brick's list.
    let (lo, hi) = (lattice(0, 0, 0), lattice(BRICK, BRICK, BRICK));
    let mut hint = mesh.closest_triangle(lattice(BRICK / 2, BRICK / 2, BRICK / 2)) as u32;
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
    // Per block: the chunks that may hold a closest triangle (within the
    // distance from the block to the previous centre's), its centre's sample
    // and triangle, and 0 near, else the side (-1 inside, 1 outside).
    let block_box = |k: usize| {
        let (x, y, z) = (
            2 * (k % BLOCKS),
            2 * (k / BLOCKS % BLOCKS),
            2 * (k / (BLOCKS * BLOCKS)),
        );
        (lattice(x, y, z), lattice(x + 2, y + 2, z + 2))
    };
    let mut near = Vec::new();
    let mut first = [0usize; BLOCKS * BLOCKS * BLOCKS + 1];
    let mut centre = [([0.0f32; 4], 0u32); BLOCKS * BLOCKS * BLOCKS];
    let mut far = [0i8; BLOCKS * BLOCKS * BLOCKS];
    for k in 0..BLOCKS * BLOCKS * BLOCKS {
        let (lo, hi) = block_box(k);
        all.near(lo, hi, slack.widen(farthest(mesh, lo, hi, hint)), &mut near);
        first[k + 1] = near.len();
        let p = lattice(
            2 * (k % BLOCKS) + 1,
            2 * (k / BLOCKS % BLOCKS) + 1,
            2 * (k / (BLOCKS * BLOCKS)) + 1,
        );
        let c = sample(
            mesh,
            p,
            &all,
            &near[first[k]..],
            distance2(mesh, p, hint),
            &slack,
        );
        hint = c.1;
        centre[k] = c;
        let d = c.0[0];
        if d.abs() - half > grid.reach {
            far[k] = if d < 0.0 { -1 } else { 1 };
        }
    }
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
    for (k, &(c, tri)) in centre.iter().enumerate() {
        if far[k] != 0 {
            continue;
        }
        let near = &near[first[k]..first[k + 1]];
        let (bx, by, bz) = (
            2 * (k % BLOCKS),
            2 * (k / BLOCKS % BLOCKS),
            2 * (k / (BLOCKS * BLOCKS)),
        );
        let mut hint = tri;
        for z in bz..=bz + 2 {
            for y in by..=by + 2 {
                for x in bx..=bx + 2 {
                    let s = x + SIDE * (y + SIDE * z);
                    if owner[s] as usize != k {
                        continue;
                    }
                    if (x, y, z) == (bx + 1, by + 1, bz + 1) {
                        out[s] = c;
                        continue;
                    }
                    let p = lattice(x, y, z);
                    let (v, i) = sample(mesh, p, &all, near, distance2(mesh, p, hint), &slack);
                    out[s] = v;
                    hint = i;
                }
            }
        }
    }

    out
}
