//! The instruction sets the hot kernels are compiled for, chosen at run time,
//! and the lanes they work on.
//!
//! The bottom layer of the crate: it uses nothing of it. A kernel is written
//! once, lane-parallel over [`LANES`] points, and [`per_isa!`] compiles it
//! once per instruction set behind `#[target_feature]` (AVX-512, AVX2 and
//! SSE4.1 on x86-64; NEON on aarch64) beside its scalar form, and writes the
//! dispatch on an [`Isa`]: the one place where a `#[target_feature]` function
//! is called, after the CPU was checked ([`Isa::runs_here`]). The kernels'
//! helpers are `#[inline(always)]`, so each copy holds its path's code; the
//! rest of the program is built for the baseline (SSE2 on x86-64). Every path
//! does the same IEEE operations in the same order per lane (no FMA: Rust
//! never contracts `a * b + c`, and the fused instructions are never asked
//! for), so every [`Isa`] gives the same bits; `tests/` renders whole images
//! on each and compares them.
//!
//! The choice is a field of the scene (`Scene::isa`), not global state: a
//! test can force any path, and a farm of mixed CPUs stays exact.
//!
//! Architecture invariant: no `#[target_feature]` function is written by
//! hand outside this module; [`per_isa!`] writes them all.

/// Points per batch in the vectorised paths: 16 (a ray's chunk of samples,
/// or the gradient neighbours of 8 samples). Fewer calls of the kernels per
/// ray outweigh the lanes evaluated past a ray's end (docs/benchmark-log.md).
pub const LANES: usize = 16;

/// One f32 per lane.
pub type Lanes = [f32; LANES];

/// Lanes per block: an AVX register of f32. Lane code that takes a mask of
/// live lanes skips a block of [`BLOCK`] lanes with none live
/// ([`live_blocks`]).
pub const BLOCK: usize = 8;

/// Which lanes of a mask `live` (bit l for lane l) to compute, by whole
/// blocks of [`BLOCK`]: all [`LANES`] (both blocks live, one register on
/// AVX-512), the first or the second block only, or none.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum LiveBlocks {
    /// Both blocks.
    All,
    /// Lanes 0 .. [`BLOCK`] only.
    First,
    /// Lanes [`BLOCK`] .. [`LANES`] only.
    Second,
    /// No lane.
    None,
}

/// The blocks of `live` to compute.
#[inline(always)]
pub fn live_blocks(live: u32) -> LiveBlocks {
    const MASK: u32 = (1 << BLOCK) - 1;
    match (live & MASK != 0, (live >> BLOCK) & MASK != 0) {
        (true, true) => LiveBlocks::All,
        (true, false) => LiveBlocks::First,
        (false, true) => LiveBlocks::Second,
        (false, false) => LiveBlocks::None,
    }
}

/// The mask of the lanes where `test` holds (bit l for lane l): each lane's
/// bit, then their union, two loops that vectorise (a compare and a few
/// shifts and ors per register, not a chain of 16).
#[inline(always)]
pub fn lane_mask(test: impl Fn(usize) -> bool) -> u32 {
    let mut bits = [0u32; LANES];
    for (l, bit) in bits.iter_mut().enumerate() {
        *bit = u32::from(test(l)) << l;
    }
    bits.iter().fold(0, |m, b| m | b)
}

/// The mask of the lanes of `v` that are not +0 (bit l for lane l), on
/// `isa`'s registers where it is a SIMD path (inlined into that path's
/// copy): the mask [`lane_mask`] gives.
#[inline(always)]
pub fn nonzero_mask(isa: Isa, v: &Lanes) -> u32 {
    #[cfg(target_arch = "x86_64")]
    if matches!(isa, Isa::Avx2 | Isa::Avx512) {
        use std::arch::x86_64::*;
        // SAFETY: `isa` is AVX2 or AVX-512 only in `per_isa!`'s copies for
        // them, run once the CPU was checked, and this code is inlined into
        // them; the loads are of 8 lanes within arrays of LANES.
        return unsafe {
            let zero = _mm256_setzero_si256();
            let mut m = 0u32;
            for h in 0..LANES / 8 {
                let bits = _mm256_loadu_si256(v.as_ptr().add(8 * h).cast());
                let zeros = _mm256_castsi256_ps(_mm256_cmpeq_epi32(bits, zero));
                m |= (_mm256_movemask_ps(zeros) as u32) << (8 * h);
            }
            !m & ((1u64 << LANES) - 1) as u32
        };
    }
    let _ = isa;
    lane_mask(|l| v[l].to_bits() != 0)
}

/// The mask of the lanes of `v` below `bound` (bit l for lane l; false for
/// NaN), on `isa`'s registers where it is a SIMD path (inlined into that
/// path's copy): the mask [`lane_mask`] gives.
#[inline(always)]
pub fn below_mask(isa: Isa, v: &Lanes, bound: f32) -> u32 {
    #[cfg(target_arch = "x86_64")]
    if matches!(isa, Isa::Avx2 | Isa::Avx512) {
        use std::arch::x86_64::*;
        // SAFETY: as in `nonzero_mask`.
        return unsafe {
            let b = _mm256_set1_ps(bound);
            let mut m = 0u32;
            for h in 0..LANES / 8 {
                let x = _mm256_loadu_ps(v.as_ptr().add(8 * h));
                let below = _mm256_cmp_ps::<_CMP_LT_OQ>(x, b);
                m |= (_mm256_movemask_ps(below) as u32) << (8 * h);
            }
            m
        };
    }
    let _ = isa;
    lane_mask(|l| v[l] < bound)
}

/// An instruction-set path for the batch kernels.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum Isa {
    /// One point at a time through the scalar functions: the reference.
    Scalar,
    /// Lane-parallel code compiled for SSE4.1 (4-wide).
    Sse41,
    /// Lane-parallel code compiled for AVX2 (8-wide).
    Avx2,
    /// Lane-parallel code compiled for AVX-512 F, BW and VBMI (16-wide: all
    /// [`LANES`] in one register; Ice Lake, Sapphire Rapids, Zen 4 and
    /// later).
    Avx512,
    /// Lane-parallel code compiled for NEON (aarch64, 4-wide).
    Neon,
}

impl Isa {
    /// The path the renderer takes on this CPU: the widest it supports. The
    /// 16-wide path looks up the noise's permutation by byte permutes
    /// (VBMI), which leaves it 0.89× the CPU time of AVX2 for the fur and
    /// 0.88× for the noisy sphere on the Xeon measured (docs/benchmark-log.md).
    /// `Scene::set_isa` asks for another (`ISA=avx2` in the examples).
    pub fn detect() -> Isa {
        Isa::available().into_iter().last().unwrap_or(Isa::Scalar)
    }

    /// Every path this CPU can run, slowest first.
    pub fn available() -> Vec<Isa> {
        [Isa::Scalar, Isa::Neon, Isa::Sse41, Isa::Avx2, Isa::Avx512]
            .into_iter()
            .filter(|isa| isa.runs_here())
            .collect()
    }

    /// Whether this CPU can run the path.
    pub fn is_available(self) -> bool {
        self.runs_here()
    }

    /// Whether this CPU has the path's features: the check [`per_isa!`]'s
    /// dispatch makes before it calls a `#[target_feature]` copy (one load
    /// and a test of the paths found once, [`available_paths`]).
    #[inline(always)]
    pub fn runs_here(self) -> bool {
        self == Isa::Scalar || available_paths() & (1 << self as u32) != 0
    }

    /// Whether this CPU has the path's features, asked of the CPU.
    fn detected(self) -> bool {
        match self {
            Isa::Scalar => true,
            #[cfg(target_arch = "x86_64")]
            Isa::Sse41 => std::is_x86_feature_detected!("sse4.1"),
            #[cfg(target_arch = "x86_64")]
            Isa::Avx2 => std::is_x86_feature_detected!("avx2"),
            #[cfg(target_arch = "x86_64")]
            Isa::Avx512 => {
                std::is_x86_feature_detected!("avx512f")
                    && std::is_x86_feature_detected!("avx512bw")
                    && std::is_x86_feature_detected!("avx512vbmi")
            }
            #[cfg(target_arch = "aarch64")]
            Isa::Neon => std::arch::is_aarch64_feature_detected!("neon"),
            #[allow(unreachable_patterns)]
            _ => false,
        }
    }

    /// The path's name, as `--isa` spells it.
    pub fn name(self) -> &'static str {
        match self {
            Isa::Scalar => "scalar",
            Isa::Sse41 => "sse4.1",
            Isa::Avx2 => "avx2",
            Isa::Avx512 => "avx512",
            Isa::Neon => "neon",
        }
    }
}

/// The paths this CPU runs, bit `isa as u32` for each (and bit 31 once
/// they are found): asked of the CPU at the first call, then one load.
#[inline(always)]
fn available_paths() -> u32 {
    use std::sync::atomic::{AtomicU32, Ordering};
    static PATHS: AtomicU32 = AtomicU32::new(0);
    let paths = PATHS.load(Ordering::Relaxed);
    if paths != 0 {
        return paths;
    }
    let paths = find_paths();
    PATHS.store(paths, Ordering::Relaxed);
    paths
}

/// The bits of [`available_paths`], asked of the CPU.
#[cold]
#[inline(never)]
fn find_paths() -> u32 {
    [Isa::Scalar, Isa::Neon, Isa::Sse41, Isa::Avx2, Isa::Avx512]
        .into_iter()
        .filter(|isa| isa.detected())
        .fold(1 << 31, |bits, isa| bits | 1 << isa as u32)
}

/// A kernel's copies per instruction set and its dispatch on an [`Isa`], as
/// an expression (the body of the function that dispatches):
///
/// ```ignore
/// per_isa!(isa, (d: &Density = self, x: &Points = x, field: &Field = field) -> Lanes {
///     scalar => each(x, |p| d.eval(p, field)),
///     lanes => d.eval_lanes_simd(x, field, lanes),
/// })
/// ```
///
/// writes the scalar form and one `#[target_feature]` copy of the lane form
/// per SIMD path (in the copy, `lanes` is that path's [`Isa`], a constant the
/// inlined helpers branch on), each a function of the listed parameters, and
/// calls the copy of `isa` with the listed values. A path this CPU lacks
/// takes the scalar form (every path gives the same bits), so no caller can
/// reach a copy whose features the CPU does not have. Adding a path is one
/// copy and one arm here.
macro_rules! per_isa {
    ($isa:expr, ($($arg:ident: $ty:ty = $val:expr),* $(,)?) -> $ret:ty {
        scalar => $scalar:expr,
        $lanes:ident => $simd:expr $(,)?
    }) => {{
        #[inline(always)]
        #[allow(clippy::too_many_arguments, clippy::unused_unit, unused_variables)]
        fn scalar($($arg: $ty),*) -> $ret {
            $scalar
        }
        #[cfg(target_arch = "x86_64")]
        #[target_feature(enable = "avx512f,avx512bw,avx512vbmi")]
        #[allow(clippy::too_many_arguments, clippy::unused_unit, unused_variables)]
        fn avx512($($arg: $ty),*) -> $ret {
            let $lanes = $crate::math::simd::Isa::Avx512;
            $simd
        }
        #[cfg(target_arch = "x86_64")]
        #[target_feature(enable = "avx2")]
        #[allow(clippy::too_many_arguments, clippy::unused_unit, unused_variables)]
        fn avx2($($arg: $ty),*) -> $ret {
            let $lanes = $crate::math::simd::Isa::Avx2;
            $simd
        }
        #[cfg(target_arch = "x86_64")]
        #[target_feature(enable = "sse4.1")]
        #[allow(clippy::too_many_arguments, clippy::unused_unit, unused_variables)]
        fn sse41($($arg: $ty),*) -> $ret {
            let $lanes = $crate::math::simd::Isa::Sse41;
            $simd
        }
        #[cfg(target_arch = "aarch64")]
        #[target_feature(enable = "neon")]
        #[allow(clippy::too_many_arguments, clippy::unused_unit, unused_variables)]
        fn neon($($arg: $ty),*) -> $ret {
            let $lanes = $crate::math::simd::Isa::Neon;
            $simd
        }
        let isa: $crate::math::simd::Isa = $isa;
        $(let $arg: $ty = $val;)*
        // SAFETY: the copy compiled for a path is called only in that path's
        // arm, once `Isa::runs_here` found the path's features on this CPU;
        // `scalar` is a safe function.
        unsafe {
            match isa {
                #[cfg(target_arch = "x86_64")]
                $crate::math::simd::Isa::Avx512 if isa.runs_here() => avx512($($arg),*),
                #[cfg(target_arch = "x86_64")]
                $crate::math::simd::Isa::Avx2 if isa.runs_here() => avx2($($arg),*),
                #[cfg(target_arch = "x86_64")]
                $crate::math::simd::Isa::Sse41 if isa.runs_here() => sse41($($arg),*),
                #[cfg(target_arch = "aarch64")]
                $crate::math::simd::Isa::Neon if isa.runs_here() => neon($($arg),*),
                _ => scalar($($arg),*),
            }
        }
    }};
}
pub(crate) use per_isa;

/// The x, y and z of 4 `Vec3`s (3 loads and 6 shuffles).
#[cfg(target_arch = "x86_64")]
#[inline(always)]
pub(crate) fn deinterleave(
    p: &[glam::Vec3],
) -> (
    std::arch::x86_64::__m128,
    std::arch::x86_64::__m128,
    std::arch::x86_64::__m128,
) {
    use std::arch::x86_64::*;
    const _: () = assert!(std::mem::size_of::<glam::Vec3>() == 12);
    assert!(p.len() == 4);
    // SAFETY: 4 `Vec3`s are 12 contiguous f32 (glam's `Vec3` is `repr(C)` of
    // 3 f32), loaded as 3 unaligned vectors. SSE is part of the x86-64 baseline.
    unsafe {
        let f = p.as_ptr().cast::<f32>();
        let (a, b, c) = (
            _mm_loadu_ps(f),
            _mm_loadu_ps(f.add(4)),
            _mm_loadu_ps(f.add(8)),
        );
        // a = x0 y0 z0 x1, b = y1 z1 x2 y2, c = z2 x3 y3 z3.
        let x = _mm_shuffle_ps::<0b10_00_10_00>(
            _mm_shuffle_ps::<0b11_11_00_00>(a, a),
            _mm_shuffle_ps::<0b01_01_10_10>(b, c),
        );
        let y = _mm_shuffle_ps::<0b10_00_10_00>(
            _mm_shuffle_ps::<0b00_00_01_01>(a, b),
            _mm_shuffle_ps::<0b10_10_11_11>(b, c),
        );
        let z = _mm_shuffle_ps::<0b10_00_10_00>(
            _mm_shuffle_ps::<0b01_01_10_10>(a, b),
            _mm_shuffle_ps::<0b11_11_00_00>(c, c),
        );
        (x, y, z)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// `per_isa!` runs the copy of a path this CPU has, and the scalar form
    /// for every other path, so that no caller reaches a copy whose features
    /// the CPU lacks.
    #[test]
    fn per_isa_runs_the_copy_of_an_available_path_only() {
        fn which(isa: Isa) -> Option<Isa> {
            per_isa!(isa, () -> Option<Isa> {
                scalar => None,
                lanes => Some(lanes),
            })
        }
        for isa in [Isa::Scalar, Isa::Sse41, Isa::Avx2, Isa::Avx512, Isa::Neon] {
            let expected = (isa != Isa::Scalar && Isa::available().contains(&isa)).then_some(isa);
            assert_eq!(which(isa), expected, "{isa:?}");
            assert_eq!(isa.runs_here(), isa.detected(), "{isa:?}");
        }
    }

    /// The masks by compare and `movemask` are [`lane_mask`]'s on every
    /// path, at ±0, NaN, subnormals, the bound itself and its neighbours.
    #[test]
    fn masks_on_every_path_are_lane_masks() {
        let special = [
            0.0,
            -0.0,
            f32::NAN,
            -f32::NAN,
            f32::MIN_POSITIVE / 2.0,
            -f32::MIN_POSITIVE / 2.0,
            1.0,
            1.0f32.next_down(),
            1.0f32.next_up(),
            0.5,
            -0.5,
            f32::INFINITY,
            -f32::INFINITY,
            2.0,
            f32::MAX,
            -1.0,
        ];
        // A xorshift, so that the bottom layer's tests use nothing above it.
        let mut state = 0x9e37_79b9_u32;
        for round in 0..200 {
            let v: Lanes = std::array::from_fn(|l| {
                state ^= state << 13;
                state ^= state >> 17;
                state ^= state << 5;
                let pick = if round % 2 == 0 {
                    l * 7 + round
                } else {
                    state as usize
                };
                special[pick % special.len()]
            });
            for isa in Isa::available() {
                assert_eq!(
                    nonzero_mask(isa, &v),
                    lane_mask(|l| v[l].to_bits() != 0),
                    "{isa:?}: {v:?}"
                );
                assert_eq!(
                    below_mask(isa, &v, 1.0),
                    lane_mask(|l| v[l] < 1.0),
                    "{isa:?}: {v:?}"
                );
            }
        }
    }
}
