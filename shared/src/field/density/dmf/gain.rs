//! The `Gain` DMF: gain_g(d), a spline of two bias curves. The function itself lives in
//! [`crate::field::shaping`], shared with the expressions.

use glam::Vec3;

use super::{InnerSurface, ValueDmf};
use crate::desc::DmfDesc;
use crate::field::domain::Field;
use crate::field::domain::Points;
use crate::field::shaping::Gain;
use crate::math::dual::{Dual, DualPoint};
use crate::math::simd::{Isa, Lanes};

impl ValueDmf for Gain {
    fn from_desc(desc: &DmfDesc, _step: f32) -> Option<Self> {
        let DmfDesc::Gain(v) = *desc else {
            return None;
        };
        Some(Gain::new(v.0))
    }

    #[inline]
    fn apply(&self, d: f32, _x: Vec3, _object: &impl InnerSurface, _field: &Field) -> f32 {
        Gain::apply(self, d)
    }

    fn apply_dual(
        &self,
        d: Dual,
        _x: &DualPoint,
        _object: &impl InnerSurface,
        _field: &Field,
    ) -> Dual {
        Gain::apply_dual(self, d)
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
