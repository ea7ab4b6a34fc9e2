//! `pow` for the hot paths (bias, gain, opacity, specular), from IEEE basic
//! operations only.
//!
//! `libm::powf` is exact to an ulp but costs ~20 ns and branches on every special
//! case. Here `x^e = 2^(e·log₂ x)` with a fixed polynomial for each factor: the
//! same additions and multiplications in the same order on every CPU and in
//! every lane of the SIMD paths, so the bits never depend on the machine.
//!
//! Accuracy (tested against f64 in `tests` below): `log2` within 1.6·10⁻⁵
//! (absolute) from a division-free polynomial, `exp2` within 3·10⁻⁷
//! (relative); `pow01`, and through it `bias` and `gain` over the whole
//! range of their parameter and argument, within [`POW01_MAX_ERROR`]
//! (absolute). An 8-bit output level is 4·10⁻³.

use crate::math::simd::{Isa, LANES, Lanes};

/// The largest absolute error of [`pow01`] for x in [0, 1] and e in [0, 8],
/// and of `bias` and `gain` for every parameter in (0, 1) (tested below).
pub const POW01_MAX_ERROR: f64 = 5e-5;

/// ⌊x⌋, exactly as `f32::floor` for every finite x except −0, which gives
/// +0 (a lattice coordinate never carries a sign bit), from a conversion and
/// a compare: the SSE2 baseline of the scalar path has no rounding
/// instruction and would call libm. The SIMD kernels of noise (`floor4`,
/// `floor8` in `noise.rs`) use the rounding instruction plus +0.0, which
/// gives the same bits.
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

/// ⌊v⌋ and its integer, as `floor` and `lattice` give them, for v within
/// ±127.5 (finite), without their range tests: the truncation fits an i32
/// and is ⌊v⌋ or ⌊v⌋ + 1, and one compare gives both.
#[inline(always)]
fn floor_small(v: f32) -> (f32, i32) {
    // SAFETY: v is finite and |v| ≤ 127.5, within i32's range.
    let truncated = unsafe { v.to_int_unchecked::<i32>() };
    let above = truncated as f32 > v;
    (
        truncated as f32 - if above { 1.0 } else { 0.0 },
        truncated - i32::from(above),
    )
}

/// log₂ x for finite x > 0 (subnormals included). Not for 0, negatives or NaN:
/// callers clamp first. No division: the mantissa m, folded into [√½, √2),
/// goes through `t·P(t)`, t = m − 1, P of degree 4 fitted for the least
/// maximum error; |error| < 1.6·10⁻⁵ (absolute, tested below).
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
    // Mantissa in [1, 2), then folded into [√½, √2) so that |t| ≤ 0.415.
    let m = f32::from_bits((bits & 0x007f_ffff) | 0x3f80_0000);
    let (m, exponent) = if m > std::f32::consts::SQRT_2 {
        (m * 0.5, exponent + 1)
    } else {
        (m, exponent)
    };
    let t = m - 1.0;
    const L1: f32 = 1.442_578;
    const L2: f32 = -0.720_241_84;
    const L3: f32 = 0.486_687_4;
    const L4: f32 = -0.394_574_17;
    const L5: f32 = 0.252_651_45;
    // Estrin's scheme: the pairs first, so that the chain of dependent
    // operations is six long, not ten.
    let t2 = t * t;
    let p = t * ((L1 + t * L2) + t2 * ((L3 + t * L4) + t2 * L5));
    (exponent as f32 - bias) + p
}

/// 2^y for finite y; underflows to 0 below −126 and saturates at 2^127·(2 − ε).
/// 2^f on f ∈ [−½, ½] is a degree-5 polynomial fitted for the least maximum
/// relative error (< 3·10⁻⁷ with f32 rounding, tested below).
#[inline(always)]
pub fn exp2(y: f32) -> f32 {
    // max/min (not clamp) so that NaN becomes −126 rather than staying NaN.
    #[allow(clippy::manual_clamp)]
    let y = y.max(-126.0).min(127.0);
    // y + ½ is finite and within ±127.5.
    let (k, n) = floor_small(y + 0.5);
    let f = y - k; // [−0.5, 0.5]
    const C1: f32 = std::f32::consts::LN_2; // the fitted value rounds to it
    const C2: f32 = 0.240_222_35;
    const C3: f32 = 0.055_503_08;
    const C4: f32 = 0.009_671_88;
    const C5: f32 = 0.001_340_72;
    // Estrin's scheme, as in `log2`.
    let f2 = f * f;
    let p = 1.0 + f * ((C1 + f * C2) + f2 * ((C3 + f * C4) + f2 * C5));
    // 2^k built from its exponent bits; 0 at the bottom of the range.
    let scale = f32::from_bits(((n.max(-126) + 127) as u32) << 23);
    if n <= -126 { 0.0 } else { p * scale }
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
    pow01_on_live(isa, x, e, u32::MAX)
}

/// [`pow01_on`] at the lanes set in `live`: on a SIMD path a block of lanes
/// none of which is live is skipped (and comes out 1).
#[inline]
pub fn pow01_on_live(isa: Isa, x: &Lanes, e: f32, live: u32) -> Lanes {
    crate::math::simd::per_isa!(isa, (x: &Lanes = x, e: f32 = e, live: u32 = live) -> Lanes {
        scalar => x.map(|x| pow01(x, e)),
        lanes => pow01_lanes_live(x, e, live),
    })
}

/// `pow01` written lane-parallel (both branches computed, then selected, so
/// the loop vectorises; each lane's value is the scalar one), in the blocks
/// of lanes with a lane set in `live` ([`crate::math::simd::live_blocks`]); the
/// other blocks come out 1.
#[inline(always)]
pub(crate) fn pow01_lanes_live(x: &Lanes, e: f32, live: u32) -> Lanes {
    use crate::math::simd::{BLOCK, LiveBlocks, live_blocks};
    let mut out = [1.0; LANES];
    match live_blocks(live) {
        LiveBlocks::All => pow01_block(x, &mut out, e),
        LiveBlocks::First => pow01_block(
            &x.as_chunks::<BLOCK>().0[0],
            &mut out.as_chunks_mut::<BLOCK>().0[0],
            e,
        ),
        LiveBlocks::Second => pow01_block(
            &x.as_chunks::<BLOCK>().0[1],
            &mut out.as_chunks_mut::<BLOCK>().0[1],
            e,
        ),
        LiveBlocks::None => {}
    }
    out
}

/// `pow01` of N lanes into `out`, every lane computed and selected.
#[inline(always)]
fn pow01_block<const N: usize>(x: &[f32; N], out: &mut [f32; N], e: f32) {
    for l in 0..N {
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
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::math::random::SplitMix64;

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
        assert!(worst_log < 1.6e-5, "log2: {worst_log:e}");
        assert!(worst_exp < 3e-7, "exp2: {worst_exp:e}");
        assert_eq!(log2(1.0), 0.0);
        assert_eq!(log2(0.5), -1.0);
        assert_eq!(exp2(0.0), 1.0);
        assert_eq!(exp2(-3.0), 0.125);
        assert!((log2(1e-40) - (1e-40f64).log2() as f32).abs() < 1e-4);
    }

    /// `floor_small` is `floor` and `lattice` over its whole domain (every
    /// f32 within ±127.5 at a step of 2⁻¹⁰, each ± an ulp, the integers and
    /// halves among them), so exp2's bits are those of the two.
    #[test]
    fn floor_small_is_floor_and_lattice() {
        let mut v = -127.5f32;
        while v <= 127.5 {
            for v in [v, v.next_down().max(-127.5), v.next_up().min(127.5), -0.0] {
                let k = floor(v);
                assert_eq!(floor_small(v), (k, lattice(k)), "floor_small({v})");
                assert_eq!(
                    floor_small(v).0.to_bits(),
                    k.to_bits(),
                    "the sign of 0 at {v}"
                );
            }
            v += 1.0 / 1024.0;
        }
    }

    #[test]
    fn pow01_matches_powf() {
        let mut r = SplitMix64::new(4);
        // Absolute error over the unit interval, for exponents up to 8.
        let mut worst = 0.0f64;
        for _ in 0..400_000 {
            let x = r.next_f32();
            let e = r.next_f32() * 8.0;
            let exact = f64::from(x).powf(f64::from(e));
            worst = worst.max((f64::from(pow01(x, e)) - exact).abs());
        }
        assert!(worst < POW01_MAX_ERROR, "pow01: {worst:e}");
        assert_eq!(pow01(0.0, 2.0), 0.0);
        assert_eq!(pow01(0.0, 0.0), 1.0);
        assert_eq!(pow01(1.0, 3.0), 1.0);
        assert_eq!(pow01(0.25, 0.5), 0.5);
    }

    /// bias and gain over the whole range of their parameter, (0, 1), and of
    /// t, [0, 1]: the largest absolute error against f64 is below
    /// [`POW01_MAX_ERROR`].
    #[test]
    fn bias_and_gain_are_accurate_over_their_whole_range() {
        use crate::field::shaping::{bias, gain};
        let exact_bias = |b: f64, t: f64| t.powf(b.ln() / 0.5f64.ln());
        let exact_gain = |g: f64, t: f64| {
            if t < 0.5 {
                exact_bias(1.0 - g, 2.0 * t) / 2.0
            } else {
                1.0 - exact_bias(1.0 - g, 2.0 - 2.0 * t) / 2.0
            }
        };
        let (mut worst_bias, mut worst_gain) = (0.0f64, 0.0f64);
        // Parameters from 2⁻²⁰ to 1 − 2⁻²⁰, t on a grid with its ends.
        let params = (1..=2000)
            .map(|i| i as f32 / 2001.0)
            .chain([1.0 / 1_048_576.0, 1.0 - 1.0 / 1_048_576.0]);
        for p in params {
            for i in 0..=1000 {
                let t = i as f32 / 1000.0;
                let (pd, td) = (f64::from(p), f64::from(t));
                worst_bias = worst_bias.max((f64::from(bias(p, t)) - exact_bias(pd, td)).abs());
                worst_gain = worst_gain.max((f64::from(gain(p, t)) - exact_gain(pd, td)).abs());
            }
        }
        assert!(worst_bias < POW01_MAX_ERROR, "bias: {worst_bias:e}");
        assert!(worst_gain < POW01_MAX_ERROR, "gain: {worst_gain:e}");
    }

    #[test]
    fn every_path_gives_the_scalar_powers() {
        let mut r = SplitMix64::new(9);
        for _ in 0..20_000 {
            // The exact powers' edge cases in every round.
            let edges = [0.0, 1.0, 1e-30, 0.5, 0.999, 2.0, -1.0];
            let x: Lanes = std::array::from_fn(|l| edges.get(l).copied().unwrap_or(r.next_f32()));
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
