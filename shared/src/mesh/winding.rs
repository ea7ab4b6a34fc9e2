//! The generalized winding number of a triangle mesh (Jacobson, Kavan &
//! Sorkine-Hornung, "Robust inside-outside segmentation using generalized
//! winding numbers", SIGGRAPH 2013): the signed solid angle the triangles
//! subtend at a point, over 4π. It is 1 inside a closed, outward-oriented
//! surface and 0 outside; on a mesh that is open, self-intersecting or made
//! of several parts it still varies smoothly away from the triangles, and
//! `w ≥ ½` is inside.
//!
//! Made fast with Barill, Dickson, Schmidt, Levin & Jacobson's tree ("Fast
//! winding numbers for soups and clouds", SIGGRAPH 2018): every node of the
//! mesh's BVH holds the Taylor expansion of its triangles' dipoles about their
//! area-weighted centroid p̃, to second order: the area-weighted normal
//! N = Σ aₜnₜ, the first moment Mᵢⱼ = Σ nₜᵢ ∫(x − p̃)ⱼ dA and the second
//! Tᵢⱼₖ = Σ nₜᵢ ∫(x − p̃)ⱼ(x − p̃)ₖ dA over each triangle t. A node whose
//! triangles all lie within r of p̃, seen from q with |p̃ − q| > β r,
//! contributes, with g(x) = x / |x|³ and r = p̃ − q,
//!
//! ```text
//! 4π w = Nᵢ gᵢ(r) + Mᵢⱼ ∂ⱼgᵢ(r) + ½ Tᵢⱼₖ ∂ⱼ∂ₖgᵢ(r)
//! ```
//!
//! and every other node is opened, down to the leaves, whose triangles add
//! their exact solid angles (Van Oosterom & Strackee, IEEE TBME 1983).
//!
//! The expansions are summed in f64 from the leaves up in a fixed order, and a
//! query walks the tree in a fixed order on one thread: the same mesh gives
//! the same bits for every query, whatever the thread count.

use glam::{DMat3, DVec3, Vec3};

use super::bvh::{Bvh, Content};

/// Nodes closer than β times their radius are opened (Barill et al.'s
/// accuracy parameter; 2 is their choice).
pub(super) const BETA: f32 = 2.0;

/// The deepest walk: a median-split tree of any allowed size is far
/// shallower, and each level leaves at most one node waiting.
const STACK: usize = 128;

/// The six entries of a symmetric 3×3 matrix: xx, xy, xz, yy, yz, zz.
type Sym = [f32; 6];

/// A node's expansion.
#[derive(Clone, Copy, Debug, PartialEq)]
struct Expansion {
    /// The area-weighted centroid p̃ of the node's triangles.
    centre: Vec3,
    /// β² r², r the distance from p̃ to the farthest corner.
    far2: f32,
    /// N = Σ aₜnₜ (half the sum of the triangles' cross products).
    normal: Vec3,
    /// M by rows: Mᵢⱼ = Σ aₜ nₜᵢ (cₜ − p̃)ⱼ, cₜ the triangle's centroid.
    moment: [Vec3; 3],
    /// T by its first index: Tᵢ = Σ nₜᵢ ∫(x − p̃)(x − p̃)ᵀ dA.
    second: [Sym; 3],
}

/// The expansions of every node of a BVH.
#[derive(Clone, Debug, PartialEq)]
pub(super) struct WindingTree {
    nodes: Vec<Expansion>,
}

/// Sums kept while building, about the origin: area, area-weighted
/// centroid, N, Σ aₜnₜ ⊗ cₜ (by rows), and Σ nₜᵢ ∫x xᵀ dA.
#[derive(Clone, Copy, Default)]
struct Sums {
    area: f64,
    centroid: DVec3,
    normal: DVec3,
    moment: [DVec3; 3],
    second: [DMat3; 3],
}

impl Sums {
    fn of(t: &[Vec3; 3]) -> Sums {
        let [a, b, c] = t.map(|v| v.as_dvec3());
        let normal = (b - a).cross(c - a) * 0.5;
        let centre = (a + b + c) / 3.0;
        let area = normal.length();
        // ∫ x xᵀ dA over a triangle, over its area: (Σ vvᵀ + 9 c cᵀ) / 12.
        let outer = |v: DVec3| DMat3::from_cols(v * v.x, v * v.y, v * v.z);
        let inertia = (outer(a) + outer(b) + outer(c) + outer(centre) * 9.0) * (1.0 / 12.0);
        Sums {
            area,
            centroid: centre * area,
            normal,
            moment: [0, 1, 2].map(|i| centre * normal[i]),
            second: [0, 1, 2].map(|i| inertia * normal[i]),
        }
    }

    fn add(self, o: Sums) -> Sums {
        Sums {
            area: self.area + o.area,
            centroid: self.centroid + o.centroid,
            normal: self.normal + o.normal,
            moment: [0, 1, 2].map(|i| self.moment[i] + o.moment[i]),
            second: [0, 1, 2].map(|i| self.second[i] + o.second[i]),
        }
    }

    /// The expansion about `p` (within `radius` of every corner).
    fn about(&self, p: DVec3, radius: f64) -> Expansion {
        let far = f64::from(BETA) * radius;
        Expansion {
            centre: p.as_vec3(),
            far2: (far * far) as f32,
            normal: self.normal.as_vec3(),
            // Σ aₙ ⊗ (c − p) = Σ aₙ ⊗ c − N ⊗ p.
            moment: [0, 1, 2].map(|i| (self.moment[i] - p * self.normal[i]).as_vec3()),
            // Σ nᵢ ∫(x − p)(x − p)ᵀ = Σ nᵢ ∫xxᵀ − m pᵀ − p mᵀ + Nᵢ p pᵀ, mᵢ = Σ aₙᵢ c.
            second: [0, 1, 2].map(|i| {
                let m = self.moment[i];
                let t = self.second[i];
                let e = |j: usize, k: usize| {
                    (t.col(k)[j] - m[j] * p[k] - p[j] * m[k] + self.normal[i] * p[j] * p[k]) as f32
                };
                [e(0, 0), e(0, 1), e(0, 2), e(1, 1), e(1, 2), e(2, 2)]
            }),
        }
    }
}

impl WindingTree {
    /// The expansions of `bvh`'s nodes over the triangles whose corners
    /// `corners` gives by their index in the tree's order.
    pub(super) fn build(bvh: &Bvh, corners: impl Fn(usize) -> [Vec3; 3]) -> WindingTree {
        let mut sums = vec![Sums::default(); bvh.len()];
        let mut centres = vec![DVec3::ZERO; bvh.len()];
        let mut nodes = Vec::with_capacity(bvh.len());
        // Children come after their parent: going down the indices sums each
        // node from finished children.
        for i in (0..bvh.len()).rev() {
            sums[i] = match bvh.content(i) {
                Content::Leaf(range) => {
                    range.fold(Sums::default(), |s, t| s.add(Sums::of(&corners(t))))
                }
                Content::Inner(a, b) => sums[a].add(sums[b]),
            };
            let s = &sums[i];
            let (lo, hi) = bvh.bounds(i);
            centres[i] = if s.area > 0.0 {
                s.centroid / s.area
            } else {
                ((lo + hi) * 0.5).as_dvec3()
            };
        }
        for (i, s) in sums.iter().enumerate() {
            let p = centres[i];
            let radius = match bvh.content(i) {
                Content::Leaf(range) => range
                    .flat_map(&corners)
                    .map(|v| (v.as_dvec3() - p).length())
                    .fold(0.0, f64::max),
                // The box holds every corner below the node.
                Content::Inner(..) => {
                    let (lo, hi) = bvh.bounds(i);
                    (lo.as_dvec3() - p)
                        .abs()
                        .max((hi.as_dvec3() - p).abs())
                        .length()
                }
            };
            nodes.push(s.about(p, radius));
        }
        WindingTree { nodes }
    }

    /// The bytes of its expansions.
    pub(super) fn memory_bytes(&self) -> usize {
        self.nodes.capacity() * std::mem::size_of::<Expansion>()
    }

    /// The winding number at `q` of the triangles whose corners `corners`
    /// gives (by index in the tree's order, counter-clockwise seen from
    /// outside).
    #[inline]
    pub(super) fn winding_number(
        &self,
        bvh: &Bvh,
        corners: impl Fn(usize) -> [Vec3; 3],
        q: Vec3,
    ) -> f32 {
        let mut sum = 0.0f64;
        let mut stack = [0usize; STACK];
        let mut top = 1;
        while top > 0 {
            top -= 1;
            let i = stack[top];
            let e = &self.nodes[i];
            let r = e.centre - q;
            let d2 = r.length_squared();
            if d2 > e.far2 {
                sum += f64::from(dipole(e, r, d2));
                continue;
            }
            match bvh.content(i) {
                Content::Leaf(range) => {
                    for t in range {
                        sum += solid_angle(&corners(t), q);
                    }
                }
                Content::Inner(a, b) => {
                    stack[top] = b;
                    stack[top + 1] = a;
                    top += 2;
                }
            }
        }
        (sum / (4.0 * std::f64::consts::PI)) as f32
    }

    /// The winding number at `q` summed over every triangle exactly: the
    /// reference the tree's far-field answer is measured against.
    #[cfg(test)]
    pub(super) fn exact(triangles: &[[Vec3; 3]], q: Vec3) -> f32 {
        let sum: f64 = triangles.iter().map(|t| solid_angle(t, q)).sum();
        (sum / (4.0 * std::f64::consts::PI)) as f32
    }
}

/// A node's far-field contribution, times 4π, at q = p̃ − r (d2 = |r|²).
#[inline]
fn dipole(e: &Expansion, r: Vec3, d2: f32) -> f32 {
    let d = d2.sqrt();
    let inv3 = 1.0 / (d2 * d);
    let inv5 = inv3 / d2;
    let inv7 = inv5 / d2;
    // Mᵢⱼ ∂ⱼgᵢ = tr M / |r|³ − 3 rᵀMr / |r|⁵.
    let trace = e.moment[0].x + e.moment[1].y + e.moment[2].z;
    let mr = Vec3::new(e.moment[0].dot(r), e.moment[1].dot(r), e.moment[2].dot(r));
    let first = trace * inv3 - 3.0 * r.dot(mr) * inv5;
    // ∂ⱼ∂ₖgᵢ = −3(δᵢₖrⱼ + δᵢⱼrₖ + δⱼₖrᵢ)/|r|⁵ + 15 rᵢrⱼrₖ/|r|⁷, so
    // ½ Tᵢⱼₖ ∂ⱼ∂ₖgᵢ = ½ (−3 (2 u + v)·r / |r|⁵ + 15 Σᵢ rᵢ rᵀTᵢr / |r|⁷),
    // uⱼ = Σᵢ Tᵢᵢⱼ, vᵢ = tr Tᵢ.
    let row = |t: &Sym, k: usize| match k {
        0 => Vec3::new(t[0], t[1], t[2]),
        1 => Vec3::new(t[1], t[3], t[4]),
        _ => Vec3::new(t[2], t[4], t[5]),
    };
    let [t0, t1, t2] = &e.second;
    let u = row(t0, 0) + row(t1, 1) + row(t2, 2);
    let v = Vec3::new(
        t0[0] + t0[3] + t0[5],
        t1[0] + t1[3] + t1[5],
        t2[0] + t2[3] + t2[5],
    );
    let quad = |t: &Sym| {
        r.x * r.x * t[0]
            + r.y * r.y * t[3]
            + r.z * r.z * t[5]
            + 2.0 * (r.x * r.y * t[1] + r.x * r.z * t[2] + r.y * r.z * t[4])
    };
    let rtr = r.x * quad(t0) + r.y * quad(t1) + r.z * quad(t2);
    let second = 0.5 * (-3.0 * (2.0 * u + v).dot(r) * inv5 + 15.0 * rtr * inv7);
    e.normal.dot(r) * inv3 + first + second
}

/// The signed solid angle triangle `t` subtends at `q` (Van Oosterom &
/// Strackee): positive when q lies behind it, on the side its normal
/// (corners counter-clockwise seen from the front) points away from.
#[inline]
fn solid_angle(t: &[Vec3; 3], q: Vec3) -> f64 {
    let [a, b, c] = t.map(|v| (v - q).as_dvec3());
    let (la, lb, lc) = (a.length(), b.length(), c.length());
    let det = a.dot(b.cross(c));
    let div = la * lb * lc + a.dot(b) * lc + b.dot(c) * la + c.dot(a) * lb;
    2.0 * libm::atan2(det, div)
}
