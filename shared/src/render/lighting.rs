//! Gilet & Dischler's shading options (section 5, Figure 11): the density gradient
//! by central differences, and self-shadowing by a secondary ray marched towards
//! each light.

use glam::Vec3;

use crate::field::domain::{Field, Points};
use crate::field::shaping::clamp01;
use crate::math::simd::LANES;
use crate::scene::Scene;
use crate::scene::camera::{Ray, slab};

/// The unit outward normal at x from central differences of the density along x,
/// y and z with spacing `h` on either side (six evaluations), or `None` where the
/// gradient vanishes.
#[inline]
pub fn central_normal(f_at: &impl Fn(Vec3) -> f32, x: Vec3, h: f32) -> Option<Vec3> {
    let g = Vec3::new(
        f_at(x + Vec3::X * h) - f_at(x - Vec3::X * h),
        f_at(x + Vec3::Y * h) - f_at(x - Vec3::Y * h),
        f_at(x + Vec3::Z * h) - f_at(x - Vec3::Z * h),
    );
    let len2 = g.length_squared();
    (len2 > 1e-30).then(|| -g / len2.sqrt())
}

/// The opacity of one marching step of material of density `f`: the opacity
/// transfer function (`alpha_map`, default the identity) turned into
/// `α = 1 − (1 − ρ)^(c · step)`, exactly as the primary ray composites.
#[inline]
pub fn step_opacity(scene: &Scene, f: f32) -> f32 {
    let rho = clamp01(scene.alpha_map.as_ref().map_or(f, |m| m.eval1(f)));
    1.0 - libm::powf(1.0 - rho, scene.opacity_exponent)
}

/// The fraction of light that reaches x (of unit outward normal n) from direction
/// `to_light` (unit) over `distance` (infinite for a directional light): the
/// product of `1 − α` over a secondary ray marched to where it leaves the bounds
/// or reaches the light. The ray starts two steps out along the normal, so that
/// the material of the sample itself (an opaque iso-surface is hit up to a step
/// deep) does not shadow it. Stops once less than `1 − threshold` gets through.
pub fn transmittance(
    scene: &Scene,
    field: &Field,
    x: Vec3,
    n: Vec3,
    to_light: Vec3,
    distance: f32,
) -> f32 {
    let ray = Ray {
        origin: x + n * (2.0 * scene.step),
        direction: to_light,
    };
    let (min, max) = scene.bounds;
    let Some((_, exit)) = slab(&ray, min, max) else {
        return 1.0;
    };
    let end = exit.min(distance);
    let floor = 1.0 - scene.threshold;
    let mut through = 1.0f32;
    // The samples are evaluated [`LANES`] at a time in the lane code (the
    // scalar bits); those past the end at a point outside the support.
    let spare = field.support.map(|s| s.aabb.1 + Vec3::ONE);
    let mut k: u32 = 1;
    loop {
        let mut x = Points::default();
        for l in 0..LANES {
            let t = (k + l as u32) as f32 * scene.step;
            x.set(
                l,
                match spare {
                    Some(o) if t > end => o,
                    _ => ray.at(t),
                },
            );
        }
        let f = scene.density.eval_lanes(&x, field, scene.isa);
        for f in f {
            let t = k as f32 * scene.step;
            if t > end {
                return through;
            }
            if f > 0.0 {
                through *= 1.0 - step_opacity(scene, f);
                if through <= floor {
                    return through;
                }
            }
            k += 1;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn central_differences_of_a_linear_field_are_exact() {
        // f = 0.5 − 0.1·(x + 2y − 2z): gradient ∝ (1, 2, −2), normal = −gradient/|…|.
        let f = |p: Vec3| 0.5 - 0.1 * (p.x + 2.0 * p.y - 2.0 * p.z);
        let n = central_normal(&f, Vec3::new(0.1, 0.2, 0.3), 0.01).unwrap();
        let expected = Vec3::new(1.0, 2.0, -2.0) / 3.0;
        assert!((n - expected).length() < 1e-4, "{n:?}");
        assert_eq!(central_normal(&|_| 0.5, Vec3::ZERO, 0.01), None);
    }

    fn scene(shadows: bool) -> Scene {
        let text = format!(
            "Scene(image: (width: 8, height: 8),
              camera: (eye: (0.0, 0.0, 5.0), look_at: (0.0, 0.0, 0.0), projection: Perspective(fov_y: 30.0)),
              march: (bounds: (min: (-2.0, -2.0, -2.0), max: (2.0, 2.0, 2.0)), step: Length(0.02), opacity: 20.0),
              object: Sphere(radius: 1.0, softness: 0.2),
              shading: (shadows: {shadows}))"
        );
        Scene::from_text(&text, "test", crate::Overrides::default()).unwrap()
    }

    #[test]
    fn a_sphere_shadows_what_lies_behind_it() {
        let s = scene(true);
        let field = s.field(0);
        // Below the sphere, looking up at the light through it: dark.
        let behind = transmittance(
            &s,
            &field,
            Vec3::new(0.0, -1.5, 0.0),
            Vec3::ZERO,
            Vec3::Y,
            f32::INFINITY,
        );
        assert!(behind < 0.02, "{behind}");
        // Beside it, looking up: nothing in the way.
        let beside = transmittance(
            &s,
            &field,
            Vec3::new(1.5, -1.5, 0.0),
            Vec3::ZERO,
            Vec3::Y,
            f32::INFINITY,
        );
        assert_eq!(beside, 1.0);
        // A point light between the point and the sphere casts no shadow.
        let short = transmittance(
            &s,
            &field,
            Vec3::new(0.0, -1.9, 0.0),
            Vec3::ZERO,
            Vec3::Y,
            0.5,
        );
        assert_eq!(short, 1.0);
    }
}
