//! The fractal sphere's warp: `c + (x − c)(1 + a · Σ noise(2^i f x) / (2^i f))`.

use glam::Vec3;

use super::{Settling, WarpDmf, bounds_left};
use crate::desc::{DmfDesc, Octaves};
use crate::field::domain::Field;
use crate::field::domain::{Points, map, zip};
use crate::field::noise::NOISE_BOUND;
use crate::math::dual::{Dual, DualPoint};
use crate::math::simd::{Isa, LANES};

/// `c + (x − c)(1 + a · Σ noise(2^i f x) / (2^i f))`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct FractalRadius {
    /// Frequency f of the first octave.
    frequency: f32,
    /// Octaves, clamped by the marching step.
    octaves: u32,
    /// Amplitude a of the radial displacement.
    amplitude: f32,
    /// Centre c of the scaling.
    centre: Vec3,
    /// The leading octaves whose samples along a ray mostly share their
    /// noise cells eight at a time ([`crate::field::noise::runs`]).
    runs: u32,
    /// How far the sum can move after each octave ([`bounds_left`]).
    left: [f32; Octaves::MOST],
}

impl WarpDmf for FractalRadius {
    fn from_desc(desc: &DmfDesc, step: f32) -> Option<Self> {
        let DmfDesc::FractalRadius {
            frequency,
            octaves,
            amplitude,
            centre,
        } = *desc
        else {
            return None;
        };
        // At most `Octaves::MOST`, as parsing ensures: the length of `left`.
        let clamped = crate::field::noise::clamped_octaves(frequency.0, step, octaves.0)
            .min(Octaves::MOST as u32);
        Some(FractalRadius {
            frequency: frequency.0,
            octaves: clamped,
            amplitude: amplitude.0,
            centre: centre.0,
            runs: crate::field::noise::octaves_in_runs(frequency.0, step, octaves.0),
            left: bounds_left(frequency.0, clamped),
        })
    }

    #[inline]
    fn apply(&self, x: Vec3, field: &Field) -> Vec3 {
        let mut sum = 0.0;
        let mut f = self.frequency;
        for _ in 0..self.octaves {
            sum += field.noise(f, x) / f;
            f *= 2.0;
        }
        self.centre + (x - self.centre) * (1.0 + self.amplitude * sum)
    }

    fn apply_dual(&self, x: &DualPoint, field: &Field) -> DualPoint {
        let mut sum = Dual::constant(0.0);
        let mut f = self.frequency;
        for _ in 0..self.octaves {
            sum = sum + field.noise_dual(f, x) * (1.0 / f);
            f *= 2.0;
        }
        let s = sum * self.amplitude + 1.0;
        x.offset(-self.centre).scale(s).offset(self.centre)
    }

    #[inline(always)]
    fn apply_lanes(&self, x: &Points, field: &Field, isa: Isa, settled: &impl Settling) -> Points {
        let a = self.amplitude;
        let mut sum = [0.0; LANES];
        let mut f = self.frequency;
        let mut live = u32::MAX;
        for octave in 0..self.octaves {
            // s = 1 + a·Σ ends within |a|·(the octaves left) of today's.
            let rest = a.abs() * self.left[octave as usize];
            let s = map(&sum, |s| 1.0 + a * s);
            live &= !settled.settled(&map(&s, |s| s - rest), &map(&s, |s| s + rest));
            if live == 0 {
                break;
            }
            let n = field.noise_at_along(f, x, isa, live, octave < self.runs);
            sum = zip(&sum, &n, |s, n| s + n / f);
            f *= 2.0;
        }
        x.scale_about(self.centre, &map(&sum, |s| 1.0 + a * s))
    }

    fn scale_range(&self) -> Option<(Vec3, f32, f32)> {
        let mut sum = 0.0;
        let mut f = self.frequency;
        for _ in 0..self.octaves {
            sum += NOISE_BOUND / f;
            f *= 2.0;
        }
        let a = self.amplitude.abs() * sum;
        Some((self.centre, 1.0 - a, 1.0 + a))
    }
}
