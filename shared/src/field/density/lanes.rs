//! The density at [`LANES`] points at once: [`Density::eval_lanes`], the same
//! bits lane by lane as [`Density::eval`], with the noise and the powers
//! computed a batch at a time. On a SIMD path the whole tree below a
//! `#[target_feature]` copy (`x86` below) is `#[inline(always)]`: the
//! primitives, the warps and value DMFs' lane forms ([`super::dmf`]), noise
//! and `pow01`, so the lanes stay in that instruction set's registers; only a
//! non-primitive child node is a call.

use glam::Vec3;

use super::dmf::{InnerSurface, Settling};
use super::{Density, Hypertexture};
use crate::field::domain::{Field, Points, zip};
use crate::field::motion::Pose;
use crate::field::soft::{Falloff, ProjectBlock, SoftMesh, boolean};
use crate::math::dual::DualPoint;
use crate::math::simd::{Isa, LANES, Lanes, lane_mask};

/// Every lane's bit.
const ALL_LANES: u32 = if LANES == 32 {
    u32::MAX
} else {
    (1 << LANES) - 1
};

/// `f(point)` lane by lane.
#[inline(always)]
fn each(x: &Points, f: impl Fn(Vec3) -> f32) -> Lanes {
    let mut out = [0.0; LANES];
    for (l, o) in out.iter_mut().enumerate() {
        *o = f(x.get(l));
    }
    out
}

impl Pose {
    /// [`Pose::to_object`] lane by lane (the same bits).
    #[inline]
    pub fn to_object_lanes(&self, p: &Points) -> Points {
        let mut out = Points::default();
        for l in 0..LANES {
            out.set(l, self.to_object(p.get(l)));
        }
        out
    }
}

impl Field<'_> {
    /// `noise` at the points: the lane kernel itself, inlined into the
    /// per-instruction-set copy of [`Density::eval_lanes`] (`isa` is a
    /// constant there).
    #[inline(always)]
    pub(super) fn noise_lanes(&self, p: &Points, isa: Isa) -> Lanes {
        self.noise_lanes_live(p, isa, u32::MAX)
    }

    /// [`Field::noise_lanes`] at the lanes set in `live` (the others come
    /// out as anything).
    #[inline(always)]
    pub(super) fn noise_lanes_live(&self, p: &Points, isa: Isa, live: u32) -> Lanes {
        self.noise.noise_lanes_live(isa, live, &p.x, &p.y, &p.z)
    }

    /// [`Field::noise`] at each point set in `live`, `noise((x − offset) ·
    /// frequency)` (the others come out as anything).
    #[inline(always)]
    pub(super) fn noise_at_live(&self, frequency: f32, x: &Points, isa: Isa, live: u32) -> Lanes {
        self.noise_at_along(frequency, x, isa, live, false)
    }

    /// [`Field::noise_lanes_live`]; `runs`: the points lie along a ray at
    /// a step fine for the frequency ([`crate::field::noise::runs`]).
    #[inline(always)]
    pub(super) fn noise_lanes_along(&self, p: &Points, isa: Isa, live: u32, runs: bool) -> Lanes {
        self.noise
            .noise_lanes_along(isa, live, runs, &p.x, &p.y, &p.z)
    }

    /// [`Field::noise_at_live`]; `runs` as in [`Field::noise_lanes_along`].
    #[inline(always)]
    pub(super) fn noise_at_along(
        &self,
        frequency: f32,
        x: &Points,
        isa: Isa,
        live: u32,
        runs: bool,
    ) -> Lanes {
        self.noise_lanes_along(&x.map(|p| (p - self.offset) * frequency), isa, live, runs)
    }
}

impl Density {
    /// [`Density::project`] at each point.
    #[inline(always)]
    pub(crate) fn project_lanes(&self, x: &Points) -> Points {
        match self {
            Density::Sphere(s) => x.map(|p| s.project(p)),
            Density::Box(b) => x.map(|p| b.project(p)),
            Density::Torus(t) => {
                let mut p = *x;
                t.project_lanes(&mut p.x, &mut p.y, &mut p.z);
                p
            }
            Density::Mesh(m) => {
                let mut p = *x;
                m.project_lanes_live(&mut p.x, &mut p.y, &mut p.z, u32::MAX);
                p
            }
            _ => *x,
        }
    }

    /// [`Density::project_lanes`] in place (the points are not copied: the
    /// fur's hot path), of the lanes set in `live` (bit l for lane l): a
    /// sphere's or a torus's in the blocks of [`crate::math::simd::BLOCK`] lanes
    /// with one live, the other objects' point by point. The other points
    /// are left.
    #[inline(always)]
    pub(crate) fn project_lanes_in_place(&self, x: &mut Points, live: u32) {
        #[inline(always)]
        fn each_live(x: &mut Points, live: u32, project: impl Fn(Vec3) -> Vec3) {
            for l in 0..LANES {
                if live & (1 << l) != 0 {
                    x.set(l, project(x.get(l)));
                }
            }
        }
        match self {
            Density::Sphere(s) => s.project_lanes_live(&mut x.x, &mut x.y, &mut x.z, live),
            Density::Box(b) => each_live(x, live, |p| b.project(p)),
            Density::Torus(t) => t.project_lanes_live(&mut x.x, &mut x.y, &mut x.z, live),
            Density::Mesh(m) => m.project_lanes_live(&mut x.x, &mut x.y, &mut x.z, live),
            _ => {}
        }
    }

    /// [`Density::eval`] at [`LANES`] points: the same bits lane by lane, with
    /// the noise and the powers computed a batch at a time on `isa`.
    #[inline]
    pub fn eval_lanes(&self, x: &Points, field: &Field, isa: Isa) -> Lanes {
        crate::math::simd::per_isa!(isa, (d: &Density = self, x: &Points = x, field: &Field = field) -> Lanes {
            scalar => each(x, |p| d.eval(p, field)),
            lanes => d.eval_lanes_simd(x, field, lanes),
        })
    }

    /// [`Density::eval_object`] (D without the value DMFs) at [`LANES`]
    /// points: the same bits lane by lane. A hypertexture's warps and
    /// distortion and a primitive run on `isa`'s lanes; the other nodes (the
    /// booleans, motion) point by point.
    #[inline]
    pub fn eval_object_lanes(&self, x: &Points, field: &Field, isa: Isa) -> Lanes {
        crate::math::simd::per_isa!(isa, (d: &Density = self, x: &Points = x, field: &Field = field) -> Lanes {
            scalar => each(x, |p| d.eval_object(p, field)),
            lanes => d.eval_object_lanes_simd(x, field, lanes),
        })
    }

    /// [`Density::eval_object_lanes`] on a SIMD path: a hypertexture's warps
    /// and distortion, then its object's D; a boolean of its children's D
    /// (every child, as `eval_object` folds them); a primitive's density.
    #[inline(always)]
    fn eval_object_lanes_simd(&self, x: &Points, field: &Field, isa: Isa) -> Lanes {
        let child = |d: &Density| d.eval_object_lanes(x, field, isa);
        match self {
            Density::Hypertexture(h) => {
                let beyond = h.empty_lanes(x);
                if beyond == ALL_LANES {
                    return [0.0; LANES];
                }
                let mut p = *x;
                for w in &h.warps {
                    p = w.apply_lanes(&p, field, isa);
                }
                if let Some(d) = &h.distortion {
                    p = d.apply_lanes(&p, &h.object, field, isa);
                }
                let mut v = h.object.eval_object_lanes(&p, field, isa);
                for (l, v) in v.iter_mut().enumerate() {
                    if beyond >> l & 1 != 0 {
                        *v = 0.0;
                    }
                }
                v
            }
            Density::Union(v) => v
                .iter()
                .fold([0.0; LANES], |a, d| zip(&a, &child(d), boolean::union)),
            Density::Intersection(v) => v.iter().fold([1.0; LANES], |a, d| {
                zip(&a, &child(d), boolean::intersection)
            }),
            Density::Difference(a, b) => zip(&child(a), &child(b), boolean::difference),
            Density::Complement(a) => child(a).map(boolean::complement),
            Density::Max(v) => v
                .iter()
                .fold([0.0; LANES], |a, d| zip(&a, &child(d), f32::max)),
            Density::Min(v) => v
                .iter()
                .fold([1.0; LANES], |a, d| zip(&a, &child(d), f32::min)),
            Density::Moving(d) => match &field.pose {
                Some(pose) => d.eval_object_lanes(&pose.to_object_lanes(x), field, isa),
                None => child(d),
            },
            _ => self.eval_lanes_simd(x, field, isa),
        }
    }

    /// [`Density::eval_lanes`] on a SIMD path: written once, inlined into a
    /// copy per instruction set (`x86` below) together with everything it
    /// calls but its children, so the lanes stay in that set's registers
    /// from the points to the powers.
    #[inline(always)]
    pub(crate) fn eval_lanes_simd(&self, x: &Points, field: &Field, isa: Isa) -> Lanes {
        match self {
            Density::Sphere(s) => s.density_lanes(&x.x, &x.y, &x.z),
            Density::Box(b) => each(x, |p| b.density(p)),
            Density::Torus(t) => t.density_lanes(&x.x, &x.y, &x.z),
            Density::Mesh(m) => m.density_lanes(&x.x, &x.y, &x.z),
            Density::Expression(program) => program.eval_lanes(x, &[0.0; LANES], field, isa)[0]
                .map(crate::field::shaping::clamp01),
            Density::Union(v) => v.iter().fold([0.0; LANES], |a, d| {
                zip(&a, &d.eval_child(x, field, isa), boolean::union)
            }),
            Density::Intersection(v) => {
                let mut a = [1.0; LANES];
                for d in v {
                    if a.iter().all(|&a| a == 0.0) {
                        break;
                    }
                    let b = d.eval_child(x, field, isa);
                    // A lane that reached 0 stopped there (`eval` breaks out).
                    a = zip(&a, &b, |a, b| {
                        if a == 0.0 {
                            a
                        } else {
                            boolean::intersection(a, b)
                        }
                    });
                }
                a
            }
            Density::Difference(a, b) => {
                let a = a.eval_child(x, field, isa);
                if a.iter().all(|&a| a == 0.0) {
                    return [0.0; LANES];
                }
                let b = b.eval_child(x, field, isa);
                zip(&a, &b, |a, b| {
                    if a == 0.0 {
                        0.0
                    } else {
                        boolean::difference(a, b)
                    }
                })
            }
            Density::Complement(a) => a.eval_child(x, field, isa).map(boolean::complement),
            Density::Max(v) => v.iter().fold([0.0; LANES], |a, d| {
                zip(&a, &d.eval_child(x, field, isa), f32::max)
            }),
            Density::Min(v) => v.iter().fold([1.0; LANES], |a, d| {
                zip(&a, &d.eval_child(x, field, isa), f32::min)
            }),
            Density::Hypertexture(h) => h.eval_lanes_simd(x, field, isa),
            Density::Moving(d) => match &field.pose {
                Some(pose) => d.eval_child(&pose.to_object_lanes(x), field, isa),
                None => d.eval_child(x, field, isa),
            },
        }
    }
}

impl Density {
    /// A child's lanes inside [`Density::eval_lanes_simd`]: the primitives
    /// inline, the rest through [`Density::eval_lanes`].
    #[inline(always)]
    fn eval_child(&self, x: &Points, field: &Field, isa: Isa) -> Lanes {
        match self {
            Density::Sphere(s) => s.density_lanes(&x.x, &x.y, &x.z),
            Density::Torus(t) => t.density_lanes(&x.x, &x.y, &x.z),
            _ => self.eval_lanes(x, field, isa),
        }
    }
}

/// A mesh's inner surface with its field's samples at the points `at`:
/// the projection of those points is read from them ([`SoftMesh::project_sampled`]),
/// of any others from the field again (the same bits).
struct SampledMesh<'a> {
    object: &'a Density,
    mesh: &'a SoftMesh,
    at: Points,
    sample: crate::mesh::SampleLanes,
}

impl InnerSurface for SampledMesh<'_> {
    #[inline(always)]
    fn project(&self, x: Vec3) -> Vec3 {
        self.object.project(x)
    }

    #[inline(always)]
    fn project_dual(&self, x: &DualPoint) -> DualPoint {
        InnerSurface::project_dual(self.object, x)
    }

    #[inline(always)]
    fn project_lanes_in_place(&self, x: &mut Points, live: u32) {
        let bits = |p: &Points| [p.x, p.y, p.z].map(|a| a.map(f32::to_bits));
        if bits(x) == bits(&self.at) {
            self.mesh
                .project_sampled(&mut x.x, &mut x.y, &mut x.z, live, &self.sample);
        } else {
            self.object.project_lanes_in_place(x, live);
        }
    }
}

/// A soft sphere's D at `c + (x − c)·s`, settled when the squared distances
/// `d2 = |x − c|²` scaled by every s of the range give one value.
struct SettlingSphere<'a> {
    d2: Lanes,
    falloff: &'a Falloff,
    /// Whether D = 1 counts as settled (the hard region is solid).
    hard: bool,
}

impl Settling for SettlingSphere<'_> {
    #[inline(always)]
    fn settled(&self, lo: &Lanes, hi: &Lanes) -> u32 {
        lane_mask(|l| self.falloff.settled(self.d2[l], lo[l], hi[l], self.hard))
    }
}

impl Hypertexture {
    /// The points where D is evaluated: x under the warps and the distortion.
    /// A sphere under one warp that scales about its centre (the noisy,
    /// fractal and fiery spheres) lets the warp's octaves stop at the lanes
    /// whose D is settled: 0 whatever the octaves left add, or 1 in a solid
    /// hard region (H keeps both), so such a lane's point may differ from
    /// `eval`'s but never its D nor H.
    #[inline(always)]
    fn warped_lanes(&self, x: &Points, field: &Field, isa: Isa) -> Points {
        if let (true, [w], None, Density::Sphere(sphere)) = (
            self.settles,
            self.warps.as_slice(),
            &self.distortion,
            &self.object,
        ) {
            let c = sphere.centre;
            let settling = SettlingSphere {
                d2: each(x, |p| (p - c).length_squared()),
                falloff: &sphere.falloff,
                hard: self.solid_core,
            };
            return w.apply_lanes_settling(x, field, isa, &settling);
        }
        let mut p = *x;
        for w in &self.warps {
            p = w.apply_lanes(&p, field, isa);
        }
        if let Some(d) = &self.distortion {
            p = d.apply_lanes(&p, &self.object, field, isa);
        }
        p
    }

    /// [`Hypertexture::eval`] at [`LANES`] points on a SIMD path (see
    /// [`Density::eval_lanes_simd`]).
    #[inline(always)]
    fn eval_lanes_simd(&self, x: &Points, field: &Field, isa: Isa) -> Lanes {
        // Without a distortion (and so, with `empty_beyond`, at x itself) a
        // lane beyond the band is one the field's samples put outside: D is
        // +0 there, and H keeps it, so the slots are found once, below.
        let beyond = if self.distortion.is_some() {
            self.empty_lanes(x)
        } else {
            0
        };
        if beyond == ALL_LANES {
            return [0.0; LANES];
        }
        let mut v = self.eval_lanes_near(x, field, isa);
        for (l, v) in v.iter_mut().enumerate() {
            if beyond >> l & 1 != 0 {
                *v = 0.0;
            }
        }
        v
    }

    /// Bit l: H is 0 at lane l's point for certain ([`Hypertexture::empty_at`]).
    #[inline(always)]
    pub(super) fn empty_lanes(&self, x: &Points) -> u32 {
        match &self.object {
            Density::Mesh(m) if self.empty_beyond => m.beyond_lanes(&x.x, &x.y, &x.z),
            _ => 0,
        }
    }

    /// [`Hypertexture::eval_lanes_simd`] without the test for empty space.
    #[inline(always)]
    fn eval_lanes_near(&self, x: &Points, field: &Field, isa: Isa) -> Lanes {
        let p = self.warped_lanes(x, field, isa);
        // A mesh's field is read once for D and for the projection.
        if let Density::Mesh(mesh) = &self.object
            && let Some(sample) = mesh.sample_lanes(&p.x, &p.y, &p.z)
        {
            let d = mesh.density_sampled(&p.x, &p.y, &p.z, &sample);
            let sampled = SampledMesh {
                object: &self.object,
                mesh,
                at: p,
                sample,
            };
            return self.modulate_lanes(d, &p, &sampled, field, isa);
        }
        let d = self.object.eval_child(&p, field, isa);
        self.modulate_lanes(d, &p, &self.object, field, isa)
    }

    /// The value DMFs at the lanes' points `p` (under the warps and the
    /// distortion) of D = `d`, reading `object`'s inner surface.
    #[inline(always)]
    fn modulate_lanes(
        &self,
        d: Lanes,
        p: &Points,
        object: &impl InnerSurface,
        field: &Field,
        isa: Isa,
    ) -> Lanes {
        // Lanes at D = 0, or in the solid hard region, keep D (as `eval`).
        let kept = d.map(|d| self.keeps(d));
        if kept.iter().all(|&k| k) {
            return d;
        }
        // Only the other lanes' modulation is used (below): the noise
        // kernels skip a register's worth of kept lanes.
        let live = (0..LANES).fold(0u32, |m, l| m | (u32::from(!kept[l]) << l));
        let mut v = d;
        for m in &self.modulation {
            if v.iter().all(|&v| v == 0.0) {
                break;
            }
            let next = m.apply_lanes(&v, p, object, field, isa, live);
            // A lane at 0 stopped there (`eval` breaks out: every DMF keeps 0).
            v = zip(&v, &next, |v, n| if v == 0.0 { v } else { n });
        }
        for l in 0..v.len() {
            if kept[l] {
                v[l] = d[l];
            }
        }
        v
    }
}
