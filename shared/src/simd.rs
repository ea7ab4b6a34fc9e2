//! The instruction sets the hot kernels are compiled for, chosen at run time.
//!
//! Each kernel (noise, `pow`) is written once, lane-parallel over [`LANES`]
//! points (noise with SSE intrinsics, 8 lanes in AVX registers on AVX2), and
//! compiled here for AVX2 and SSE4.1 behind `#[target_feature]`. The hot paths
//! that call them have their own `#[target_feature]` copies with the kernels
//! inlined (`density::x86`, `march::x86`); the rest of the program is built for
//! the x86-64 baseline (SSE2). Every path does
//! the same IEEE operations in the same order per lane (no FMA: Rust never
//! contracts `a * b + c`), so [`Isa::Scalar`], [`Isa::Sse41`] and [`Isa::Avx2`]
//! give the same bits; `tests/` renders whole images on each and compares them.
//!
//! The choice is a field of the scene ([`crate::Scene::isa`]), not global
//! state: a test can force any path, and a farm of mixed CPUs stays exact.

use glam::Vec3;

use crate::fastmath;
use crate::noise::{LANES, Lanes, Noise};

/// An instruction-set path for the batch kernels.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum Isa {
    /// One point at a time through the scalar functions: the reference.
    Scalar,
    /// Lane-parallel code compiled for SSE4.1 (4-wide).
    Sse41,
    /// Lane-parallel code compiled for AVX2 (8-wide).
    Avx2,
}

impl Isa {
    /// The fastest path this CPU supports.
    pub fn detect() -> Isa {
        Isa::available().into_iter().last().unwrap_or(Isa::Scalar)
    }

    /// Every path this CPU can run, slowest first.
    pub fn available() -> Vec<Isa> {
        let mut v = vec![Isa::Scalar];
        #[cfg(target_arch = "x86_64")]
        {
            if std::is_x86_feature_detected!("sse4.1") {
                v.push(Isa::Sse41);
            }
            if std::is_x86_feature_detected!("avx2") {
                v.push(Isa::Avx2);
            }
        }
        v
    }

    /// Whether this CPU can run the path.
    pub fn is_available(self) -> bool {
        Isa::available().contains(&self)
    }

    /// The path's name, as `--isa` spells it.
    pub fn name(self) -> &'static str {
        match self {
            Isa::Scalar => "scalar",
            Isa::Sse41 => "sse4.1",
            Isa::Avx2 => "avx2",
        }
    }

    /// `noise` at each of the lanes' points.
    #[inline]
    pub fn noise(self, n: &Noise, x: &Lanes, y: &Lanes, z: &Lanes) -> Lanes {
        match self {
            Isa::Scalar => {
                let mut out = [0.0; LANES];
                for l in 0..LANES {
                    out[l] = n.noise(Vec3::new(x[l], y[l], z[l]));
                }
                out
            }
            // SAFETY: a scene only carries a path that `Isa::available` reported,
            // and `Scene::with_isa` refuses the others.
            #[cfg(target_arch = "x86_64")]
            Isa::Sse41 => unsafe { x86::noise_sse41(n, x, y, z) },
            #[cfg(target_arch = "x86_64")]
            Isa::Avx2 => unsafe { x86::noise_avx2(n, x, y, z) },
            #[cfg(not(target_arch = "x86_64"))]
            _ => Isa::Scalar.noise(n, x, y, z),
        }
    }

    /// `noise` at every point of `points`, into `out` (at least as long).
    pub fn noise_batch(self, n: &Noise, points: &[Vec3], out: &mut [f32]) {
        match self {
            Isa::Scalar => {
                for (o, &p) in out.iter_mut().zip(points) {
                    *o = n.noise(p);
                }
            }
            // SAFETY: as in `noise`.
            #[cfg(target_arch = "x86_64")]
            Isa::Sse41 => unsafe { x86::noise_batch_sse41(n, points, out) },
            #[cfg(target_arch = "x86_64")]
            Isa::Avx2 => unsafe { x86::noise_batch_avx2(n, points, out) },
            #[cfg(not(target_arch = "x86_64"))]
            _ => Isa::Scalar.noise_batch(n, points, out),
        }
    }

    /// `pow01(x, e)` lane by lane, one exponent for all.
    #[inline]
    pub fn pow01(self, x: &Lanes, e: f32) -> Lanes {
        match self {
            Isa::Scalar => x.map(|x| fastmath::pow01(x, e)),
            // SAFETY: as in `noise`.
            #[cfg(target_arch = "x86_64")]
            Isa::Sse41 => unsafe { x86::pow01_sse41(x, e) },
            #[cfg(target_arch = "x86_64")]
            Isa::Avx2 => unsafe { x86::pow01_avx2(x, e) },
            #[cfg(not(target_arch = "x86_64"))]
            _ => Isa::Scalar.pow01(x, e),
        }
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
        let p = fastmath::exp2(e * fastmath::log2(safe));
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

/// The x, y and z of 4 `Vec3`s (3 loads and 6 shuffles).
#[cfg(target_arch = "x86_64")]
#[inline(always)]
fn deinterleave(
    p: &[Vec3],
) -> (
    std::arch::x86_64::__m128,
    std::arch::x86_64::__m128,
    std::arch::x86_64::__m128,
) {
    use std::arch::x86_64::*;
    const _: () = assert!(std::mem::size_of::<Vec3>() == 12);
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

/// `noise` over a slice, 4 points at a time: 4 `Vec3`s are 3 loads, turned
/// into x, y and z vectors by shuffles (the last batch padded).
#[cfg(target_arch = "x86_64")]
#[inline(always)]
fn noise_batch_lanes(n: &Noise, points: &[Vec3], out: &mut [f32]) {
    use std::arch::x86_64::*;
    let out = &mut out[..points.len()];
    let mut quads = points.chunks_exact(4);
    let mut outs = out.chunks_exact_mut(4);
    for (p, o) in (&mut quads).zip(&mut outs) {
        // SAFETY: `o` holds 4 f32; SSE is part of the x86-64 baseline.
        unsafe {
            let (x, y, z) = deinterleave(p);
            _mm_storeu_ps(o.as_mut_ptr(), n.noise4(x, y, z));
        }
    }
    let rest = quads.remainder();
    let (mut x, mut y, mut z) = ([0.0; LANES], [0.0; LANES], [0.0; LANES]);
    for (l, q) in rest.iter().enumerate() {
        (x[l], y[l], z[l]) = (q.x, q.y, q.z);
    }
    let v = n.noise_lanes(&x, &y, &z);
    let o = outs.into_remainder();
    o.copy_from_slice(&v[..o.len()]);
}

#[cfg(target_arch = "x86_64")]
mod x86 {
    use std::arch::x86_64::*;

    use super::*;

    #[target_feature(enable = "avx2")]
    pub(super) fn noise_batch_avx2(n: &Noise, points: &[Vec3], out: &mut [f32]) {
        let out = &mut out[..points.len()];
        let mut eights = points.chunks_exact(8);
        let mut outs = out.chunks_exact_mut(8);
        for (p, o) in (&mut eights).zip(&mut outs) {
            let ((x0, y0, z0), (x1, y1, z1)) = (deinterleave(&p[..4]), deinterleave(&p[4..]));
            // SAFETY: this function is compiled for AVX2 (and only called on
            // CPUs that have it); `o` holds 8 f32.
            unsafe {
                let n = n.noise8(
                    _mm256_set_m128(x1, x0),
                    _mm256_set_m128(y1, y0),
                    _mm256_set_m128(z1, z0),
                );
                _mm256_storeu_ps(o.as_mut_ptr(), n);
            }
        }
        noise_batch_lanes(n, eights.remainder(), outs.into_remainder())
    }

    #[target_feature(enable = "sse4.1")]
    pub(super) fn noise_batch_sse41(n: &Noise, points: &[Vec3], out: &mut [f32]) {
        noise_batch_lanes(n, points, out)
    }

    #[target_feature(enable = "avx2")]
    pub(super) fn noise_avx2(n: &Noise, x: &Lanes, y: &Lanes, z: &Lanes) -> Lanes {
        n.noise_lanes_on(Isa::Avx2, x, y, z)
    }

    #[target_feature(enable = "sse4.1")]
    pub(super) fn noise_sse41(n: &Noise, x: &Lanes, y: &Lanes, z: &Lanes) -> Lanes {
        n.noise_lanes(x, y, z)
    }

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

    #[test]
    fn every_path_gives_the_scalar_bits() {
        let n = Noise::new(77);
        let mut r = SplitMix64::new(9);
        for round in 0..20_000 {
            let scale = if round % 2 == 0 { 8.0 } else { 3.0e4 };
            let mut p = [[0.0f32; LANES]; 3];
            for axis in &mut p {
                for v in axis.iter_mut() {
                    *v = (r.next_f32() - 0.5) * scale;
                }
            }
            // Lattice points and the exact powers' edge cases too.
            if round == 0 {
                p[0] = [0.0, -0.0, 1.0, -1.0, 255.0, 256.0, -300.0, 1.0e9];
            }
            let x = [r.next_f32(), 0.0, 1.0, 1e-30, 0.5, 0.999, 2.0, -1.0];
            let e = r.next_f32() * 6.0;
            let reference = Isa::Scalar.noise(&n, &p[0], &p[1], &p[2]);
            let pow_reference = Isa::Scalar.pow01(&x, e);
            for isa in Isa::available() {
                let got = isa.noise(&n, &p[0], &p[1], &p[2]);
                assert_eq!(
                    got.map(f32::to_bits),
                    reference.map(f32::to_bits),
                    "{isa:?}"
                );
                let got = isa.pow01(&x, e);
                assert_eq!(
                    got.map(f32::to_bits),
                    pow_reference.map(f32::to_bits),
                    "{isa:?}"
                );
            }
        }
    }
}
