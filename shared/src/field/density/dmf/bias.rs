//! The `Bias` DMF: bias_b(d), with its exponent computed at load. The function itself lives in
//! [`crate::field::shaping`], shared with the expressions.

use glam::Vec3;

use super::{InnerSurface, ValueDmf};
use crate::desc::DmfDesc;
use crate::field::domain::Field;
use crate::field::domain::Points;
use crate::field::shaping::Bias;
use crate::math::dual::{Dual, DualPoint};
use crate::math::simd::{Isa, Lanes};

impl ValueDmf for Bias {
    fn from_desc(desc: &DmfDesc, _step: f32) -> Option<Self> {
        let DmfDesc::Bias(v) = *desc else {
            return None;
        };
        Some(Bias::new(v.0))
    }

    #[inline]
    fn apply(&self, d: f32, _x: Vec3, _object: &impl InnerSurface, _field: &Field) -> f32 {
        Bias::apply(self, d)
    }

    fn apply_dual(
        &self,
        d: Dual,
        _x: &DualPoint,
        _object: &impl InnerSurface,
        _field: &Field,
    ) -> Dual {
        Bias::apply_dual(self, d)
    }

    #[inline(always)]
    fn apply_lanes(
        &self,
        d: &Lanes,
        _x: &Points,
        _object: &impl InnerSurface,
        _field: &Field,
        _isa: Isa,
        live: u32,
    ) -> Lanes {
        self.apply_simd_live(d, live)
    }
}
