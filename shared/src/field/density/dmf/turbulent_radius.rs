//! The fiery sphere's warp: `c + (x − c)(1 + a · turbulence(f x))`.

use glam::Vec3;

use super::{Settling, WarpDmf, bounds_left};
use crate::desc::{DmfDesc, Octaves};
use crate::field::domain::Field;
use crate::field::domain::{Points, map, zip};
use crate::field::noise::NOISE_BOUND;
use crate::math::dual::{Dual, DualPoint};
use crate::math::simd::{Isa, LANES};

/// `c + (x − c)(1 + a · turbulence(f x))`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TurbulentRadius {
    /// Frequency f of the first octave.
    frequency: f32,
    /// Amplitude a of the radial displacement.
    amplitude: f32,
    /// Octaves, clamped by the marching step.
    octaves: u32,
    /// Centre c of the scaling.
    centre: Vec3,
    /// The leading octaves whose samples along a ray mostly share their
    /// noise cells eight at a time ([`crate::field::noise::runs`]).
    runs: u32,
    /// How far the sum can move after each octave ([`bounds_left`]).
    left: [f32; Octaves::MOST],
}

impl WarpDmf for TurbulentRadius {
    fn from_desc(desc: &DmfDesc, step: f32) -> Option<Self> {
        let DmfDesc::TurbulentRadius {
            frequency,
            amplitude,
            octaves,
            centre,
        } = *desc
        else {
            return None;
        };
        // At most `Octaves::MOST`, as parsing ensures: the length of `left`.
        let clamped = crate::field::noise::clamped_octaves(frequency.0, step, octaves.0)
            .min(Octaves::MOST as u32);
        Some(TurbulentRadius {
            frequency: frequency.0,
            amplitude: amplitude.0,
            octaves: clamped,
            centre: centre.0,
            runs: crate::field::noise::octaves_in_runs(frequency.0, step, octaves.0),
            left: bounds_left(1.0, clamped),
        })
    }

    #[inline]
    fn apply(&self, x: Vec3, field: &Field) -> Vec3 {
        let t = field.turbulence(self.frequency, x, self.octaves);
        self.centre + (x - self.centre) * (1.0 + self.amplitude * t)
    }

    fn apply_dual(&self, x: &DualPoint, field: &Field) -> DualPoint {
        let q = x.offset(-field.offset).times(self.frequency);
        let mut sum = Dual::constant(0.0);
        let mut scale = 1.0f32;
        for _ in 0..self.octaves {
            sum = sum + field.noise.noise_dual(&q.times(scale)).abs() * (1.0 / scale);
            scale *= 2.0;
        }
        let s = sum * self.amplitude + 1.0;
        x.offset(-self.centre).scale(s).offset(self.centre)
    }

    #[inline(always)]
    fn apply_lanes(&self, x: &Points, field: &Field, isa: Isa, settled: &impl Settling) -> Points {
        let a = self.amplitude;
        let q = x.map(|p| (p - field.offset) * self.frequency);
        let mut sum = [0.0; LANES];
        let mut scale = 1.0f32;
        let mut live = u32::MAX;
        for octave in 0..self.octaves {
            // Every octave adds |noise| ≥ 0: s = 1 + a·Σ moves from today's
            // only towards the sign of a, by at most a·(the octaves left).
            let rest = a * self.left[octave as usize];
            let s = map(&sum, |s| 1.0 + a * s);
            let (lo, hi) = (rest.min(0.0), rest.max(0.0));
            live &= !settled.settled(&map(&s, |s| s + lo), &map(&s, |s| s + hi));
            if live == 0 {
                break;
            }
            let n = field.noise_lanes_along(&q.map(|p| p * scale), isa, live, octave < self.runs);
            // |n| / scale, by the reciprocal: scale is a power of two, so
            // 1 / scale is exact and the product rounds as the quotient.
            let weight = 1.0 / scale;
            sum = zip(&sum, &n, |s, n| s + n.abs() * weight);
            scale *= 2.0;
        }
        x.scale_about(self.centre, &map(&sum, |t| 1.0 + a * t))
    }

    fn scale_range(&self) -> Option<(Vec3, f32, f32)> {
        let mut t = 0.0;
        let mut scale = 1.0;
        for _ in 0..self.octaves {
            t += NOISE_BOUND / scale;
            scale *= 2.0;
        }
        let a = self.amplitude * t;
        Some((self.centre, 1.0 + a.min(0.0), 1.0 + a.max(0.0)))
    }
}
