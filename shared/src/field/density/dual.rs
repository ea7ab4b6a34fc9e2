//! The density tree differentiated ([`crate::math::dual`]): [`Density::eval_dual`],
//! the density and its gradient with respect to the world point in one pass.
//! Each DMF's dual form is in its own file of [`super::dmf`].

use super::{Density, Hypertexture};
use crate::field::domain::Field;
use crate::math::dual::{Dual, DualPoint};

/// The tree differentiated ([`crate::math::dual`]): the density and its gradient with
/// respect to the world point in one pass. `h` is the spacing of the central
/// differences of the parts without a derivative written out (the distortion
/// and expressions).
impl Density {
    /// [`Density::eval`] at `x` with its gradient.
    pub fn eval_dual(&self, x: &DualPoint, field: &Field, h: f32) -> Dual {
        match self {
            Density::Sphere(s) => s.density_dual(x),
            Density::Box(b) => b.density_dual(x),
            Density::Torus(t) => t.density_dual(x),
            // No derivative written out: central differences, as expressions.
            Density::Mesh(m) => x.apply(h, |p| m.density(p)),
            Density::Union(v) => v.iter().fold(Dual::constant(0.0), |a, d| {
                let b = d.eval_dual(x, field, h);
                a + b - a * b
            }),
            Density::Intersection(v) => {
                let mut a = Dual::constant(1.0);
                for d in v {
                    a = a * d.eval_dual(x, field, h);
                    if a.v == 0.0 {
                        break;
                    }
                }
                a
            }
            Density::Difference(a, b) => {
                let a = a.eval_dual(x, field, h);
                if a.v == 0.0 {
                    return Dual::constant(0.0);
                }
                a - a * b.eval_dual(x, field, h)
            }
            Density::Complement(a) => -a.eval_dual(x, field, h) + 1.0,
            Density::Max(v) => v
                .iter()
                .fold(Dual::constant(0.0), |a, d| a.max(d.eval_dual(x, field, h))),
            Density::Min(v) => v
                .iter()
                .fold(Dual::constant(1.0), |a, d| a.min(d.eval_dual(x, field, h))),
            Density::Hypertexture(t) => t.eval_dual(x, field, h),
            Density::Expression(_) => x.apply(h, |p| self.eval(p, field)).clamp01(),
            Density::Moving(d) => match &field.pose {
                Some(pose) => d.eval_dual(&pose.to_object_dual(x), field, h),
                None => d.eval_dual(x, field, h),
            },
        }
    }

    /// [`Density::project`] with its Jacobian.
    #[inline]
    pub(super) fn project_dual(&self, x: &DualPoint) -> DualPoint {
        match self {
            Density::Sphere(s) => s.project_dual(x),
            Density::Box(b) => b.project_dual(x),
            Density::Torus(t) => t.project_dual(x),
            // Central differences over a thousandth of a unit (the mesh's
            // projection has no derivative written out).
            Density::Mesh(m) => DualPoint {
                x: x.apply(1e-3, |p| m.project(p).x),
                y: x.apply(1e-3, |p| m.project(p).y),
                z: x.apply(1e-3, |p| m.project(p).z),
            },
            _ => *x,
        }
    }
}

impl Hypertexture {
    /// [`Hypertexture::eval`] with its gradient.
    fn eval_dual(&self, x: &DualPoint, field: &Field, h: f32) -> Dual {
        let mut p = *x;
        for w in &self.warps {
            p = w.apply_dual(&p, field);
        }
        if let Some(d) = &self.distortion {
            p = p.through(h, |q| d.apply(q, &self.object, field));
        }
        let mut v = self.object.eval_dual(&p, field, h);
        if self.keeps(v.v) {
            return v;
        }
        for m in &self.modulation {
            if v.v == 0.0 {
                break; // every value DMF maps 0 to 0
            }
            v = m.apply_dual(v, &p, &self.object, field);
        }
        v
    }
}

impl Field<'_> {
    /// [`Field::noise`] with its gradient.
    #[inline]
    pub(super) fn noise_dual(&self, frequency: f32, x: &DualPoint) -> Dual {
        self.noise
            .noise_dual(&x.offset(-self.offset).times(frequency))
    }
}
