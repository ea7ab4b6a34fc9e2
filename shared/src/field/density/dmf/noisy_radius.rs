//! The noisy sphere's warp: `c + (x − c)(1 + a · noise(f x))`.

use glam::Vec3;

use super::{Settling, WarpDmf};
use crate::desc::DmfDesc;
use crate::field::domain::Field;
use crate::field::domain::{Points, map};
use crate::field::noise::NOISE_BOUND;
use crate::math::dual::DualPoint;
use crate::math::simd::Isa;

/// `c + (x − c)(1 + a · noise(f x))`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct NoisyRadius {
    /// Noise frequency f.
    frequency: f32,
    /// Amplitude a of the radial displacement.
    amplitude: f32,
    /// Centre c of the scaling.
    centre: Vec3,
    /// Whether a ray's samples mostly share their noise cells eight at a
    /// time ([`crate::field::noise::runs`]).
    runs: bool,
}

impl WarpDmf for NoisyRadius {
    fn from_desc(desc: &DmfDesc, step: f32) -> Option<Self> {
        let DmfDesc::NoisyRadius {
            frequency,
            amplitude,
            centre,
        } = *desc
        else {
            return None;
        };
        Some(NoisyRadius {
            frequency: frequency.0,
            amplitude: amplitude.0,
            centre: centre.0,
            runs: crate::field::noise::runs(frequency.0, step),
        })
    }

    #[inline]
    fn apply(&self, x: Vec3, field: &Field) -> Vec3 {
        let NoisyRadius {
            frequency,
            amplitude,
            centre,
            ..
        } = *self;
        centre + (x - centre) * (1.0 + amplitude * field.noise(frequency, x))
    }

    fn apply_dual(&self, x: &DualPoint, field: &Field) -> DualPoint {
        let s = field.noise_dual(self.frequency, x) * self.amplitude + 1.0;
        x.offset(-self.centre).scale(s).offset(self.centre)
    }

    #[inline(always)]
    fn apply_lanes(&self, x: &Points, field: &Field, isa: Isa, _: &impl Settling) -> Points {
        let n = field.noise_at_along(self.frequency, x, isa, u32::MAX, self.runs);
        x.scale_about(self.centre, &map(&n, |n| 1.0 + self.amplitude * n))
    }

    fn scale_range(&self) -> Option<(Vec3, f32, f32)> {
        let a = self.amplitude.abs() * NOISE_BOUND;
        Some((self.centre, 1.0 - a, 1.0 + a))
    }
}
