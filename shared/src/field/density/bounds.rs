//! Where the density can be non-zero: [`Density::support`] (a box) and
//! [`Density::support_ball`], the bounds the marcher skips empty space by.
//! Each warp bounds its own displacement ([`super::dmf::WarpDmf::scale_range`],
//! [`super::dmf::WarpDmf::preimage`]).

use glam::Vec3;

use super::{Density, Hypertexture};
use crate::field::distortion::Distortion;
use crate::field::domain::{Aabb, Support, hull};
use crate::field::motion::Pose;

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

impl Density {
    /// The largest displacement any distortion in the tree can cause (nested
    /// distortions add up): a ray marcher may treat everything further than
    /// this from the undistorted objects as empty.
    pub fn max_displacement(&self) -> f32 {
        match self {
            Density::Sphere(_)
            | Density::Box(_)
            | Density::Torus(_)
            | Density::Mesh(_)
            | Density::Expression(_) => 0.0,
            Density::Union(v) | Density::Intersection(v) | Density::Max(v) | Density::Min(v) => {
                v.iter().map(Density::max_displacement).fold(0.0, f32::max)
            }
            Density::Difference(a, b) => a.max_displacement().max(b.max_displacement()),
            Density::Complement(a) | Density::Moving(a) => a.max_displacement(),
            Density::Hypertexture(h) => {
                h.distortion().map_or(0.0, Distortion::max_displacement)
                    + h.object().max_displacement()
            }
        }
    }
}
