//! The paper's shaping base functions, `bias` and `gain` (section 2.3).
//!
//! Both map the unit interval onto itself. Powers go through
//! [`fastmath::pow01`](crate::math::fastmath::pow01): basic IEEE operations only, so that
//! every machine of the farm, and every SIMD path, computes the same bits.

use crate::math::simd::Isa;
use crate::math::simd::{LANES, Lanes};

/// `bias_b(t) = t^(ln b / ln 0.5)`: pushes values in the unit interval up (b > 0.5)
/// or down (b < 0.5) while keeping `bias_b(0) = 0`, `bias_b(1/2) = b`,
/// `bias_b(1) = 1`. `t` is clamped to `[0, 1]` first (densities live there).
#[inline]
pub fn bias(b: f32, t: f32) -> f32 {
    Bias::new(b).apply(t)
}

/// `gain_g(t)`: a spline of two bias curves that makes the mid-range steeper
/// (g > 0.5) or flatter (g < 0.5): `bias_{1-g}(2t)/2` for `t < 1/2`, else
/// `1 - bias_{1-g}(2 - 2t)/2`. `t` is clamped to `[0, 1]` first.
#[inline]
pub fn gain(g: f32, t: f32) -> f32 {
    Gain::new(g).apply(t)
}

/// `bias_b` with its exponent `ln b / ln 0.5` computed once (at scene load).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Bias {
    /// `ln b / ln 0.5`.
    exponent: f32,
}

impl Bias {
    /// Whether every t in [0, 1] maps into [0, 1] (b in (0, 1]: a finite
    /// exponent ≥ 0), so the result is finite for every finite t.
    pub(crate) fn keeps_unit_interval(&self) -> bool {
        self.exponent >= 0.0 && self.exponent.is_finite()
    }

    /// The bias curve with parameter `b` in (0, 1).
    pub fn new(b: f32) -> Self {
        Bias {
            exponent: libm::logf(b) / libm::logf(0.5),
        }
    }

    /// `bias_b(t)` for `t` clamped to `[0, 1]`.
    #[inline]
    pub fn apply(&self, t: f32) -> f32 {
        let t = clamp01(t);
        if t == 0.0 {
            // 0^e is 0 for every e > 0; spelt out so that b = 1 (e = 0) keeps bias(0) = 0.
            return 0.0;
        }
        crate::math::fastmath::pow01(t, self.exponent)
    }

    /// [`Bias::apply`] with its gradient: `bias'(t) = e·t^(e−1) = e·bias(t)/t`.
    #[inline]
    pub fn apply_dual(&self, t: crate::math::dual::Dual) -> crate::math::dual::Dual {
        let t = t.clamp01();
        if t.v == 0.0 {
            return t;
        }
        let p = crate::math::fastmath::pow01(t.v, self.exponent);
        t.chain(p, self.exponent * p / t.v)
    }

    /// [`Bias::apply`] lane by lane on `isa` (the same bits).
    #[inline]
    pub fn apply_lanes(&self, t: &Lanes, isa: Isa) -> Lanes {
        let t = t.map(clamp01);
        self.finish(&t, &crate::math::fastmath::pow01_on(isa, &t, self.exponent))
    }

    /// [`Bias::apply_lanes`] inlined into a SIMD path's code (never the
    /// scalar path's: that goes point by point).
    #[inline(always)]
    pub(crate) fn apply_simd(&self, t: &Lanes) -> Lanes {
        self.apply_simd_live(t, u32::MAX)
    }

    /// [`Bias::apply_simd`] in the blocks of lanes with a lane set in
    /// `live` (the others come out as anything).
    #[inline(always)]
    pub(crate) fn apply_simd_live(&self, t: &Lanes, live: u32) -> Lanes {
        let t = t.map(clamp01);
        self.finish(
            &t,
            &crate::math::fastmath::pow01_lanes_live(&t, self.exponent, live),
        )
    }

    /// 0 where t is 0, else the power `p`.
    #[inline(always)]
    fn finish(&self, t: &Lanes, p: &Lanes) -> Lanes {
        let mut out = [0.0; LANES];
        for l in 0..LANES {
            out[l] = if t[l] == 0.0 { 0.0 } else { p[l] };
        }
        out
    }
}

/// `gain_g`, built on `bias_{1-g}`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Gain {
    /// `bias_{1-g}`.
    bias: Bias,
}

impl Gain {
    /// [`Bias::keeps_unit_interval`] of the underlying bias.
    pub(crate) fn keeps_unit_interval(&self) -> bool {
        self.bias.keeps_unit_interval()
    }

    /// The gain curve with parameter `g` in (0, 1).
    pub fn new(g: f32) -> Self {
        Gain {
            bias: Bias::new(1.0 - g),
        }
    }

    /// `gain_g(t)` for `t` clamped to `[0, 1]`.
    #[inline]
    pub fn apply(&self, t: f32) -> f32 {
        let t = clamp01(t);
        if t < 0.5 {
            self.bias.apply(2.0 * t) / 2.0
        } else {
            1.0 - self.bias.apply(2.0 - 2.0 * t) / 2.0
        }
    }

    /// [`Gain::apply`] with its gradient.
    #[inline]
    pub fn apply_dual(&self, t: crate::math::dual::Dual) -> crate::math::dual::Dual {
        let t = t.clamp01();
        if t.v < 0.5 {
            self.bias.apply_dual(t * 2.0) * 0.5
        } else {
            -(self.bias.apply_dual(-(t * 2.0) + 2.0) * 0.5) + 1.0
        }
    }

    /// [`Gain::apply`] lane by lane on `isa` (the same bits).
    #[inline]
    pub fn apply_lanes(&self, t: &Lanes, isa: Isa) -> Lanes {
        let t = t.map(clamp01);
        let arg = t.map(|t| if t < 0.5 { 2.0 * t } else { 2.0 - 2.0 * t });
        self.finish(&t, &self.bias.apply_lanes(&arg, isa))
    }

    /// [`Gain::apply_lanes`] inlined into a SIMD path's code.
    #[inline(always)]
    pub(crate) fn apply_simd(&self, t: &Lanes) -> Lanes {
        self.apply_simd_live(t, u32::MAX)
    }

    /// [`Gain::apply_simd`] in the blocks of lanes with a lane set in
    /// `live` (the others come out as anything).
    #[inline(always)]
    pub(crate) fn apply_simd_live(&self, t: &Lanes, live: u32) -> Lanes {
        let t = t.map(clamp01);
        let arg = t.map(|t| if t < 0.5 { 2.0 * t } else { 2.0 - 2.0 * t });
        self.finish(&t, &self.bias.apply_simd_live(&arg, live))
    }

    /// The two halves of the spline from `b = bias(arg)`.
    #[inline(always)]
    fn finish(&self, t: &Lanes, b: &Lanes) -> Lanes {
        let mut out = [0.0; LANES];
        for l in 0..LANES {
            out[l] = if t[l] < 0.5 {
                b[l] / 2.0
            } else {
                1.0 - b[l] / 2.0
            };
        }
        out
    }
}

/// Clamp to the unit interval; NaN becomes 0 so that nothing downstream sees it.
#[inline]
pub fn clamp01(t: f32) -> f32 {
    if t > 0.0 {
        if t < 1.0 { t } else { 1.0 }
    } else {
        0.0
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The powers' largest absolute error (`fastmath`'s polynomials).
    const EPS: f32 = crate::math::fastmath::POW01_MAX_ERROR as f32;

    #[test]
    fn bias_defining_points() {
        for b in [0.1, 0.25, 0.3, 0.5, 0.75, 0.9] {
            assert_eq!(bias(b, 0.0), 0.0);
            assert!(
                (bias(b, 0.5) - b).abs() < EPS,
                "bias_{b}(1/2) = {}",
                bias(b, 0.5)
            );
            assert!((bias(b, 1.0) - 1.0).abs() < EPS);
        }
    }

    #[test]
    fn gain_defining_points() {
        for g in [0.1, 0.25, 0.5, 0.75, 0.9] {
            assert_eq!(gain(g, 0.0), 0.0);
            assert!((gain(g, 0.25) - (1.0 - g) / 2.0).abs() < EPS);
            assert!((gain(g, 0.5) - 0.5).abs() < EPS);
            assert!((gain(g, 0.75) - (1.0 + g) / 2.0).abs() < EPS);
            assert!((gain(g, 1.0) - 1.0).abs() < EPS);
        }
    }

    #[test]
    fn half_is_the_identity() {
        for i in 0..=100 {
            let t = i as f32 / 100.0;
            assert!((bias(0.5, t) - t).abs() < EPS);
            assert!((gain(0.5, t) - t).abs() < EPS);
        }
    }

    #[test]
    fn monotone_and_clamped() {
        let mut last = (0.0, 0.0);
        for i in 0..=1000 {
            let t = i as f32 / 1000.0;
            let now = (bias(0.3, t), gain(0.9, t));
            assert!(now.0 >= last.0 && now.1 >= last.1);
            last = now;
        }
        assert_eq!(bias(0.3, -2.0), 0.0);
        assert_eq!(gain(0.9, 7.0), 1.0);
        assert_eq!(bias(0.3, f32::NAN), 0.0);
    }
}
