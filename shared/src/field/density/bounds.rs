//! Where the density can be non-zero: [`Density::support`] (a box) and
//! [`Density::support_ball`], the bounds the marcher skips empty space by.
//! Each warp bounds its own displacement ([`super::dmf::WarpDmf::scale_range`],
//! [`super::dmf::WarpDmf::preimage`]).

use glam::Vec3;

use super::{Density, Hypertexture};
use crate::field::motion::Pose;

/// An axis-aligned box `(min, max)`.
pub type Aabb = (Vec3, Vec3);

/// Where the density can be non-zero, as the marcher uses it: a box and,
/// where one is known, a ball (see [`Density::support_ball`]).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Support {
    /// The box of [`Density::support`].
    pub aabb: Aabb,
    /// The ball of [`Density::support_ball`] `(centre, radius)`.
    pub ball: Option<(Vec3, f32)>,
}

/// A bound on |noise| that holds for every seed, √(3/4) widened by 1% for
/// rounding. With W_c = ω(u_c)ω(v_c)ω(w_c) the weight and d_c the offset of
/// corner c (the weights are ≥ 0 and sum to 1: ω(t) + ω(1 − t) = 1 on each
/// axis) and |Γ_c| = 1:
/// |noise| ≤ Σ W_c |Γ_c·d_c| ≤ Σ W_c |d_c| ≤ √(Σ W_c |d_c|²) (Jensen)
/// = √(g(u) + g(v) + g(w)) with g(t) = ω(t)t² + ω(1 − t)(1 − t)², and
/// g(t) − ¼ = (2t − 1)²((2t − 1)² − 2)/4 ≤ 0 on [0, 1].
pub const NOISE_BOUND: f32 = 0.875;

pub(super) fn hull(a: Aabb, b: Aabb) -> Aabb {
    (a.0.min(b.0), a.1.max(b.1))
}

/// The points x whose scaling about `centre` by some factor in `[lo, hi]` lands
/// in `b` (lo > 0): each coordinate is linear in 1/s, so the ends bound it.
pub(super) fn unscale(b: Aabb, centre: Vec3, lo: f32, hi: f32, axes: Vec3) -> Option<Aabb> {
    if !(lo > 0.0 && hi.is_finite()) {
        return None;
    }
    let scaled = |s: f32| {
        let k = Vec3::ONE + axes * (1.0 / s - 1.0);
        let (p, q) = (centre + (b.0 - centre) * k, centre + (b.1 - centre) * k);
        (p.min(q), p.max(q))
    };
    Some(hull(scaled(lo), scaled(hi)))
}

impl Pose {
    /// The object-space support `s` where the pose puts it: a world box around
    /// the turned box, and the ball moved (its radius a little larger for
    /// rounding).
    pub fn world_support(&self, s: Support) -> Support {
        Support {
            aabb: self.world_box(s.aabb),
            ball: s.ball.map(|(centre, r)| {
                let c = self.to_world(centre);
                (c, r * (1.0 + 1e-5) + 1e-5 * c.abs().max_element())
            }),
        }
    }
}

impl Density {
    /// A box outside which the density is 0 for certain, or `None` when it may
    /// be non-zero anywhere (a complement). The marcher skips samples outside it.
    pub fn support(&self) -> Option<Aabb> {
        let all = |v: &[Density], join: fn(Aabb, Aabb) -> Aabb| {
            v.iter()
                .map(Density::support)
                .try_fold(None, |acc: Option<Aabb>, s| {
                    let s = s?;
                    Some(Some(acc.map_or(s, |a| join(a, s))))
                })
                .flatten()
        };
        let meet_known = |v: &[Density]| {
            v.iter()
                .filter_map(Density::support)
                .reduce(|a, b| (a.0.max(b.0), a.1.min(b.1)))
        };
        match self {
            Density::Sphere(s) => Some((
                s.centre - Vec3::splat(s.falloff.outer()),
                s.centre + Vec3::splat(s.falloff.outer()),
            )),
            Density::Box(b) => {
                let h = Vec3::new(
                    b.falloff[0].outer(),
                    b.falloff[1].outer(),
                    b.falloff[2].outer(),
                );
                Some((b.centre - h, b.centre + h))
            }
            Density::Torus(t) => {
                let a = t.axis;
                let r = t.falloff.outer();
                let across = (Vec3::ONE - a * a).max(Vec3::ZERO);
                let across = Vec3::new(across.x.sqrt(), across.y.sqrt(), across.z.sqrt());
                let reach = across * t.major_radius + Vec3::splat(r);
                Some((t.centre - reach, t.centre + reach))
            }
            Density::Mesh(m) => Some(m.support()),
            Density::Union(v) | Density::Max(v) => all(v, hull),
            Density::Intersection(v) | Density::Min(v) => meet_known(v),
            Density::Difference(a, _) => a.support(),
            // A complement may be non-zero anywhere.
            Density::Complement(_) => None,
            Density::Expression(p) => p.support(),
            // In object space: the field maps it to the world of each moment.
            Density::Moving(d) => d.support(),
            Density::Hypertexture(h) => h.support(),
        }
    }
}

impl Density {
    /// A ball `(centre, radius)` outside which the density is 0 for certain,
    /// where one is known: around soft spheres and tori and the radial warps
    /// of them (the gallery's noisy, fractal and fiery spheres, the furry
    /// donut), tighter than the box of [`Density::support`] (the marcher skips
    /// what lies outside either).
    pub fn support_ball(&self) -> Option<(Vec3, f32)> {
        match self {
            Density::Sphere(s) => Some((s.centre, s.falloff.outer())),
            Density::Torus(t) => Some((t.centre, t.major_radius + t.falloff.outer())),
            Density::Intersection(v) | Density::Min(v) => v.iter().find_map(Density::support_ball),
            Density::Difference(a, _) => a.support_ball(),
            Density::Hypertexture(h) => h.support_ball(),
            // In object space, like `support`.
            Density::Moving(d) => d.support_ball(),
            Density::Expression(p) => p.support_ball(),
            _ => None,
        }
    }
}

impl Hypertexture {
    /// [`Density::support_ball`]: the object's, widened by the distortion's
    /// largest displacement and pulled back through the warps that scale about
    /// its centre (x is evaluated at c + (x − c)·s, s ≥ lo > 0, so |x − c| ≤ r / lo).
    fn support_ball(&self) -> Option<(Vec3, f32)> {
        let (centre, mut r) = self.object.support_ball()?;
        if let Some(d) = &self.distortion {
            r += d.max_displacement();
        }
        for w in self.warps.iter().rev() {
            let (about, lo, _) = w.scale_range()?;
            if about != centre || lo.is_nan() || lo <= 0.0 {
                return None;
            }
            r /= lo;
        }
        r.is_finite().then_some((centre, r))
    }

    /// [`Density::support`]: the object's, widened by the distortion's largest
    /// displacement and pulled back through the warps.
    pub fn support(&self) -> Option<Aabb> {
        let mut b = self.object.support()?;
        if let Some(d) = &self.distortion {
            // x is evaluated at x − k·V/|V| with |k| ≤ the largest displacement.
            let reach = Vec3::splat(d.max_displacement());
            b = (b.0 - reach, b.1 + reach);
        }
        for w in self.warps.iter().rev() {
            b = w.preimage(b)?;
        }
        Some(b)
    }
}
