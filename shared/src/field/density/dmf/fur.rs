//! The paper's fur, straight (curliness 0) or curly (the tribble):
//! `f = gain(bias(s)) · d` with `s = (1 + noise(freq · project(x'))) / 2`.

use glam::Vec3;

use super::{InnerSurface, ValueDmf};
use crate::desc::DmfDesc;
use crate::field::domain::Field;
use crate::field::domain::{Points, zip};
use crate::field::noise::VNOISE_OFFSET;
use crate::field::shaping::{Bias, Gain};
use crate::math::dual::{Dual, DualPoint};
use crate::math::simd::{Isa, LANES, Lanes};

/// The paper's fur, straight (curliness 0) or curly (the tribble).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Fur {
    /// Fineness: noise frequency on the inner surface.
    frequency: f32,
    /// Shapes the noise: more empty space than hair.
    bias: Bias,
    /// Shapes the noise: hard-edged hairs.
    gain: Gain,
    /// Magnitude of the curl.
    curliness: f32,
    /// `gain_0.8`: straight at the root (d = 1), curling towards the tip.
    curl_gain: Gain,
}

impl ValueDmf for Fur {
    fn from_desc(desc: &DmfDesc, _step: f32) -> Option<Self> {
        let DmfDesc::Fur {
            frequency,
            bias,
            gain,
            curliness,
            curl_gain,
        } = *desc
        else {
            return None;
        };
        Some(Fur {
            frequency: frequency.0,
            bias: Bias::new(bias.0),
            gain: Gain::new(gain.0),
            curliness: curliness.0,
            curl_gain: Gain::new(curl_gain.0),
        })
    }

    /// `f = gain(bias(s)) · d` with `s = noise(freq · project(x'))` brought into the
    /// unit interval where bias and gain are defined: `s = (1 + noise) / 2` (the
    /// paper's noise ranges over [-1, 1]; clamping it instead would leave half the
    /// surface bald).
    #[inline]
    fn apply(&self, d: f32, x: Vec3, object: &impl InnerSurface, field: &Field) -> f32 {
        let x = if self.curliness > 0.0 {
            let q = x - field.offset;
            x + field.noise.vnoise(q) * (self.curl_gain.apply(1.0 - d) * self.curliness)
        } else {
            x
        };
        let s = 0.5 * (1.0 + field.noise(self.frequency, object.project(x)));
        self.gain.apply(self.bias.apply(s)) * d
    }

    /// Through the curl, the projection onto the inner surface and the noise there.
    fn apply_dual(
        &self,
        d: Dual,
        x: &DualPoint,
        object: &impl InnerSurface,
        field: &Field,
    ) -> Dual {
        let x = if self.curliness > 0.0 {
            let q = x.offset(-field.offset);
            let vnoise = DualPoint {
                x: field.noise.noise_dual(&q.offset(-VNOISE_OFFSET)),
                y: field.noise.noise_dual(&q),
                z: field.noise.noise_dual(&q.offset(VNOISE_OFFSET)),
            };
            let curl = self.curl_gain.apply_dual(-d + 1.0) * self.curliness;
            x.add(&vnoise.scale(curl))
        } else {
            *x
        };
        let s = (field.noise_dual(self.frequency, &object.project_dual(&x)) + 1.0) * 0.5;
        self.gain.apply_dual(self.bias.apply_dual(s)) * d
    }

    #[inline(always)]
    fn apply_lanes(
        &self,
        d: &Lanes,
        x: &Points,
        object: &impl InnerSurface,
        field: &Field,
        isa: Isa,
        live: u32,
    ) -> Lanes {
        let mut x = if self.curliness > 0.0 {
            let q = x.map(|x| x - field.offset);
            let a = field.noise_lanes_live(&q.map(|q| q - VNOISE_OFFSET), isa, live);
            let b = field.noise_lanes_live(&q, isa, live);
            let c = field.noise_lanes_live(&q.map(|q| q + VNOISE_OFFSET), isa, live);
            let curl = self.curl_gain.apply_simd_live(&d.map(|d| 1.0 - d), live);
            let mut out = Points::default();
            for l in 0..LANES {
                let v = Vec3::new(a[l], b[l], c[l]);
                out.set(l, x.get(l) + v * (curl[l] * self.curliness));
            }
            out
        } else {
            *x
        };
        object.project_lanes_in_place(&mut x, live);
        let s = field
            .noise_at_live(self.frequency, &x, isa, live)
            .map(|n| 0.5 * (1.0 + n));
        let shaped = self
            .gain
            .apply_simd_live(&self.bias.apply_simd_live(&s, live), live);
        zip(&shaped, d, |f, d| f * d)
    }
}
