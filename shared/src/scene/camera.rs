//! The camera: one ray per pixel through the pixel centre.

use glam::Vec3;

use crate::desc::{CameraDesc, ProjectionDesc};

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
    let mut t = (0.0f32, f32::INFINITY);
    let (o, d) = (ray.origin, ray.direction);
    let inside = slab_axis(o.x, d.x, min.x, max.x, &mut t)
        && slab_axis(o.y, d.y, min.y, max.y, &mut t)
        && slab_axis(o.z, d.z, min.z, max.z, &mut t);
    (inside && t.0 <= t.1).then_some(t)
}

/// One axis of [`slab`]: narrows `(t0, t1)` to the parameters between the
/// axis's two planes (a NaN bound, from a plane through the origin along
/// an axis the ray barely moves on, is ignored), or says the ray misses.
#[inline(always)]
fn slab_axis(o: f32, d: f32, min: f32, max: f32, (t0, t1): &mut (f32, f32)) -> bool {
    if d == 0.0 {
        return !(o < min || o > max);
    }
    let inv = 1.0 / d;
    let (a, b) = ((min - o) * inv, (max - o) * inv);
    let (near, far) = if a > b { (b, a) } else { (a, b) };
    if near > *t0 {
        *t0 = near;
    }
    if far < *t1 {
        *t1 = far;
    }
    true
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

    /// [`Camera::ray`] through the centres of `pixels` (N at most; the
    /// other rays are through pixel (0, 0)): the same rays, found lane by
    /// lane in arrays so that the divisions and square roots vectorise.
    #[inline]
    pub fn centre_rays<const N: usize>(&self, pixels: &[(u32, u32)]) -> [Ray; N] {
        let (mut sx, mut sy) = ([0.0f32; N], [0.0f32; N]);
        for (i, &(x, y)) in pixels.iter().take(N).enumerate() {
            sx[i] = x as f32;
            sy[i] = y as f32;
        }
        for i in 0..N {
            sx[i] = 2.0 * (sx[i] + 0.5) / self.width - 1.0;
            sy[i] = 1.0 - 2.0 * (sy[i] + 0.5) / self.height;
        }
        // `Vec3` arithmetic coordinate by coordinate: the same operations.
        let (r, u, f) = (self.right, self.up, self.forward);
        let mut d = [[0.0f32; N]; 3];
        for i in 0..N {
            d[0][i] = r.x * sx[i] + u.x * sy[i];
            d[1][i] = r.y * sx[i] + u.y * sy[i];
            d[2][i] = r.z * sx[i] + u.z * sy[i];
        }
        if !self.perspective {
            return std::array::from_fn(|i| Ray {
                origin: self.eye + Vec3::new(d[0][i], d[1][i], d[2][i]),
                direction: self.forward,
            });
        }
        let mut recip = [0.0f32; N];
        for i in 0..N {
            d[0][i] += f.x;
            d[1][i] += f.y;
            d[2][i] += f.z;
            // `normalize`: the direction times 1 / √(d · d).
            let dot = d[0][i] * d[0][i] + d[1][i] * d[1][i] + d[2][i] * d[2][i];
            recip[i] = 1.0 / dot.sqrt();
        }
        std::array::from_fn(|i| Ray {
            origin: self.eye,
            direction: Vec3::new(d[0][i], d[1][i], d[2][i]) * recip[i],
        })
    }

    /// OpenEXR's `worldToCamera`: the matrix, row-major, by which a world point
    /// as a row vector `(x, y, z, 1)` is multiplied to give camera coordinates
    /// (x right, y up, the camera looking down −z, the eye at the origin).
    pub fn world_to_camera(&self) -> [f32; 16] {
        let (r, u, b) = (self.right.normalize(), self.up.normalize(), -self.forward);
        let e = self.eye;
        [
            r.x,
            u.x,
            b.x,
            0.0, //
            r.y,
            u.y,
            b.y,
            0.0, //
            r.z,
            u.z,
            b.z,
            0.0, //
            -e.dot(r),
            -e.dot(u),
            -e.dot(b),
            1.0,
        ]
    }

    /// OpenEXR's `worldToNDC`: `worldToCamera` followed by the projection to
    /// normalized device coordinates, row-major for row vectors. After the
    /// division by w, x and y run from −1 to 1 across the image (left to right,
    /// bottom to top); z is 1 / depth for a perspective camera (w is the depth
    /// along the view axis) and the depth itself for an orthographic one.
    pub fn world_to_ndc(&self) -> [f32; 16] {
        let (sx, sy) = (1.0 / self.right.length(), 1.0 / self.up.length());
        #[rustfmt::skip]
        let projection = if self.perspective {
            [
                sx, 0.0, 0.0, 0.0,
                0.0, sy, 0.0, 0.0,
                0.0, 0.0, 0.0, -1.0,
                0.0, 0.0, 1.0, 0.0,
            ]
        } else {
            [
                sx, 0.0, 0.0, 0.0,
                0.0, sy, 0.0, 0.0,
                0.0, 0.0, -1.0, 0.0,
                0.0, 0.0, 0.0, 1.0,
            ]
        };
        multiply(&self.world_to_camera(), &projection)
    }
}

/// The product `a · b` of two row-major 4×4 matrices.
fn multiply(a: &[f32; 16], b: &[f32; 16]) -> [f32; 16] {
    std::array::from_fn(|i| {
        let (row, col) = (i / 4, i % 4);
        (0..4).map(|k| a[row * 4 + k] * b[k * 4 + col]).sum()
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::desc::{FieldOfView, Positive, V3};

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
    fn the_centre_rays_are_each_pixels_ray() {
        let mut odd = desc(ProjectionDesc::Orthographic {
            height: Positive(2.5),
        });
        odd.eye = V3(Vec3::new(0.3, 1.7, 2.9));
        odd.look_at = V3(Vec3::new(-0.2, 0.1, 0.4));
        let perspective = desc(ProjectionDesc::Perspective {
            fov_y: FieldOfView(37.0),
        });
        let tilted = CameraDesc {
            projection: perspective.projection,
            ..odd
        };
        for (what, d) in [
            ("perspective", perspective),
            ("tilted", tilted),
            ("orthographic", odd),
        ] {
            let cam = Camera::new(&d, 641, 359);
            let pixels: Vec<(u32, u32)> = (0..641u32)
                .flat_map(|x| [(x, (x * 7) % 359), (x, 358 - (x * 3) % 359)])
                .collect();
            for group in pixels.chunks(5) {
                let rays: [Ray; 8] = cam.centre_rays(group);
                for (&(x, y), r) in group.iter().zip(&rays) {
                    let one = cam.ray(x, y, (0.5, 0.5));
                    assert_eq!(
                        (
                            r.origin.to_array().map(f32::to_bits),
                            r.direction.to_array().map(f32::to_bits)
                        ),
                        (
                            one.origin.to_array().map(f32::to_bits),
                            one.direction.to_array().map(f32::to_bits)
                        ),
                        "{what}: pixel ({x}, {y})"
                    );
                }
            }
        }
    }

    /// `p` (a row vector) times the row-major matrix `m`.
    fn transform(p: Vec3, m: &[f32; 16]) -> [f32; 4] {
        std::array::from_fn(|c| p.x * m[c] + p.y * m[4 + c] + p.z * m[8 + c] + m[12 + c])
    }

    #[test]
    fn ndc_matrices_put_each_ray_on_its_pixel() {
        let mut eyed = desc(ProjectionDesc::Perspective {
            fov_y: FieldOfView(40.0),
        });
        eyed.eye = V3(Vec3::new(1.0, 2.0, 4.0));
        let ortho = CameraDesc {
            projection: ProjectionDesc::Orthographic {
                height: Positive(3.0),
            },
            ..eyed
        };
        for d in [eyed, ortho] {
            let cam = Camera::new(&d, 8, 4);
            let to_camera = cam.world_to_camera();
            let eye = transform(d.eye.0, &to_camera);
            assert!(eye[..3].iter().all(|c| c.abs() < 1e-5), "{eye:?}");
            let ahead = transform(d.eye.0 + (d.look_at.0 - d.eye.0).normalize(), &to_camera);
            assert!((ahead[2] + 1.0).abs() < 1e-5, "looks down −z: {ahead:?}");
            for (x, y) in [(0, 0), (7, 3), (3, 1)] {
                let ray = cam.ray(x, y, (0.5, 0.5));
                let ndc = transform(ray.at(2.5), &cam.world_to_ndc());
                let (nx, ny) = (ndc[0] / ndc[3], ndc[1] / ndc[3]);
                let want = ((x as f32 + 0.5) / 4.0 - 1.0, 1.0 - (y as f32 + 0.5) / 2.0);
                assert!(
                    (nx - want.0).abs() < 1e-5 && (ny - want.1).abs() < 1e-5,
                    "{ndc:?}"
                );
            }
        }
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

    /// The slab test as `f32::max` and `min` over the axes: `slab` gives
    /// the same parameters (a zero's sign aside, where either is a maximum)
    /// for rays along and across the axes, from the faces, and with
    /// directions of ±0, subnormal and ordinary components.
    #[test]
    fn slab_is_the_maximum_of_the_near_planes() {
        fn reference(ray: &Ray, min: Vec3, max: Vec3) -> Option<(f32, f32)> {
            let (mut t0, mut t1) = (0.0f32, f32::INFINITY);
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
        let (min, max) = (Vec3::new(-1.0, -0.5, -2.0), Vec3::new(1.0, 1.5, 0.25));
        let coordinates = [-3.0, -1.0, -0.5, 0.0, 0.25, 1.0, 1.5, 4.0];
        let components = [-1.0, -0.6, -1e-40, -0.0, 0.0, 1e-40, 0.3, 1.0];
        let mut rays = 0;
        for &ox in &coordinates {
            for &oy in &coordinates {
                for &oz in &coordinates {
                    for &dx in &components {
                        for &dy in &components {
                            for &dz in &components {
                                let ray = Ray {
                                    origin: Vec3::new(ox, oy, oz),
                                    direction: Vec3::new(dx, dy, dz),
                                };
                                let (got, want) = (slab(&ray, min, max), reference(&ray, min, max));
                                match (got, want) {
                                    (Some(g), Some(w)) => {
                                        assert!(
                                            g.0 == w.0 && g.1 == w.1,
                                            "{ray:?}: {g:?} against {w:?}"
                                        );
                                        assert_eq!(g.0.is_nan(), w.0.is_nan());
                                        rays += 1;
                                    }
                                    _ => assert_eq!(got, want, "{ray:?}"),
                                }
                            }
                        }
                    }
                }
            }
        }
        assert!(rays > 10_000, "{rays} rays through the box");
    }
}
