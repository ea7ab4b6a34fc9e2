//! `pow` for the hot paths (bias, gain, opacity, specular), from IEEE basic
//! operations only.
//!
//! `libm::powf` is exact to an ulp but costs ~20 ns and branches on every special
//! case. Here `x^e = 2^(e·log₂ x)` with a fixed polynomial for each factor: the
//! same additions and multiplications in the same order on every CPU and in
//! every lane of the SIMD paths, so the bits never depend on the machine.
//!
//! Accuracy (tested against f64 in `tests` below): `log2` within 2·10⁻⁷ and
//! `exp2` within 3·10⁻⁷ (relative); `pow01` within 10⁻⁶ relative for results
//! ≥ 10⁻³, and within 2·10⁻⁷·(1 + |log₂ result|) everywhere (the exponent
//! e·log₂ x is rounded to f32). An 8-bit output level is 4·10⁻³.

use crate::simd::{Isa, LANES, Lanes};

/// 1 / ln 2.
const INV_LN2: f32 = std::f32::consts::LOG2_E;

/// ⌊x⌋, exactly as `f32::floor` for every finite x, from a conversion and a
/// compare: the SSE2 baseline has no rounding instruction and would call libm,
/// and Rust's saturating `as i32` would keep the lanes from vectorising.
#[inline(always)]
pub fn floor(x: f32) -> f32 {
    // |x| ≥ 2²³ is already an integer (NaN stays NaN: the compare fails).
    let small = x.abs() < 8_388_608.0;
    let t = lattice(if small { x } else { 0.0 }) as f32;
    let floor = if t > x { t - 1.0 } else { t };
    if small { floor } else { x }
}

/// The integer of an integral `x` (a lattice coordinate), 0 where it would not
/// fit an i32 (and for NaN): the same in every lane and on every path.
#[inline(always)]
pub fn lattice(x: f32) -> i32 {
    let fits = x.abs() < 2_147_483_520.0; // the largest f32 below 2³¹
    // SAFETY: the argument is finite and within i32's range.
    unsafe { (if fits { x } else { 0.0 }).to_int_unchecked::<i32>() }
}

/// log₂ x for finite x > 0 (subnormals included). Not for 0, negatives or NaN:
/// callers clamp first.
#[inline(always)]
pub fn log2(x: f32) -> f32 {
    // Bring subnormals into the normal range: x · 2²³.
    let (x, bias) = if x < f32::MIN_POSITIVE {
        (x * 8_388_608.0, 23.0)
    } else {
        (x, 0.0)
    };
    let bits = x.to_bits();
    let exponent = ((bits >> 23) & 0xff) as i32 - 127;
    // Mantissa in [1, 2), then folded into [√½, √2) so that |s| ≤ 0.172.
    let m = f32::from_bits((bits & 0x007f_ffff) | 0x3f80_0000);
    let (m, exponent) = if m > std::f32::consts::SQRT_2 {
        (m * 0.5, exponent + 1)
    } else {
        (m, exponent)
    };
    // ln m = 2 artanh s = 2 (s + s³/3 + s⁵/5 + s⁷/7 + s⁹/9), s = (m − 1)/(m + 1).
    let s = (m - 1.0) / (m + 1.0);
    let s2 = s * s;
    let series = 1.0 + s2 * (1.0 / 3.0 + s2 * (0.2 + s2 * (1.0 / 7.0 + s2 * (1.0 / 9.0))));
    (exponent as f32 - bias) + (2.0 * INV_LN2) * (s * series)
}

/// 2^y for finite y; underflows to 0 below −126 and saturates at 2^127·(2 − ε).
#[inline(always)]
pub fn exp2(y: f32) -> f32 {
    // max/min (not clamp) so that NaN becomes −126 rather than staying NaN.
    #[allow(clippy::manual_clamp)]
    let y = y.max(-126.0).min(127.0);
    let k = floor(y + 0.5);
    let f = y - k; // [−0.5, 0.5]
    // 2^f = e^(f ln 2): Taylor to degree 7 (remainder < 6·10⁻⁹ on [−½, ½]).
    const C1: f32 = std::f32::consts::LN_2;
    const C2: f32 = 0.240_226_5; // ln²2 / 2
    const C3: f32 = 0.055_504_11; // ln³2 / 6
    const C4: f32 = 0.009_618_129; // ln⁴2 / 24
    const C5: f32 = 0.001_333_355_8; // ln⁵2 / 120
    const C6: f32 = 0.000_154_035_3; // ln⁶2 / 720
    const C7: f32 = 0.000_015_252_734; // ln⁷2 / 5040
    let p = 1.0 + f * (C1 + f * (C2 + f * (C3 + f * (C4 + f * (C5 + f * (C6 + f * C7))))));
    let k = lattice(k);
    // 2^k built from its exponent bits; 0 at the bottom of the range.
    let scale = f32::from_bits(((k.max(-126) + 127) as u32) << 23);
    if k <= -126 { 0.0 } else { p * scale }
}

/// x^e for x in [0, 1] and e ≥ 0 (0^e = 0 for e > 0, x^0 = 1 for x > 0): the
/// powers of bias, gain, opacity and specular highlights.
#[inline(always)]
pub fn pow01(x: f32, e: f32) -> f32 {
    if x <= 0.0 {
        return if e == 0.0 { 1.0 } else { 0.0 };
    }
    if x >= 1.0 {
        return 1.0;
    }
    exp2(e * log2(x))
}

/// `pow01(x, e)` lane by lane on `isa`, one exponent for all.
#[inline]
pub fn pow01_on(isa: Isa, x: &Lanes, e: f32) -> Lanes {
    match isa {
        Isa::Scalar => x.map(|x| pow01(x, e)),
        // SAFETY: a scene only carries a path that `Isa::available` reported,
        // and `Scene::with_isa` refuses the others.
        #[cfg(target_arch = "x86_64")]
        Isa::Sse41 => unsafe { x86::pow01_sse41(x, e) },
        #[cfg(target_arch = "x86_64")]
        Isa::Avx2 => unsafe { x86::pow01_avx2(x, e) },
        #[cfg(not(target_arch = "x86_64"))]
        _ => pow01_on(Isa::Scalar, x, e),
    }
}

/// `pow01` written lane-parallel: both branches computed, then selected, so the
/// loop vectorises; each lane's value is the scalar one.
#[inline(always)]
pub(crate) fn pow01_lanes(x: &Lanes, e: f32) -> Lanes {
    let mut out = [0.0; LANES];
    for l in 0..LANES {
        let v = x[l];
        // Keep log2's argument in range for the lanes whose result is discarded.
        let safe = if v > 0.0 && v < 1.0 { v } else { 0.5 };
        let p = exp2(e * log2(safe));
        out[l] = if v <= 0.0 {
            if e == 0.0 { 1.0 } else { 0.0 }
        } else if v >= 1.0 {
            1.0
        } else {
            p
        };
    }
    out
}

#[cfg(target_arch = "x86_64")]
mod x86 {
    use super::*;

    #[target_feature(enable = "avx2")]
    pub(super) fn pow01_avx2(x: &Lanes, e: f32) -> Lanes {
        pow01_lanes(x, e)
    }

    #[target_feature(enable = "sse4.1")]
    pub(super) fn pow01_sse41(x: &Lanes, e: f32) -> Lanes {
        pow01_lanes(x, e)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::random::SplitMix64;

    fn rel(a: f32, b: f64) -> f64 {
        if b == 0.0 {
            f64::from(a).abs()
        } else {
            ((f64::from(a) - b) / b).abs()
        }
    }

    #[test]
    fn log2_and_exp2_are_accurate() {
        let mut r = SplitMix64::new(3);
        let mut worst_log = 0.0f64;
        let mut worst_exp = 0.0f64;
        for _ in 0..200_000 {
            let x = r.next_f32() * 4.0 + 1e-7;
            let exact = f64::from(x).log2();
            // Absolute error near x = 1, relative elsewhere.
            let err = (f64::from(log2(x)) - exact).abs() / exact.abs().max(1.0);
            worst_log = worst_log.max(err);
            let y = r.next_f32() * 60.0 - 40.0;
            worst_exp = worst_exp.max(rel(exp2(y), f64::from(y).exp2()));
        }
        assert!(worst_log < 2e-7, "log2: {worst_log:e}");
        assert!(worst_exp < 3e-7, "exp2: {worst_exp:e}");
        assert_eq!(log2(1.0), 0.0);
        assert_eq!(log2(0.5), -1.0);
        assert_eq!(exp2(0.0), 1.0);
        assert_eq!(exp2(-3.0), 0.125);
        assert!((log2(1e-40) - (1e-40f64).log2() as f32).abs() < 1e-4);
    }

    #[test]
    fn pow01_matches_powf() {
        let mut r = SplitMix64::new(4);
        // Relative error, over the range that reaches an image (results ≥ 10⁻³),
        // and scaled by 1 + |e·log₂ x| everywhere (y = e·log₂ x is rounded to f32).
        let (mut worst, mut worst_scaled) = (0.0f64, 0.0f64);
        for _ in 0..400_000 {
            let x = r.next_f32();
            let e = r.next_f32() * 8.0;
            let exact = f64::from(x).powf(f64::from(e));
            if exact > 1e-30 {
                let err = rel(pow01(x, e), exact);
                worst_scaled = worst_scaled.max(err / (1.0 + exact.log2().abs()));
                if exact >= 1e-3 {
                    worst = worst.max(err);
                }
            }
        }
        assert!(worst < 1e-6, "pow01: {worst:e}");
        assert!(worst_scaled < 2e-7, "pow01 (scaled): {worst_scaled:e}");
        assert_eq!(pow01(0.0, 2.0), 0.0);
        assert_eq!(pow01(0.0, 0.0), 1.0);
        assert_eq!(pow01(1.0, 3.0), 1.0);
        assert_eq!(pow01(0.25, 0.5), 0.5);
    }

    #[test]
    fn every_path_gives_the_scalar_powers() {
        let mut r = SplitMix64::new(9);
        for _ in 0..20_000 {
            // The exact powers' edge cases in every round.
            let x = [r.next_f32(), 0.0, 1.0, 1e-30, 0.5, 0.999, 2.0, -1.0];
            let e = r.next_f32() * 6.0;
            let reference = pow01_on(Isa::Scalar, &x, e);
            for isa in Isa::available() {
                let got = pow01_on(isa, &x, e);
                assert_eq!(
                    got.map(f32::to_bits),
                    reference.map(f32::to_bits),
                    "{isa:?}"
                );
            }
        }
    }
}
