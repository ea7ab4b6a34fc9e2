//! The camera: one ray per pixel through the pixel centre.

use glam::Vec3;

use crate::scene::desc::{CameraDesc, ProjectionDesc};

/// A ray `origin + t · direction` with a unit direction.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Ray {
    /// Where the ray starts.
    pub origin: Vec3,
    /// Unit direction.
    pub direction: Vec3,
}

impl Ray {
    /// The point at parameter t.
    #[inline]
    pub fn at(&self, t: f32) -> Vec3 {
        self.origin + self.direction * t
    }
}

/// The entry and exit parameters of `ray` through the box `(min, max)`, clipped to
/// t ≥ 0, or `None` when it misses (the slab test).
#[inline]
pub fn slab(ray: &Ray, min: Vec3, max: Vec3) -> Option<(f32, f32)> {
    let mut t0: f32 = 0.0;
    let mut t1 = f32::INFINITY;
    for axis in 0..3 {
        let (o, d) = (ray.origin[axis], ray.direction[axis]);
        if d == 0.0 {
            if o < min[axis] || o > max[axis] {
                return None;
            }
            continue;
        }
        let inv = 1.0 / d;
        let (mut near, mut far) = ((min[axis] - o) * inv, (max[axis] - o) * inv);
        if near > far {
            std::mem::swap(&mut near, &mut far);
        }
        t0 = t0.max(near);
        t1 = t1.min(far);
    }
    (t0 <= t1).then_some((t0, t1))
}

/// A camera ready to generate rays for an image of a given size.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Camera {
    eye: Vec3,
    /// Unit view direction.
    forward: Vec3,
    /// Unit right vector, scaled to half the view width at distance 1 (perspective)
    /// or in scene units (orthographic).
    right: Vec3,
    /// Unit up vector, scaled like `right`.
    up: Vec3,
    perspective: bool,
    width: f32,
    height: f32,
}

impl Camera {
    /// The camera of `desc` for a `width × height` image.
    pub fn new(desc: &CameraDesc, width: u32, height: u32) -> Camera {
        let forward = (desc.look_at.0 - desc.eye.0).normalize();
        let right = forward.cross(desc.up.0).normalize();
        let up = right.cross(forward);
        let aspect = width as f32 / height as f32;
        let (half_height, perspective) = match desc.projection {
            ProjectionDesc::Perspective { fov_y } => (libm::tanf(fov_y.0.to_radians() / 2.0), true),
            ProjectionDesc::Orthographic { height } => (height.0 / 2.0, false),
        };
        Camera {
            eye: desc.eye.0,
            forward,
            right: right * (half_height * aspect),
            up: up * half_height,
            perspective,
            width: width as f32,
            height: height as f32,
        }
    }

    /// The ray through the centre of pixel (x, y), offset within the pixel by
    /// `jitter` ((0.5, 0.5) is the centre). Row 0 is the top of the image.
    #[inline]
    pub fn ray(&self, x: u32, y: u32, jitter: (f32, f32)) -> Ray {
        let sx = 2.0 * (x as f32 + jitter.0) / self.width - 1.0;
        let sy = 1.0 - 2.0 * (y as f32 + jitter.1) / self.height;
        let offset = self.right * sx + self.up * sy;
        if self.perspective {
            Ray {
                origin: self.eye,
                direction: (self.forward + offset).normalize(),
            }
        } else {
            Ray {
                origin: self.eye + offset,
                direction: self.forward,
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::scene::desc::{FieldOfView, Positive, V3};

    fn desc(projection: ProjectionDesc) -> CameraDesc {
        CameraDesc {
            eye: V3(Vec3::new(0.0, 0.0, 5.0)),
            look_at: V3(Vec3::ZERO),
            up: V3(Vec3::Y),
            projection,
        }
    }

    #[test]
    fn centre_ray_looks_at_target() {
        let cam = Camera::new(
            &desc(ProjectionDesc::Perspective {
                fov_y: FieldOfView(90.0),
            }),
            2,
            2,
        );
        // With an even size the image centre is a pixel corner: jitter (1, 1) of pixel 0.
        let r = cam.ray(0, 0, (1.0, 1.0));
        assert!((r.direction - Vec3::NEG_Z).length() < 1e-6);
        // Top-left pixel centre of a 2×2 image at 90°: direction (-0.5, 0.5, -1) normalised.
        let r = cam.ray(0, 0, (0.5, 0.5));
        assert!((r.direction - Vec3::new(-0.5, 0.5, -1.0).normalize()).length() < 1e-6);
    }

    #[test]
    fn orthographic_rays_are_parallel() {
        let cam = Camera::new(
            &desc(ProjectionDesc::Orthographic {
                height: Positive(2.0),
            }),
            4,
            2,
        );
        let a = cam.ray(0, 0, (0.5, 0.5));
        let b = cam.ray(3, 1, (0.5, 0.5));
        assert_eq!(a.direction, b.direction);
        assert!((a.origin - Vec3::new(-1.5, 0.5, 5.0)).length() < 1e-6);
    }

    #[test]
    fn slab_clips_rays() {
        let (min, max) = (Vec3::splat(-1.0), Vec3::splat(1.0));
        let hit = Ray {
            origin: Vec3::new(0.0, 0.0, 5.0),
            direction: Vec3::NEG_Z,
        };
        assert_eq!(slab(&hit, min, max), Some((4.0, 6.0)));
        let miss = Ray {
            origin: Vec3::new(2.0, 0.0, 5.0),
            direction: Vec3::NEG_Z,
        };
        assert_eq!(slab(&miss, min, max), None);
        let away = Ray {
            origin: Vec3::new(0.0, 0.0, 5.0),
            direction: Vec3::Z,
        };
        assert_eq!(slab(&away, min, max), None);
        let inside = Ray {
            origin: Vec3::ZERO,
            direction: Vec3::new(1.0, 1.0, 0.0).normalize(),
        };
        let (t0, t1) = slab(&inside, min, max).unwrap();
        assert_eq!(t0, 0.0);
        assert!((t1 - 2f32.sqrt()).abs() < 1e-6);
        let diagonal = Ray {
            origin: Vec3::new(-3.0, -3.0, -3.0),
            direction: Vec3::ONE.normalize(),
        };
        let (t0, t1) = slab(&diagonal, min, max).unwrap();
        assert!((t0 - 2.0 * 3f32.sqrt()).abs() < 1e-5 && (t1 - 4.0 * 3f32.sqrt()).abs() < 1e-5);
    }
}
