//! The rigid motion of the object. The solid texturing notes warn of
//! "crawling textures": a solid texture evaluated at the world point swims
//! through a moving object. Evaluated at the object-space point, it sticks.
//!
//! A scene's `transform` ([`TransformDesc`]) places the object at every moment;
//! [`Motion::at`] gives the [`Pose`] of one moment (a frame, or a time inside
//! the shutter of motion blur), which takes world points back to object space.
//! The marcher, the lights and the camera stay in world space; only the
//! hypertexture, its colour and its textures see object-space points.
//!
//! Every pose is computed with basic IEEE operations and `libm` in a fixed order,
//! and the same scalar code maps a point alone or in a batch of lanes, so every
//! CPU computes the same bits.

use glam::Vec3;

use crate::desc::TransformDesc;

/// The object's motion over time.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Motion {
    translate: Vec3,
    velocity: Vec3,
    pivot: Vec3,
    axis: Vec3,
    /// Radians at frame 0.
    angle: f32,
    /// Radians per frame.
    spin: f32,
}

/// Where the object is at one moment: the map from world to object space.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Pose {
    /// Rows of R⁻¹ (= the columns of R).
    inverse: [Vec3; 3],
    pivot: Vec3,
    /// `translate + velocity·τ + pivot`.
    shift: Vec3,
}

impl Motion {
    /// The runtime motion of a scene's `transform`.
    pub fn build(desc: &TransformDesc) -> Motion {
        Motion {
            translate: desc.translate.0,
            velocity: desc.velocity.0,
            pivot: desc.pivot.0,
            axis: desc.axis.0,
            angle: desc.angle.0.to_radians(),
            spin: desc.spin.0.to_radians(),
        }
    }

    /// The pose at `time` frames.
    pub fn at(&self, time: f32) -> Pose {
        let theta = self.angle + self.spin * time;
        let (s, c) = (libm::sinf(theta), libm::cosf(theta));
        let k = self.axis;
        let t = 1.0 - c;
        // Rodrigues: R = cI + s[k]× + t·kkᵀ; the rows of R⁻¹ = Rᵀ.
        let inverse = [
            Vec3::new(
                c + t * k.x * k.x,
                t * k.x * k.y + s * k.z,
                t * k.x * k.z - s * k.y,
            ),
            Vec3::new(
                t * k.x * k.y - s * k.z,
                c + t * k.y * k.y,
                t * k.y * k.z + s * k.x,
            ),
            Vec3::new(
                t * k.x * k.z + s * k.y,
                t * k.y * k.z - s * k.x,
                c + t * k.z * k.z,
            ),
        ];
        Pose {
            inverse,
            pivot: self.pivot,
            shift: self.translate + self.velocity * time + self.pivot,
        }
    }
}

/// `a · b`, summed in a fixed order.
#[inline(always)]
fn dot(a: Vec3, b: Vec3) -> f32 {
    a.x * b.x + a.y * b.y + a.z * b.z
}

impl Pose {
    /// The object-space point of the world point `w`.
    #[inline(always)]
    pub fn to_object(&self, w: Vec3) -> Vec3 {
        let q = w - self.shift;
        let [a, b, c] = self.inverse;
        self.pivot + Vec3::new(dot(a, q), dot(b, q), dot(c, q))
    }

    /// [`Pose::to_object`] of a point with its Jacobian.
    #[inline]
    pub fn to_object_dual(&self, w: &crate::math::dual::DualPoint) -> crate::math::dual::DualPoint {
        let q = w.offset(-self.shift);
        let [a, b, c] = self.inverse;
        crate::math::dual::DualPoint {
            x: q.dot(a),
            y: q.dot(b),
            z: q.dot(c),
        }
        .offset(self.pivot)
    }

    /// The world direction of the object-space direction `v` (R v).
    #[inline]
    pub fn to_world_vector(&self, v: Vec3) -> Vec3 {
        let [a, b, c] = self.inverse;
        a * v.x + b * v.y + c * v.z
    }

    /// The world point of the object-space point `o`.
    #[inline]
    pub fn to_world(&self, o: Vec3) -> Vec3 {
        self.to_world_vector(o - self.pivot) + self.shift
    }

    /// A world box holding the object-space box `(lo, hi)` wherever the pose
    /// puts it.
    pub fn world_box(&self, (lo, hi): (Vec3, Vec3)) -> (Vec3, Vec3) {
        let centre = (lo + hi) * 0.5;
        let half = (hi - lo) * 0.5;
        let world_centre = self.to_world(centre);
        // |R| h: the half extents of the rotated box; a little more for rounding.
        let [a, b, c] = self.inverse;
        let reach = a.abs() * half.x + b.abs() * half.y + c.abs() * half.z;
        let reach = reach * (1.0 + 1e-5) + Vec3::splat(1e-5 * world_centre.abs().max_element());
        (world_centre - reach, world_centre + reach)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::field::domain::Points;
    use crate::math::simd::LANES;

    fn motion(ron_text: &str) -> Motion {
        Motion::build(&ron::from_str(ron_text).expect("a transform"))
    }

    #[test]
    fn the_pose_undoes_the_motion() {
        let m = motion(
            "(translate: (1, 2, 3), velocity: (0.5, 0, 0), pivot: (0.2, 0, 0), axis: (0, 1, 0), angle: 30, spin: 15)",
        );
        for time in [0.0f32, 1.0, 2.5, 10.0] {
            let pose = m.at(time);
            for o in [
                Vec3::ZERO,
                Vec3::new(1.0, -2.0, 0.5),
                Vec3::new(0.2, 0.0, 0.0),
            ] {
                let w = pose.to_world(o);
                assert!((pose.to_object(w) - o).length() < 1e-5, "{time} {o}");
            }
            // The pivot travels with the translation only.
            let shift = Vec3::new(1.0 + 0.5 * time, 2.0, 3.0);
            assert!((pose.to_object(m.pivot + shift) - m.pivot).length() < 1e-6);
        }
        // 90° about y takes x to −z.
        let quarter = motion("(angle: 90)").at(0.0);
        assert!((quarter.to_world_vector(Vec3::X) - Vec3::NEG_Z).length() < 1e-6);
        assert!((quarter.to_object(Vec3::NEG_Z) - Vec3::X).length() < 1e-6);
    }

    #[test]
    fn the_world_box_holds_the_moved_object() {
        let m = motion("(translate: (0.3, 0, -1), axis: (1, 1, 0), angle: 40, spin: 7)");
        let b = (Vec3::new(-1.0, -0.5, -0.2), Vec3::new(0.5, 0.5, 0.8));
        for time in [0.0f32, 3.0, 11.0] {
            let pose = m.at(time);
            let (lo, hi) = pose.world_box(b);
            for i in 0..8 {
                let corner = Vec3::new(
                    if i & 1 == 0 { b.0.x } else { b.1.x },
                    if i & 2 == 0 { b.0.y } else { b.1.y },
                    if i & 4 == 0 { b.0.z } else { b.1.z },
                );
                let w = pose.to_world(corner);
                assert!(
                    w.cmpge(lo).all() && w.cmple(hi).all(),
                    "{w} outside {lo} {hi}"
                );
            }
        }
    }

    #[test]
    fn lanes_give_the_same_bits() {
        let pose =
            motion("(translate: (0.1, 0.2, 0.3), axis: (1, 2, 3), angle: 33, spin: 3)").at(1.5);
        let mut p = Points::default();
        for l in 0..LANES {
            p.set(
                l,
                Vec3::new(l as f32 * 0.37, 1.0 - l as f32, 0.1 * l as f32),
            );
        }
        let q = pose.to_object_lanes(&p);
        for l in 0..LANES {
            let one = pose.to_object(p.get(l));
            assert_eq!(
                q.get(l).to_array().map(f32::to_bits),
                one.to_array().map(f32::to_bits)
            );
        }
    }
}
