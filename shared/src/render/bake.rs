//! Sampling H(x) on a voxel lattice: what `coordinator bake` writes to an
//! OpenVDB file, whether its own threads sample it or the farm's workers do.
//!
//! A voxel's value is a pure function of (scene, frame, lattice, voxel), so a
//! bake is the same on any thread or worker. For the farm the lattice is laid
//! out as an image ([`Lattice::image_size`]): voxel number
//! `n = (i · ny + j) · nz + k` is pixel `(n mod W, n div W)`, so the farm's
//! units, leases and retries carry a bake unchanged.

use glam::Vec3;

use crate::Scene;
use crate::desc::{MAX_PIXELS, MAX_SIDE};
use crate::render::film::Sample;

/// The width of the image a lattice is laid out as (the last row may be
/// short: pixels past the last voxel are empty).
pub const IMAGE_WIDTH: u32 = 4096;

/// The voxel lattice of a bake: voxel (i, j, k) is centred at
/// `origin + voxel · (i, j, k)`, for `0 ≤ (i, j, k) < dims`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Lattice {
    /// The centre of voxel (0, 0, 0).
    pub origin: Vec3,
    /// The edge of a voxel.
    pub voxel: f32,
    /// Voxels along each axis.
    pub dims: [u32; 3],
}

impl Lattice {
    /// The lattice of `resolution` voxels along the longest edge of the box
    /// where the scene's density can be non-zero at `frame`.
    pub fn of(scene: &Scene, frame: u32, resolution: u32) -> Lattice {
        let (lo, hi) = scene.density_box(frame);
        let extent = (hi - lo).max(Vec3::ZERO);
        let longest = extent.max_element().max(f32::MIN_POSITIVE);
        let voxel = longest / resolution.max(1) as f32;
        let along = |e: f32| ((e / voxel).ceil() as u32).clamp(1, resolution.max(1));
        Lattice {
            origin: lo + Vec3::splat(0.5 * voxel),
            voxel,
            dims: [along(extent.x), along(extent.y), along(extent.z)],
        }
    }

    /// The world position of voxel (i, j, k): `origin + voxel · ijk` in
    /// double precision rounded once to f32, which is what a reader that
    /// applies the file's transform (in double) and rounds gets.
    pub fn point(&self, ijk: [u32; 3]) -> Vec3 {
        let axis = |o: f32, i: u32| (f64::from(o) + f64::from(i) * f64::from(self.voxel)) as f32;
        Vec3::new(
            axis(self.origin.x, ijk[0]),
            axis(self.origin.y, ijk[1]),
            axis(self.origin.z, ijk[2]),
        )
    }

    /// The number of voxels.
    pub fn voxels(&self) -> u64 {
        self.dims.iter().map(|&d| u64::from(d)).product()
    }

    /// The size of the image the lattice is laid out as: [`IMAGE_WIDTH`]
    /// wide (less for a small lattice), as many rows as the voxels need.
    /// `None` when that image is larger than a scene's image may be.
    pub fn image_size(&self) -> Option<(u32, u32)> {
        let n = self.voxels();
        if n == 0 || n > MAX_PIXELS {
            return None;
        }
        let width = n.min(u64::from(IMAGE_WIDTH));
        let height = n.div_ceil(width);
        (height <= u64::from(MAX_SIDE)).then_some((width as u32, height as u32))
    }

    /// The voxel number of voxel (i, j, k), its pixel's index in the image.
    pub fn index(&self, ijk: [u32; 3]) -> u64 {
        let [_, ny, nz] = self.dims.map(u64::from);
        (u64::from(ijk[0]) * ny + u64::from(ijk[1])) * nz + u64::from(ijk[2])
    }

    /// The voxel of pixel (x, y) of an image `width` wide, if it is one.
    pub fn voxel_of_pixel(&self, width: u32, x: u32, y: u32) -> Option<[u32; 3]> {
        let n = u64::from(y) * u64::from(width) + u64::from(x);
        if x >= width || n >= self.voxels() {
            return None;
        }
        let [_, ny, nz] = self.dims.map(u64::from);
        Some([
            (n / (ny * nz)) as u32,
            (n / nz % ny) as u32,
            (n % nz) as u32,
        ])
    }

    /// Whether the lattice is one a bake can sample: finite, voxels of a
    /// positive size, no axis empty.
    pub fn is_usable(&self) -> bool {
        self.origin.is_finite()
            && self.voxel.is_finite()
            && self.voxel > 0.0
            && self.dims.iter().all(|&d| d > 0)
    }
}

/// The value of voxel `ijk` at `frame`: H(x) at its centre and, where that is
/// not 0, the unlit colour there (black where it is 0).
pub fn voxel(scene: &Scene, lattice: &Lattice, frame: u32, ijk: [u32; 3]) -> (f32, [f32; 3]) {
    let p = lattice.point(ijk);
    let f = scene.density_at(p, frame);
    if f == 0.0 {
        (0.0, [0.0; 3])
    } else {
        (f, scene.colour_at(p, f, frame).to_array())
    }
}

/// A voxel's value as a pixel's sample: the colour in r, g, b, the density
/// in `density`, everything else 0.
pub fn to_sample((f, [r, g, b]): (f32, [f32; 3])) -> Sample {
    Sample {
        rgba: [r, g, b, 0.0],
        density: f,
        depth: 0.0,
        normal: [0.0; 3],
    }
}

/// A voxel's value from its pixel's sample ([`to_sample`] the other way).
pub fn from_sample(s: &Sample) -> (f32, [f32; 3]) {
    (s.density, [s.rgba[0], s.rgba[1], s.rgba[2]])
}

/// The samples of `pixels` of the image of `lattice` `width` wide
/// ([`Lattice::image_size`]): each its voxel's value, empty past the last voxel.
pub fn sample_pixels(
    scene: &Scene,
    lattice: &Lattice,
    frame: u32,
    width: u32,
    pixels: &[(u32, u32)],
) -> Vec<Sample> {
    pixels
        .iter()
        .map(|&(x, y)| match lattice.voxel_of_pixel(width, x, y) {
            Some(ijk) => to_sample(voxel(scene, lattice, frame, ijk)),
            None => Sample::default(),
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_voxel_has_one_pixel_and_back() {
        let lattice = Lattice {
            origin: Vec3::ZERO,
            voxel: 1.0,
            dims: [5, 7, 3],
        };
        let (w, h) = lattice.image_size().expect("a small lattice fits");
        assert_eq!((w, h), (105, 1));
        let mut seen = [false; 105];
        for y in 0..h {
            for x in 0..w {
                let ijk = lattice.voxel_of_pixel(w, x, y).expect("a voxel");
                let n = lattice.index(ijk) as usize;
                assert_eq!(n as u32, y * w + x);
                assert!(!seen[n]);
                seen[n] = true;
            }
        }
        let big = Lattice {
            dims: [100, 100, 100],
            ..lattice
        };
        let (w, h) = big.image_size().expect("a million voxels fit");
        assert_eq!((w, h), (IMAGE_WIDTH, 1_000_000u32.div_ceil(IMAGE_WIDTH)));
        assert_eq!(big.voxel_of_pixel(w, w - 1, h - 1), None, "past the end");
        assert_eq!(
            big.voxel_of_pixel(w, 0, h - 1).map(|v| big.index(v)),
            Some(u64::from(w * (h - 1)))
        );
        let huge = Lattice {
            dims: [512, 512, 512],
            ..lattice
        };
        assert_eq!(huge.image_size(), None);
    }

    #[test]
    fn a_voxel_survives_its_sample() {
        let v = (0.25, [0.5, -0.0, 3.0]);
        let back = from_sample(&to_sample(v));
        assert_eq!(back.0.to_bits(), v.0.to_bits());
        for c in 0..3 {
            assert_eq!(back.1[c].to_bits(), v.1[c].to_bits());
        }
    }
}
