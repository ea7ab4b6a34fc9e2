//! Noise, the paper's single controllable stochastic function (section 2.3).
//!
//! `noise` is a sum of pseudorandom spline knots, one per point of the integer
//! lattice. The knot at (i, j, k) is a linear gradient Γ_ijk weighted in each
//! dimension by the cubic drop-off ω(t) = 2|t|³ − 3|t|² + 1 (|t| < 1, else 0), so
//! only the 2³ lattice points around x contribute:
//!
//! ```text
//! noise(x) = Σ ω(u) ω(v) ω(w) (Γ_ijk · (u, v, w)),   (u, v, w) = x − (i, j, k)
//! ```
//!
//! Γ_ijk = G[φ(i + φ(j + φ(k)))] with φ(i) = P[i mod n]: P a pseudorandom
//! permutation of 0..n and G n unit vectors chosen by the paper's three-step
//! Monte Carlo method, n = 256, both built from a seed ([`Noise::new`]).
//!
//! Only IEEE basic operations are used (no fused multiply-add, no libm), in a
//! fixed order, so every CPU computes the same bits.

use std::sync::LazyLock;

use glam::Vec3;

use crate::random::SplitMix64;

/// The seed of the default tables (the year of the paper).
pub const DEFAULT_SEED: u64 = 1989;

/// Offset c of vector noise `[noise(x − c), noise(x), noise(x + c)]`: large enough
/// (and not a multiple of the table period 256) that the three components meet
/// entirely different knots and so are uncorrelated.
pub const VNOISE_OFFSET: Vec3 = Vec3::new(107.3, 113.7, 127.9);

/// The paper's noise tables: permutation P and gradients G, n = 256.
#[derive(Clone, Debug, PartialEq)]
pub struct Noise {
    /// P: a pseudorandom permutation of 0..256.
    perm: [u8; 256],
    /// G: 256 pseudorandom unit vectors, uniform on the sphere.
    gradients: [Vec3; 256],
}

impl Default for Noise {
    fn default() -> Self {
        Noise::new(DEFAULT_SEED)
    }
}

impl Noise {
    /// Builds P (Fisher–Yates) and G (three-step Monte Carlo: draw each coordinate
    /// uniformly from [−1, 1]; if |v| > 1 draw again; normalise) from `seed`.
    pub fn new(seed: u64) -> Noise {
        let mut rng = SplitMix64::new(seed);
        let mut perm = [0u8; 256];
        for (i, p) in perm.iter_mut().enumerate() {
            *p = i as u8;
        }
        for i in (1..256).rev() {
            let j = rng.below(i as u32 + 1) as usize;
            perm.swap(i, j);
        }
        let mut gradients = [Vec3::ZERO; 256];
        for g in gradients.iter_mut() {
            *g = loop {
                let v = Vec3::new(
                    2.0 * rng.next_f32() - 1.0,
                    2.0 * rng.next_f32() - 1.0,
                    2.0 * rng.next_f32() - 1.0,
                );
                let len2 = v.length_squared();
                // (2): reject outside the unit ball (and the degenerate centre).
                if len2 <= 1.0 && len2 > 1e-6 {
                    break v / len2.sqrt();
                }
            };
        }
        Noise { perm, gradients }
    }

    /// φ(i) = P[i mod n].
    #[inline(always)]
    fn phi(&self, i: i32) -> i32 {
        i32::from(self.perm[(i & 255) as usize])
    }

    /// Γ_ijk = G[φ(i + φ(j + φ(k)))].
    #[inline(always)]
    fn gradient(&self, i: i32, j: i32, k: i32) -> Vec3 {
        let h = self.phi(i.wrapping_add(self.phi(j.wrapping_add(self.phi(k)))));
        self.gradients[(h & 255) as usize]
    }

    /// Gradient noise at `p`, roughly in [−1, 1]; exactly 0 at every lattice point.
    #[inline]
    pub fn noise(&self, p: Vec3) -> f32 {
        let (fx, fy, fz) = (floor(p.x), floor(p.y), floor(p.z));
        let (i, j, k) = (lattice(fx), lattice(fy), lattice(fz));
        let (u, v, w) = (p.x - fx, p.y - fy, p.z - fz);
        // ω for the near (t) and far (t − 1) knot along each axis.
        let wx = [omega(u), omega(u - 1.0)];
        let wy = [omega(v), omega(v - 1.0)];
        let wz = [omega(w), omega(w - 1.0)];
        let mut sum = 0.0;
        for dk in 0..2 {
            let z = w - dk as f32;
            for dj in 0..2 {
                let y = v - dj as f32;
                let wyz = wy[dj as usize] * wz[dk as usize];
                for di in 0..2 {
                    let x = u - di as f32;
                    let g =
                        self.gradient(i.wrapping_add(di), j.wrapping_add(dj), k.wrapping_add(dk));
                    let dot = g.x * x + g.y * y + g.z * z;
                    sum += wx[di as usize] * wyz * dot;
                }
            }
        }
        sum
    }

    /// [`Noise::noise`] at [`LANES`] points at once (x, y and z of each point in
    /// separate arrays), with exactly the same operations per lane, so each lane
    /// has the bits `noise` gives. The arithmetic is written lane-parallel for the
    /// compiler to vectorise; the table look-ups stay scalar loads (gathers are
    /// slower than loads on the CPUs we run on). Compiled once per instruction
    /// set by [`crate::simd`].
    #[inline(always)]
    pub(crate) fn noise_lanes(&self, px: &Lanes, py: &Lanes, pz: &Lanes) -> Lanes {
        let mut cell = [[0i32; LANES]; 3];
        let mut frac = [[0f32; LANES]; 3];
        for l in 0..LANES {
            let (fx, fy, fz) = (floor(px[l]), floor(py[l]), floor(pz[l]));
            cell[0][l] = lattice(fx);
            cell[1][l] = lattice(fy);
            cell[2][l] = lattice(fz);
            frac[0][l] = px[l] - fx;
            frac[1][l] = py[l] - fy;
            frac[2][l] = pz[l] - fz;
        }
        // Gradient indices of the 8 corners, corner c = di + 2·dj + 4·dk.
        let mut hash = [[0u8; LANES]; 8];
        for l in 0..LANES {
            let (i, j, k) = (cell[0][l], cell[1][l], cell[2][l]);
            for dk in 0..2 {
                let pk = self.phi(k.wrapping_add(dk));
                for dj in 0..2 {
                    let pj = self.phi(j.wrapping_add(dj).wrapping_add(pk));
                    for di in 0..2 {
                        hash[(di + 2 * dj + 4 * dk) as usize][l] =
                            self.perm[(i.wrapping_add(di).wrapping_add(pj) & 255) as usize];
                    }
                }
            }
        }
        let mut sum = [0f32; LANES];
        for dk in 0..2usize {
            for dj in 0..2usize {
                for di in 0..2usize {
                    let corner = &hash[di + 2 * dj + 4 * dk];
                    for l in 0..LANES {
                        let (u, v, w) = (frac[0][l], frac[1][l], frac[2][l]);
                        let x = u - di as f32;
                        let y = v - dj as f32;
                        let z = w - dk as f32;
                        let wyz = omega(y) * omega(z);
                        let g = &self.gradients[corner[l] as usize];
                        let dot = g.x * x + g.y * y + g.z * z;
                        sum[l] += omega(x) * wyz * dot;
                    }
                }
            }
        }
        sum
    }

    /// Vector noise `[noise(x − c), noise(x), noise(x + c)]`, c = [`VNOISE_OFFSET`].
    #[inline]
    pub fn vnoise(&self, p: Vec3) -> Vec3 {
        Vec3::new(
            self.noise(p - VNOISE_OFFSET),
            self.noise(p),
            self.noise(p + VNOISE_OFFSET),
        )
    }

    /// Turbulence `Σ_{i<octaves} |noise(2^i x)| / 2^i` (Perlin 1985). Clamp the
    /// octave count to the sampling rate with [`clamped_octaves`].
    #[inline]
    pub fn turbulence(&self, p: Vec3, octaves: u32) -> f32 {
        let mut sum = 0.0;
        let mut scale = 1.0;
        for _ in 0..octaves {
            sum += self.noise(p * scale).abs() / scale;
            scale *= 2.0;
        }
        sum
    }
}

/// Points per batch in the vectorised paths.
pub const LANES: usize = 8;

/// One f32 per lane.
pub type Lanes = [f32; LANES];

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

/// ω(t) = 2|t|³ − 3|t|² + 1 for |t| < 1, else 0: the knot's cubic drop-off.
#[inline(always)]
fn omega(t: f32) -> f32 {
    let t = t.abs();
    if t < 1.0 {
        (2.0 * t - 3.0) * t * t + 1.0
    } else {
        0.0
    }
}

/// The paper's frequency clamping: how many octaves of a sum whose base frequency
/// is `frequency` (octave i has frequency `frequency · 2^i`, period
/// `1 / (frequency · 2^i)`) to keep so that the finest period is no smaller than
/// the marching `step`. At most `requested`, at least 1 when `requested ≥ 1`.
pub fn clamped_octaves(frequency: f32, step: f32, requested: u32) -> u32 {
    let mut n = 0;
    let mut period = 1.0 / frequency;
    while n < requested && (n == 0 || period >= step) {
        n += 1;
        period /= 2.0;
    }
    n
}

static DEFAULT: LazyLock<Noise> = LazyLock::new(Noise::default);

/// The paper's noise with the default tables ([`DEFAULT_SEED`]).
#[inline]
pub fn perlin(p: Vec3) -> f32 {
    DEFAULT.noise(p)
}

/// Vector noise with the default tables.
#[inline]
pub fn vnoise(p: Vec3) -> Vec3 {
    DEFAULT.vnoise(p)
}

/// Turbulence with the default tables.
#[inline]
pub fn turbulence(p: Vec3, octaves: u32) -> f32 {
    DEFAULT.turbulence(p, octaves)
}

/// `perlin` at every point of `points`, into `out` (the same bits, point by
/// point), [`LANES`] points at a time on the fastest instruction set this CPU has.
///
/// # Panics
/// When `out` is shorter than `points`.
pub fn perlin_batch(points: &[Vec3], out: &mut [f32]) {
    assert!(
        out.len() >= points.len(),
        "perlin_batch: output shorter than input"
    );
    let isa = crate::simd::Isa::detect();
    for (p, o) in points.chunks(LANES).zip(out.chunks_mut(LANES)) {
        let (mut x, mut y, mut z) = ([0.0; LANES], [0.0; LANES], [0.0; LANES]);
        for (l, q) in p.iter().enumerate() {
            (x[l], y[l], z[l]) = (q.x, q.y, q.z);
        }
        let n = isa.noise(&DEFAULT, &x, &y, &z);
        o[..p.len()].copy_from_slice(&n[..p.len()]);
    }
}

/// Perlin's permutation from the reference implementation of improved noise.
const IMPROVED_PERMUTATION: [u8; 256] = [
    151, 160, 137, 91, 90, 15, 131, 13, 201, 95, 96, 53, 194, 233, 7, 225, 140, 36, 103, 30, 69,
    142, 8, 99, 37, 240, 21, 10, 23, 190, 6, 148, 247, 120, 234, 75, 0, 26, 197, 62, 94, 252, 219,
    203, 117, 35, 11, 32, 57, 177, 33, 88, 237, 149, 56, 87, 174, 20, 125, 136, 171, 168, 68, 175,
    74, 165, 71, 134, 139, 48, 27, 166, 77, 146, 158, 231, 83, 111, 229, 122, 60, 211, 133, 230,
    220, 105, 92, 41, 55, 46, 245, 40, 244, 102, 143, 54, 65, 25, 63, 161, 1, 216, 80, 73, 209, 76,
    132, 187, 208, 89, 18, 169, 200, 196, 135, 130, 116, 188, 159, 86, 164, 100, 109, 198, 173,
    186, 3, 64, 52, 217, 226, 250, 124, 123, 5, 202, 38, 147, 118, 126, 255, 82, 85, 212, 207, 206,
    59, 227, 47, 16, 58, 17, 182, 189, 28, 42, 223, 183, 170, 213, 119, 248, 152, 2, 44, 154, 163,
    70, 221, 153, 101, 155, 167, 43, 172, 9, 129, 22, 39, 253, 19, 98, 108, 110, 79, 113, 224, 232,
    178, 185, 112, 104, 218, 246, 97, 228, 251, 34, 242, 193, 238, 210, 144, 12, 191, 179, 162,
    241, 81, 51, 145, 235, 249, 14, 239, 107, 49, 192, 214, 31, 181, 199, 106, 157, 184, 84, 204,
    176, 115, 121, 50, 45, 127, 4, 150, 254, 138, 236, 205, 93, 222, 114, 67, 29, 24, 72, 243, 141,
    128, 195, 78, 66, 215, 61, 156, 180,
];

/// Perlin's improved noise (SIGGRAPH 2002), exactly as his reference Java
/// `ImprovedNoise`: quintic fade, the fixed permutation, 12 gradient directions.
pub fn improved(x: f64, y: f64, z: f64) -> f64 {
    let p = |i: i32| i32::from(IMPROVED_PERMUTATION[(i & 255) as usize]);
    let (fx, fy, fz) = (x.floor(), y.floor(), z.floor());
    let (cx, cy, cz) = ((fx as i32) & 255, (fy as i32) & 255, (fz as i32) & 255);
    let (x, y, z) = (x - fx, y - fy, z - fz);
    let (u, v, w) = (fade(x), fade(y), fade(z));
    let a = p(cx) + cy;
    let (aa, ab) = (p(a) + cz, p(a + 1) + cz);
    let b = p(cx + 1) + cy;
    let (ba, bb) = (p(b) + cz, p(b + 1) + cz);
    lerp(
        w,
        lerp(
            v,
            lerp(u, grad(p(aa), x, y, z), grad(p(ba), x - 1.0, y, z)),
            lerp(
                u,
                grad(p(ab), x, y - 1.0, z),
                grad(p(bb), x - 1.0, y - 1.0, z),
            ),
        ),
        lerp(
            v,
            lerp(
                u,
                grad(p(aa + 1), x, y, z - 1.0),
                grad(p(ba + 1), x - 1.0, y, z - 1.0),
            ),
            lerp(
                u,
                grad(p(ab + 1), x, y - 1.0, z - 1.0),
                grad(p(bb + 1), x - 1.0, y - 1.0, z - 1.0),
            ),
        ),
    )
}

#[inline]
fn fade(t: f64) -> f64 {
    t * t * t * (t * (t * 6.0 - 15.0) + 10.0)
}

#[inline]
fn lerp(t: f64, a: f64, b: f64) -> f64 {
    a + t * (b - a)
}

#[inline]
fn grad(hash: i32, x: f64, y: f64, z: f64) -> f64 {
    let h = hash & 15;
    let u = if h < 8 { x } else { y };
    let v = if h < 4 {
        y
    } else if h == 12 || h == 14 {
        x
    } else {
        z
    };
    (if h & 1 == 0 { u } else { -u }) + (if h & 2 == 0 { v } else { -v })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn points(n: usize, seed: u64, scale: f32) -> impl Iterator<Item = Vec3> {
        let mut r = SplitMix64::new(seed);
        (0..n).map(move |_| {
            Vec3::new(r.next_f32() - 0.5, r.next_f32() - 0.5, r.next_f32() - 0.5) * scale
        })
    }

    #[test]
    fn zero_at_lattice_points() {
        let n = Noise::default();
        for i in -5..5 {
            for j in -5..5 {
                for k in [-300, -1, 0, 1, 7, 255, 256, 1000] {
                    assert_eq!(n.noise(Vec3::new(i as f32, j as f32, k as f32)), 0.0);
                }
            }
        }
    }

    #[test]
    fn bounded() {
        let n = Noise::default();
        let max = points(100_000, 1, 200.0)
            .map(|p| n.noise(p).abs())
            .fold(0.0f32, f32::max);
        // Observed about 0.6 with the default tables.
        assert!(max < 1.0, "max |noise| = {max}");
        assert!(max > 0.3, "noise is suspiciously flat: {max}");
    }

    #[test]
    fn tables_are_a_permutation_and_unit_vectors() {
        let n = Noise::new(42);
        let mut seen = [false; 256];
        for &p in &n.perm {
            seen[p as usize] = true;
        }
        assert!(seen.iter().all(|&s| s));
        for g in &n.gradients {
            assert!((g.length() - 1.0).abs() < 1e-6);
        }
    }

    #[test]
    fn seeded() {
        let (a, b, c) = (Noise::new(5), Noise::new(5), Noise::new(6));
        assert_eq!(a, b);
        let p = Vec3::new(0.3, 1.7, -2.2);
        assert_eq!(a.noise(p), b.noise(p));
        assert_ne!(a.noise(p), c.noise(p));
        assert_eq!(perlin(p), Noise::default().noise(p));
    }

    #[test]
    fn continuous() {
        let n = Noise::default();
        for p in points(1000, 2, 20.0) {
            let d = (n.noise(p) - n.noise(p + Vec3::splat(1e-3))).abs();
            assert!(d < 1e-2, "jump of {d} at {p}");
        }
    }

    #[test]
    fn vnoise_components_are_uncorrelated_noise() {
        let n = Noise::default();
        let p = Vec3::new(0.37, 0.52, 0.91);
        let v = n.vnoise(p);
        assert_eq!(v.y, n.noise(p));
        assert!(v.x != v.y && v.y != v.z && v.x != v.z);
        assert_eq!(v, vnoise(p));
    }

    #[test]
    fn turbulence_sums_octaves() {
        let n = Noise::default();
        for p in points(200, 3, 10.0) {
            assert_eq!(n.turbulence(p, 1), n.noise(p).abs());
            assert_eq!(n.turbulence(p, 0), 0.0);
            let mut last = 0.0;
            for o in 1..8 {
                let t = n.turbulence(p, o);
                assert!(t >= last);
                last = t;
            }
            assert_eq!(turbulence(p, 4), n.turbulence(p, 4));
        }
    }

    #[test]
    fn frequency_clamping() {
        // Periods 1, 0.5, 0.25, 0.125 are ≥ 0.1; 0.0625 is not.
        assert_eq!(clamped_octaves(1.0, 0.1, 16), 4);
        assert_eq!(clamped_octaves(1.0, 0.1, 2), 2);
        assert_eq!(clamped_octaves(100.0, 0.1, 6), 1);
        assert_eq!(clamped_octaves(1.0, 0.1, 0), 0);
        assert_eq!(clamped_octaves(2.0, 0.0234, 8), 5);
    }

    #[test]
    #[allow(clippy::approx_constant)] // 3.14 is Perlin's reference input, not π
    fn improved_noise_reference_values() {
        // Perlin's reference ImprovedNoise: noise(3.14, 42, 7).
        assert!((improved(3.14, 42.0, 7.0) - 0.136_919_958_784_000_12).abs() < 1e-9);
        assert_eq!(improved(1.0, 2.0, 3.0), 0.0);
        assert_eq!(improved(-4.0, 0.0, 300.0), 0.0);
        let mut seen = [false; 256];
        for &p in &IMPROVED_PERMUTATION {
            seen[p as usize] = true;
        }
        assert!(
            seen.iter().all(|&s| s),
            "the permutation has 256 distinct entries"
        );
        for p in points(10_000, 4, 100.0) {
            let v = improved(f64::from(p.x), f64::from(p.y), f64::from(p.z));
            assert!(v.abs() <= 1.0);
        }
    }

    #[test]
    fn batch_equals_point_by_point() {
        let pts: Vec<Vec3> = points(1001, 5, 50.0).collect();
        let mut out = vec![0.0; pts.len()];
        perlin_batch(&pts, &mut out);
        for (p, o) in pts.iter().zip(&out) {
            assert_eq!(perlin(*p).to_bits(), o.to_bits());
        }
    }

    #[test]
    fn never_panics_on_extreme_input() {
        let n = Noise::default();
        for p in [
            Vec3::splat(f32::NAN),
            Vec3::splat(f32::INFINITY),
            Vec3::splat(-3.0e38),
            Vec3::splat(3.0e38),
        ] {
            let _ = n.noise(p);
            let _ = n.turbulence(p, 8);
        }
        let _ = improved(f64::NAN, f64::INFINITY, -1e300);
    }
}
