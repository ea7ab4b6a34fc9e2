//! The dripping sphere's warp: material hangs down in drips where the noise
//! is positive.

use glam::Vec3;

use super::{Settling, WarpDmf};
use crate::desc::DmfDesc;
use crate::field::domain::Field;
use crate::field::domain::Points;
use crate::field::domain::{Aabb, hull, unscale};
use crate::field::noise::NOISE_BOUND;
use crate::math::dual::{Dual, DualPoint};
use crate::math::simd::{Isa, LANES};

/// y only, below the centre:
/// `c.y + (y − c.y)(1 − a · max(0, noise(f · (x, stretch · y, z))))`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Dripping {
    /// Noise frequency f.
    frequency: f32,
    /// Amplitude a of the pull.
    amplitude: f32,
    /// Stretch of the noise along y: long drips.
    stretch: f32,
    /// Centre: only points below it move.
    centre: Vec3,
}

impl WarpDmf for Dripping {
    fn from_desc(desc: &DmfDesc, _step: f32) -> Option<Self> {
        let DmfDesc::Dripping {
            frequency,
            amplitude,
            stretch,
            centre,
        } = *desc
        else {
            return None;
        };
        Some(Dripping {
            frequency: frequency.0,
            amplitude: amplitude.0,
            stretch: stretch.0,
            centre: centre.0,
        })
    }

    #[inline]
    fn apply(&self, x: Vec3, field: &Field) -> Vec3 {
        let Dripping {
            frequency,
            amplitude,
            stretch,
            centre,
        } = *self;
        if x.y >= centre.y {
            return x;
        }
        let q = x - field.offset;
        let n = field
            .noise
            .noise(Vec3::new(q.x, q.y * stretch, q.z) * frequency);
        let pull = 1.0 - amplitude * n.max(0.0);
        Vec3::new(x.x, centre.y + (x.y - centre.y) * pull, x.z)
    }

    fn apply_dual(&self, x: &DualPoint, field: &Field) -> DualPoint {
        let centre = self.centre;
        if x.y.v >= centre.y {
            return *x;
        }
        let mut q = x.offset(-field.offset);
        q.y = q.y * self.stretch;
        let n = field.noise.noise_dual(&q.times(self.frequency));
        let pull = -(n.max(Dual::constant(0.0)) * self.amplitude) + 1.0;
        DualPoint {
            y: (x.y - centre.y) * pull + centre.y,
            ..*x
        }
    }

    #[inline(always)]
    fn apply_lanes(&self, x: &Points, field: &Field, isa: Isa, _: &impl Settling) -> Points {
        let Dripping {
            frequency,
            amplitude,
            stretch,
            centre,
        } = *self;
        if x.y.iter().all(|&y| y >= centre.y) {
            return *x;
        }
        let o = field.offset;
        let mut q = Points::default();
        for l in 0..LANES {
            q.x[l] = (x.x[l] - o.x) * frequency;
            q.y[l] = ((x.y[l] - o.y) * stretch) * frequency;
            q.z[l] = (x.z[l] - o.z) * frequency;
        }
        let n = field.noise_lanes(&q, isa);
        let mut out = *x;
        for (l, &n) in n.iter().enumerate() {
            let y = x.y[l];
            let pull = 1.0 - amplitude * n.max(0.0);
            let moved = centre.y + (y - centre.y) * pull;
            out.y[l] = if y < centre.y { moved } else { y };
        }
        out
    }

    /// Not a scaling about a point: only y moves, and only below the centre.
    fn scale_range(&self) -> Option<(Vec3, f32, f32)> {
        None
    }

    fn preimage(&self, b: Aabb) -> Option<Aabb> {
        let centre = self.centre;
        // Below the centre y is scaled by a pull in [1 − a·M, 1]
        // (a ≥ 0) or [1, 1 − a·M]; above, x is unchanged.
        let pull = 1.0 - self.amplitude * NOISE_BOUND;
        match unscale(b, centre, pull.min(1.0), pull.max(1.0), Vec3::Y) {
            Some(stretched) => Some(hull(b, stretched)),
            // A pull that can reach 0 may bring any y below the
            // centre to the centre's: only x and z stay bounded.
            None => Some((
                Vec3::new(b.0.x, f32::NEG_INFINITY, b.0.z),
                Vec3::new(b.1.x, b.1.y.max(centre.y), b.1.z),
            )),
        }
    }
}
