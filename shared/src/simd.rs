//! The instruction sets the hot kernels are compiled for, chosen at run time.
//!
//! Each kernel (noise, `pow`) is written once, lane-parallel over [`LANES`]
//! points, and compiled here for AVX2 and SSE4.1 behind `#[target_feature]`; the
//! rest of the program is built for the x86-64 baseline (SSE2). Every path does
//! the same IEEE operations in the same order per lane (no FMA: Rust never
//! contracts `a * b + c`), so [`Isa::Scalar`], [`Isa::Sse41`] and [`Isa::Avx2`]
//! give the same bits; `tests/` renders whole images on each and compares them.
//!
//! The choice is a field of the scene ([`crate::Scene::isa`]), not global
//! state: a test can force any path, and a farm of mixed CPUs stays exact.

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
                    out[l] = n.noise(glam::Vec3::new(x[l], y[l], z[l]));
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
fn pow01_lanes(x: &Lanes, e: f32) -> Lanes {
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

#[cfg(target_arch = "x86_64")]
mod x86 {
    use super::*;

    #[target_feature(enable = "avx2")]
    pub(super) fn noise_avx2(n: &Noise, x: &Lanes, y: &Lanes, z: &Lanes) -> Lanes {
        n.noise_lanes(x, y, z)
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
