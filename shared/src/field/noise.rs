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
//!
//! # Speed
//!
//! Beside P and G, [`Noise`] keeps tables derived from them: the hash's inner
//! two levels for every (j, k), the four corners' bytes of a cell in one
//! `u32` (`cells`, shared by the scenes of a seed), and `G[P[m]]` as aligned
//! 16-byte rows. So a cell's hash is one look-up (one gather for 8 lanes) and
//! a corner's gradient one load. The lane kernels do exactly
//! [`Noise::noise`]'s arithmetic on 4, 8 or 16 lanes. Where the points lie
//! along a ray at a step fine for the frequency (`runs`), the 8-lane kernel
//! first tests whether every lane lies in the cell of lane 0 or of lane 7, and
//! then takes each lane's gradients from those two cells' rows by permutes.
//! The measurements are in docs/benchmark-log.md.

use std::sync::{Arc, LazyLock, Mutex};

use glam::Vec3;

use crate::math::fastmath::{floor, lattice};
use crate::math::random::SplitMix64;
use crate::math::simd::{Isa, Lanes};
#[cfg(target_arch = "x86_64")]
use crate::math::simd::{LANES, deinterleave};

use crate::desc::DEFAULT_SEED;

/// Offset c of vector noise `[noise(x − c), noise(x), noise(x + c)]`: large enough
/// (and not a multiple of the table period 256) that the three components meet
/// entirely different knots and so are uncorrelated.
pub const VNOISE_OFFSET: Vec3 = Vec3::new(107.3, 113.7, 127.9);

/// A bound on |noise| that holds for every seed, √(3/4) widened by 1% for
/// rounding. With W_c = ω(u_c)ω(v_c)ω(w_c) the weight and d_c the offset of
/// corner c (the weights are ≥ 0 and sum to 1: ω(t) + ω(1 − t) = 1 on each
/// axis) and |Γ_c| = 1:
/// |noise| ≤ Σ W_c |Γ_c·d_c| ≤ Σ W_c |d_c| ≤ √(Σ W_c |d_c|²) (Jensen)
/// = √(g(u) + g(v) + g(w)) with g(t) = ω(t)t² + ω(1 − t)(1 − t)², and
/// g(t) − ¼ = (2t − 1)²((2t − 1)² − 2)/4 ≤ 0 on [0, 1].
pub const NOISE_BOUND: f32 = 0.875;

/// The paper's noise tables: permutation P and gradients G, n = 256.
#[derive(Clone)]
pub struct Noise {
    /// P: a pseudorandom permutation of 0..256.
    perm: [u8; 256],
    /// G: 256 pseudorandom unit vectors, uniform on the sphere.
    gradients: [Vec3; 256],
    /// `G[P[m mod n]]` for m < 2n, padded to 16 bytes: the last level of the
    /// hash and the gradient in one aligned load, and the rows of corners
    /// (i, ·, ·) and (i + 1, ·, ·) next to each other (derived from `perm` and
    /// `gradients`).
    gradient_of: [Row; 512],
    /// The inner two levels of the hash for every (j, k) in 0..n: entry
    /// `k·n + j` holds φ(j + dj + φ(k + dk)) in byte dj + 2·dk, so that one
    /// load gives the rows of a cell's four corners (0, dj, dk) (derived
    /// from `perm`).
    /// Shared by every `Noise` of the same seed ([`cells_of`]).
    cells: Arc<Cells>,
}

/// The table of [`Noise`]'s `cells`: one entry per (j, k).
type Cells = [u32; 1 << 16];

/// Scenes of one seed share their table of cells (256 KiB): a process
/// that loads many scenes one after another (the known-answer probe loads
/// every gallery scene) builds it once per seed. The tables of the last
/// [`CELLS_KEPT`] seeds are kept, the latest last.
static CELLS: Mutex<Vec<(u64, Arc<Cells>)>> = Mutex::new(Vec::new());

/// How many seeds' tables [`CELLS`] keeps (2 MiB).
const CELLS_KEPT: usize = 8;

/// The table of cells of `seed`, whose P doubled is `perm2`: the one held
/// already, or built.
fn cells_of(seed: u64, perm2: &[u8; 512]) -> Arc<Cells> {
    // A panic elsewhere while the lock was held leaves the list as valid.
    let mut held = CELLS
        .lock()
        .unwrap_or_else(|poisoned| poisoned.into_inner());
    if let Some(at) = held.iter().position(|(s, _)| *s == seed) {
        let entry = held.remove(at);
        let cells = Arc::clone(&entry.1);
        held.push(entry);
        return cells;
    }
    let mut cells: Box<Cells> = vec![0; 1 << 16]
        .into_boxed_slice()
        .try_into()
        .expect("a table of n² entries");
    for (m, cell) in cells.iter_mut().enumerate() {
        let (j, k) = (m & 255, m >> 8);
        for dk in 0..2 {
            let a = usize::from(perm2[k + dk]);
            for dj in 0..2 {
                *cell |= u32::from(perm2[j + dj + a]) << (8 * (dj + 2 * dk));
            }
        }
    }
    let cells: Arc<Cells> = Arc::from(cells);
    if held.len() == CELLS_KEPT {
        held.remove(0);
    }
    held.push((seed, Arc::clone(&cells)));
    cells
}

/// The tables derived from P and G follow from them.
impl PartialEq for Noise {
    fn eq(&self, other: &Noise) -> bool {
        self.perm == other.perm && self.gradients == other.gradients
    }
}

/// P and G; the tables derived from them are left out.
impl std::fmt::Debug for Noise {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Noise")
            .field("perm", &self.perm)
            .field("gradients", &self.gradients)
            .finish_non_exhaustive()
    }
}

/// A gradient `(x, y, z, 0)` on its own 16-byte line, loaded as one vector.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
#[repr(C, align(16))]
struct Row([f32; 4]);

impl Default for Noise {
    fn default() -> Self {
        Noise::new(DEFAULT_SEED)
    }
}

/// 8 points' cells (i, j, k mod n) and their offsets from the cell's
/// corners with the knots' weights, in AVX registers: what the sums of
/// [`Noise::noise8_on`] run over.
#[cfg(target_arch = "x86_64")]
struct Cells8 {
    i: std::arch::x86_64::__m256i,
    j: std::arch::x86_64::__m256i,
    k: std::arch::x86_64::__m256i,
    /// u and u − 1; v and v − 1; w and w − 1.
    xs: [std::arch::x86_64::__m256; 2],
    ys: [std::arch::x86_64::__m256; 2],
    zs: [std::arch::x86_64::__m256; 2],
    /// ω(u), ω(u − 1); ω(v), ω(v − 1); ω(w), ω(w − 1).
    wx: [std::arch::x86_64::__m256; 2],
    wy: [std::arch::x86_64::__m256; 2],
    wz: [std::arch::x86_64::__m256; 2],
}

#[cfg(target_arch = "x86_64")]
impl Cells8 {
    /// The cells of the points (x, y, z), with `noise`'s operations.
    ///
    /// # Safety
    /// The CPU must have AVX2.
    #[inline(always)]
    unsafe fn of(
        x: std::arch::x86_64::__m256,
        y: std::arch::x86_64::__m256,
        z: std::arch::x86_64::__m256,
    ) -> Cells8 {
        use std::arch::x86_64::*;
        // SAFETY: AVX2 by the caller's contract.
        unsafe {
            let (fx, fy, fz) = (floor8(x), floor8(y), floor8(z));
            let n = _mm256_set1_epi32(255);
            let one = _mm256_set1_ps(1.0);
            let (u, v, w) = (
                _mm256_sub_ps(x, fx),
                _mm256_sub_ps(y, fy),
                _mm256_sub_ps(z, fz),
            );
            let xs = [u, _mm256_sub_ps(u, one)];
            let ys = [v, _mm256_sub_ps(v, one)];
            let zs = [w, _mm256_sub_ps(w, one)];
            Cells8 {
                i: _mm256_and_si256(lattice8(fx), n),
                j: _mm256_and_si256(lattice8(fy), n),
                k: _mm256_and_si256(lattice8(fz), n),
                wx: knots8(xs[0], one),
                wy: knots8(ys[0], one),
                wz: knots8(zs[0], one),
                xs,
                ys,
                zs,
            }
        }
    }
}

/// Σ over the corners of ω ω ω (Γ · offset) for the [`Cells8`] `$c`, Γ's
/// components in lanes from `$gradient` of the corner (0, dj, dk) and di,
/// in `noise`'s order. (A macro: a closure's intrinsics are left as calls,
/// without the target features.)
#[cfg(target_arch = "x86_64")]
macro_rules! sum8 {
    ($c:expr, |$corner:ident, $di:ident| $gradient:expr) => {{
        let c: &Cells8 = $c;
        let mut sum = _mm256_setzero_ps();
        for dk in 0..2 {
            for dj in 0..2 {
                let wyz = _mm256_mul_ps(c.wy[dj], c.wz[dk]);
                for $di in 0..2 {
                    let $corner = dj + 2 * dk;
                    let (gx, gy, gz) = $gradient;
                    let dot = _mm256_add_ps(
                        _mm256_add_ps(_mm256_mul_ps(gx, c.xs[$di]), _mm256_mul_ps(gy, c.ys[dj])),
                        _mm256_mul_ps(gz, c.zs[dk]),
                    );
                    sum = _mm256_add_ps(sum, _mm256_mul_ps(_mm256_mul_ps(c.wx[$di], wyz), dot));
                }
            }
        }
        sum
    }};
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
        // P twice over: φ(a + φ(b)) needs no mask when a and b are reduced.
        let perm2: [u8; 512] = std::array::from_fn(|m| perm[m & 255]);
        let gradient_of = std::array::from_fn(|m| {
            let g = gradients[usize::from(perm[m & 255])];
            Row([g.x, g.y, g.z, 0.0])
        });
        Noise {
            perm,
            gradients,
            gradient_of,
            cells: cells_of(seed, &perm2),
        }
    }

    /// The rows of `gradient_of` of the cell (i, j, k)'s corners (0, dj, dk),
    /// at index dj + 2·dk, all < 511; corner (1, dj, dk)'s is the next row.
    /// Γ_ijk = G[φ(i + φ(j + φ(k)))] with φ(m) = P[m mod n], from one entry
    /// of `cells` rather than 14 look-ups of P. i, j, k are already reduced
    /// mod n.
    #[inline(always)]
    fn corners(&self, i: usize, j: usize, k: usize) -> [usize; 4] {
        // (a + b) mod n = ((a mod n) + b) mod n: `gradient_of` covers the
        // sum of two reduced numbers without a mask.
        let (i, j, k) = (i & 255, j & 255, k & 255);
        let cell = self.cells[(k << 8) | j];
        std::array::from_fn(|c| i + ((cell >> (8 * c)) & 255) as usize)
    }

    /// Gradient noise at `p`, roughly in [−1, 1]; exactly 0 at every lattice point.
    #[inline]
    pub fn noise(&self, p: Vec3) -> f32 {
        let (fx, fy, fz) = (floor(p.x), floor(p.y), floor(p.z));
        let (i, j, k) = (lattice(fx), lattice(fy), lattice(fz));
        let (u, v, w) = (p.x - fx, p.y - fy, p.z - fz);
        // ω for the near (t) and far (t − 1) knot along each axis.
        let wx = [knot(u), knot(1.0 - u)];
        let wy = [knot(v), knot(1.0 - v)];
        let wz = [knot(w), knot(1.0 - w)];
        let corners = self.corners(i as usize, j as usize, k as usize);
        let mut sum = 0.0;
        for dk in 0..2 {
            let z = w - dk as f32;
            for dj in 0..2 {
                let y = v - dj as f32;
                let wyz = wy[dj] * wz[dk];
                for (di, &wxd) in wx.iter().enumerate() {
                    let x = u - di as f32;
                    let g = &self.gradient_of[corners[dj + 2 * dk] + di].0;
                    let dot = g[0] * x + g[1] * y + g[2] * z;
                    sum += wxd * wyz * dot;
                }
            }
        }
        sum
    }

    /// [`Noise::noise`] at `p` and its gradient there, from the derivative of
    /// the drop-off, ω'(t) = 6t(|t| − 1) for |t| < 1: each knot contributes
    /// `∇(ω(u)ω(v)ω(w)) (Γ · (u, v, w)) + ω(u)ω(v)ω(w) Γ`. The value has
    /// exactly the bits of `noise`.
    #[inline]
    pub fn noise_gradient(&self, p: Vec3) -> (f32, Vec3) {
        let (fx, fy, fz) = (floor(p.x), floor(p.y), floor(p.z));
        let (i, j, k) = (lattice(fx), lattice(fy), lattice(fz));
        let (u, v, w) = (p.x - fx, p.y - fy, p.z - fz);
        let wx = [knot(u), knot(1.0 - u)];
        let wy = [knot(v), knot(1.0 - v)];
        let wz = [knot(w), knot(1.0 - w)];
        let sx = [omega_slope(u), omega_slope(u - 1.0)];
        let sy = [omega_slope(v), omega_slope(v - 1.0)];
        let sz = [omega_slope(w), omega_slope(w - 1.0)];
        let corners = self.corners(i as usize, j as usize, k as usize);
        let mut sum = 0.0;
        let mut gradient = Vec3::ZERO;
        for dk in 0..2 {
            let z = w - dk as f32;
            for dj in 0..2 {
                let y = v - dj as f32;
                let wyz = wy[dj] * wz[dk];
                for (di, &wxd) in wx.iter().enumerate() {
                    let x = u - di as f32;
                    let g = &self.gradient_of[corners[dj + 2 * dk] + di].0;
                    let dot = g[0] * x + g[1] * y + g[2] * z;
                    let weight = wxd * wyz;
                    sum += weight * dot;
                    let slope =
                        Vec3::new(sx[di] * wyz, wxd * sy[dj] * wz[dk], wxd * wy[dj] * sz[dk]);
                    gradient += slope * dot + Vec3::new(g[0], g[1], g[2]) * weight;
                }
            }
        }
        (sum, gradient)
    }

    /// [`Noise::noise`] of a point with its Jacobian: the noise and its
    /// gradient with respect to the world point.
    #[inline]
    pub fn noise_dual(&self, p: &crate::math::dual::DualPoint) -> crate::math::dual::Dual {
        let (value, gradient) = self.noise_gradient(p.value());
        p.compose(value, gradient)
    }

    /// [`Noise::noise`] at [`LANES`] points at once (x, y and z of each point in
    /// separate arrays), four at a time in SSE registers, with exactly the
    /// operations of `noise` per lane, so each lane has the bits `noise` gives.
    /// The hash stays scalar (6 byte loads a point: gathers are slower than
    /// loads on the CPUs we run on); each corner's 4 gradients are 4 aligned
    /// loads and a 4×4 transpose. SSE4.1 is used (the floor): it is inlined
    /// only into the SIMD copies of the lane code, never called on
    /// the scalar path.
    #[cfg(target_arch = "x86_64")]
    #[inline(always)]
    pub(crate) fn noise_lanes(&self, px: &Lanes, py: &Lanes, pz: &Lanes) -> Lanes {
        use std::arch::x86_64::*;
        let mut out = [0.0; LANES];
        for h in 0..LANES / 4 {
            // SAFETY: the loads and stores are of 4 f32 within arrays of
            // LANES (h < LANES / 4).
            unsafe {
                let n = self.noise4(
                    _mm_loadu_ps(px.as_ptr().add(4 * h)),
                    _mm_loadu_ps(py.as_ptr().add(4 * h)),
                    _mm_loadu_ps(pz.as_ptr().add(4 * h)),
                );
                _mm_storeu_ps(out.as_mut_ptr().add(4 * h), n);
            }
        }
        out
    }

    /// [`Noise::noise_lanes`] in the copy of the code for `isa` (a SIMD path):
    /// 16 lanes at a time in AVX-512 registers, 8 at a time in AVX registers
    /// on AVX2, 4 at a time otherwise.
    #[inline(always)]
    pub(crate) fn noise_lanes_on(&self, isa: Isa, px: &Lanes, py: &Lanes, pz: &Lanes) -> Lanes {
        self.noise_lanes_live(isa, u32::MAX, px, py, pz)
    }

    /// [`Noise::noise_lanes_on`] at the lanes whose bit is set in `live`: a
    /// register's worth of lanes none of which is live is skipped (and comes
    /// out 0).
    #[inline(always)]
    pub(crate) fn noise_lanes_live(
        &self,
        isa: Isa,
        live: u32,
        px: &Lanes,
        py: &Lanes,
        pz: &Lanes,
    ) -> Lanes {
        self.noise_lanes_along(isa, live, false, px, py, pz)
    }

    /// [`Noise::noise_lanes_live`]; with `runs` (points along a ray at a
    /// step fine for the frequency, [`runs`]), the AVX2 kernel tries the
    /// cells of a register's first and last lanes first
    /// ([`Noise::noise8_on`]).
    #[inline(always)]
    pub(crate) fn noise_lanes_along(
        &self,
        isa: Isa,
        live: u32,
        runs: bool,
        px: &Lanes,
        py: &Lanes,
        pz: &Lanes,
    ) -> Lanes {
        #[cfg(target_arch = "x86_64")]
        if isa == Isa::Avx512 {
            use std::arch::x86_64::*;
            let mut out = [0.0; LANES];
            for h in 0..LANES / 16 {
                if (live >> (16 * h)) & 0xffff == 0 {
                    continue;
                }
                // SAFETY: `isa` is AVX-512 only in `per_isa!`'s AVX-512 copy,
                // run once the CPU was checked, and this code is inlined into
                // it; the loads and stores are of 16 f32 within arrays of
                // LANES.
                unsafe {
                    let n = self.noise16(
                        _mm512_loadu_ps(px.as_ptr().add(16 * h)),
                        _mm512_loadu_ps(py.as_ptr().add(16 * h)),
                        _mm512_loadu_ps(pz.as_ptr().add(16 * h)),
                    );
                    _mm512_storeu_ps(out.as_mut_ptr().add(16 * h), n);
                }
            }
            return out;
        }
        #[cfg(target_arch = "x86_64")]
        if isa == Isa::Avx2 {
            use std::arch::x86_64::*;
            let mut out = [0.0; LANES];
            for h in 0..LANES / 8 {
                if (live >> (8 * h)) & 0xff == 0 {
                    continue;
                }
                // SAFETY: `isa` is AVX2 only in `per_isa!`'s AVX2 copy, run
                // once the CPU was checked, and this code is inlined into it;
                // the loads and stores are of 8 f32 within arrays of LANES.
                unsafe {
                    let n = self.noise8_on(
                        _mm256_loadu_ps(px.as_ptr().add(8 * h)),
                        _mm256_loadu_ps(py.as_ptr().add(8 * h)),
                        _mm256_loadu_ps(pz.as_ptr().add(8 * h)),
                        runs,
                    );
                    _mm256_storeu_ps(out.as_mut_ptr().add(8 * h), n);
                }
            }
            return out;
        }
        let _ = (isa, live, runs);
        self.noise_lanes(px, py, pz)
    }

    /// [`Noise::noise`] at 8 points in AVX registers: [`Noise::noise4`]'s
    /// operations, 8 lanes at a time (gradient rows of lanes l and l + 4 in
    /// the two halves, so the in-half shuffles transpose both at once).
    ///
    /// # Safety
    /// The CPU must have AVX2.
    #[cfg(target_arch = "x86_64")]
    #[inline(always)]
    pub(crate) unsafe fn noise8(
        &self,
        x: std::arch::x86_64::__m256,
        y: std::arch::x86_64::__m256,
        z: std::arch::x86_64::__m256,
    ) -> std::arch::x86_64::__m256 {
        // SAFETY: the caller's contract.
        unsafe { self.noise8_on(x, y, z, false) }
    }

    /// [`Noise::noise8`]; with `runs`, lanes in at most two cells (those of
    /// lanes 0 and 7) take their gradients by permutes, for the same bits.
    /// For points along a ray at a step fine for the frequency
    /// ([`runs`]): elsewhere the test of the cells costs more than it saves.
    ///
    /// # Safety
    /// The CPU must have AVX2.
    #[cfg(target_arch = "x86_64")]
    #[inline(always)]
    pub(crate) unsafe fn noise8_on(
        &self,
        x: std::arch::x86_64::__m256,
        y: std::arch::x86_64::__m256,
        z: std::arch::x86_64::__m256,
        runs: bool,
    ) -> std::arch::x86_64::__m256 {
        // SAFETY: AVX2 by the caller's contract.
        unsafe {
            let c = Cells8::of(x, y, z);
            if runs && let Some(sum) = self.noise8_in_two_cells(&c) {
                return sum;
            }
            self.noise8_gathered(&c)
        }
    }

    /// [`Noise::noise8_on`] where the lanes lie in at most two cells, those
    /// of lanes 0 and 7 (consecutive samples of a ray often do): the two
    /// cells' rows, side by side in one register, give every lane its
    /// gradient by one permute per component, with no transpose. None
    /// where the lanes lie in more cells.
    ///
    /// # Safety
    /// The CPU must have AVX2.
    #[cfg(target_arch = "x86_64")]
    #[inline(always)]
    unsafe fn noise8_in_two_cells(&self, c: &Cells8) -> Option<std::arch::x86_64::__m256> {
        use std::arch::x86_64::*;
        // SAFETY: AVX2 by the caller's contract; the rows are 16-byte
        // aligned and in the table (below).
        unsafe {
            let jk = _mm256_or_si256(_mm256_slli_epi32::<8>(c.k), c.j);
            let cell = _mm256_or_si256(_mm256_slli_epi32::<16>(c.i), jk);
            let first = _mm256_permutevar8x32_epi32(cell, _mm256_setzero_si256());
            let last = _mm256_permutevar8x32_epi32(cell, _mm256_set1_epi32(7));
            let in_first = _mm256_cmpeq_epi32(cell, first);
            let in_last = _mm256_cmpeq_epi32(cell, last);
            if _mm256_movemask_epi8(_mm256_or_si256(in_first, in_last)) != -1 {
                return None;
            }
            let corners_of = |c: i32| {
                let c = c as usize;
                self.corners(c >> 16, c & 255, (c >> 8) & 255)
            };
            let (a, b) = (
                corners_of(_mm256_extract_epi32::<0>(cell)),
                corners_of(_mm256_extract_epi32::<7>(cell)),
            );
            // Component c of a lane's row: element c of the first
            // cell's row (0..4) or of the last's (4..8).
            let pick = _mm256_andnot_si256(in_first, _mm256_set1_epi32(4));
            let picks = [
                pick,
                _mm256_add_epi32(pick, _mm256_set1_epi32(1)),
                _mm256_add_epi32(pick, _mm256_set1_epi32(2)),
            ];
            let rows = self.gradient_of.as_ptr();
            Some(sum8!(c, |corner, di| {
                // SAFETY: `corners` are < 511, so the rows are in the table.
                let both = _mm256_set_m128(
                    _mm_load_ps((*rows.add(b[corner] + di)).0.as_ptr()),
                    _mm_load_ps((*rows.add(a[corner] + di)).0.as_ptr()),
                );
                (
                    _mm256_permutevar8x32_ps(both, picks[0]),
                    _mm256_permutevar8x32_ps(both, picks[1]),
                    _mm256_permutevar8x32_ps(both, picks[2]),
                )
            }))
        }
    }

    /// [`Noise::noise8_on`] by the cells' entries gathered: each lane's
    /// corners, its rows loaded and transposed (rows of lanes l and l + 4 in
    /// the two halves, so the in-half shuffles transpose both at once).
    ///
    /// # Safety
    /// The CPU must have AVX2.
    #[cfg(target_arch = "x86_64")]
    #[inline(always)]
    unsafe fn noise8_gathered(&self, c: &Cells8) -> std::arch::x86_64::__m256 {
        use std::arch::x86_64::*;
        // SAFETY: AVX2 by the caller's contract; the gather reads entries
        // k·n + j < n² of `cells`; the stores are of 8 i32 into arrays of 8;
        // the rows are 16-byte aligned and in the table (below).
        unsafe {
            let n = _mm256_set1_epi32(255);
            let jk = _mm256_or_si256(_mm256_slli_epi32::<8>(c.k), c.j);
            // `corners`: the cells' entries gathered, their bytes added to i.
            let packed = _mm256_i32gather_epi32::<4>(self.cells.as_ptr().cast(), jk);
            let bytes = [
                _mm256_and_si256(packed, n),
                _mm256_and_si256(_mm256_srli_epi32::<8>(packed), n),
                _mm256_and_si256(_mm256_srli_epi32::<16>(packed), n),
                _mm256_srli_epi32::<24>(packed),
            ];
            let mut corners = [[0u32; 8]; 4];
            for (corner, b) in corners.iter_mut().zip(bytes) {
                _mm256_storeu_si256(corner.as_mut_ptr().cast(), _mm256_add_epi32(c.i, b));
            }
            let rows = self.gradient_of.as_ptr();
            sum8!(c, |corner, di| {
                // SAFETY: `corners` are < 511, so the row is in the table.
                // (Macros, not closures: a closure is compiled without the
                // enclosing copy's instruction set, and its intrinsics become
                // calls.)
                macro_rules! row {
                    ($l:expr) => {
                        _mm_load_ps((*rows.add(corners[corner][$l] as usize + di)).0.as_ptr())
                    };
                }
                macro_rules! pair {
                    ($l:expr) => {
                        _mm256_set_m128(row!($l + 4), row!($l))
                    };
                }
                let (r0, r1, r2, r3) = (pair!(0), pair!(1), pair!(2), pair!(3));
                let (lo01, lo23) = (
                    _mm256_castps_pd(_mm256_unpacklo_ps(r0, r1)),
                    _mm256_castps_pd(_mm256_unpacklo_ps(r2, r3)),
                );
                let (hi01, hi23) = (
                    _mm256_castps_pd(_mm256_unpackhi_ps(r0, r1)),
                    _mm256_castps_pd(_mm256_unpackhi_ps(r2, r3)),
                );
                (
                    _mm256_castpd_ps(_mm256_unpacklo_pd(lo01, lo23)),
                    _mm256_castpd_ps(_mm256_unpackhi_pd(lo01, lo23)),
                    _mm256_castpd_ps(_mm256_unpacklo_pd(hi01, hi23)),
                )
            })
        }
    }

    /// [`Noise::corners`] of 16 cells at once, corner (0, dj, dk)'s rows of
    /// every lane at index dj + 2·dk: the look-ups of P as byte permutes
    /// (AVX-512 VBMI) of the 256-byte table held in four registers, so the
    /// sums (j + dj + φ(k + dk)) mod n are byte additions. The same indices.
    ///
    /// # Safety
    /// The CPU must have AVX-512F, BW and VBMI; i, j, k are in 0..256. It
    /// is inlined into the AVX-512 copy of the lane code.
    #[cfg(target_arch = "x86_64")]
    #[inline(always)]
    unsafe fn corners16(
        &self,
        i: std::arch::x86_64::__m512i,
        j: std::arch::x86_64::__m512i,
        k: std::arch::x86_64::__m512i,
    ) -> [[u32; 16]; 4] {
        use std::arch::x86_64::*;
        // SAFETY: AVX-512F/BW/VBMI by the caller's contract; the loads are
        // of 64 bytes within the 256 of P, the stores of 16 u32 into arrays
        // of 16.
        unsafe {
            let p = self.perm.as_ptr();
            let table = [
                _mm512_loadu_si512(p.cast()),
                _mm512_loadu_si512(p.add(64).cast()),
                _mm512_loadu_si512(p.add(128).cast()),
                _mm512_loadu_si512(p.add(192).cast()),
            ];
            // P at 64 byte indices: bits 0–6 pick among 128 bytes, bit 7 the
            // half. (A function inlined into the copy, not a closure: a
            // closure's intrinsics were left as calls.)
            #[inline(always)]
            unsafe fn look(table: &[__m512i; 4], idx: __m512i) -> __m512i {
                // SAFETY: AVX-512F, BW and VBMI by `corners16`'s contract.
                unsafe {
                    let low = _mm512_permutex2var_epi8(table[0], idx, table[1]);
                    let high = _mm512_permutex2var_epi8(table[2], idx, table[3]);
                    _mm512_mask_blend_epi8(_mm512_movepi8_mask(idx), low, high)
                }
            }
            // φ(k) in bytes 0–15, φ(k + 1) in 16–31 (k + 1 = 256 wraps to 0).
            let kb = _mm512_cvtepi32_epi8(k);
            let k1b = _mm512_cvtepi32_epi8(_mm512_add_epi32(k, _mm512_set1_epi32(1)));
            let a = look(
                &table,
                _mm512_inserti32x4::<1>(_mm512_castsi128_si512(kb), k1b),
            );
            // Block dj + 2·dk: j + dj + φ(k + dk), mod 256 as bytes.
            let a = _mm512_shuffle_i32x4::<0b01_01_00_00>(a, a);
            let dj = _mm512_inserti32x4::<3>(
                _mm512_inserti32x4::<1>(_mm512_setzero_si512(), _mm_set1_epi8(1)),
                _mm_set1_epi8(1),
            );
            let jb = _mm512_broadcast_i32x4(_mm512_cvtepi32_epi8(j));
            let b = look(&table, _mm512_add_epi8(_mm512_add_epi8(jb, dj), a));
            let mut out = [[0u32; 16]; 4];
            let blocks = [
                _mm512_castsi512_si128(b),
                _mm512_extracti32x4_epi32::<1>(b),
                _mm512_extracti32x4_epi32::<2>(b),
                _mm512_extracti32x4_epi32::<3>(b),
            ];
            for (o, block) in out.iter_mut().zip(blocks) {
                let m = _mm512_add_epi32(i, _mm512_cvtepu8_epi32(block));
                _mm512_storeu_si512(o.as_mut_ptr().cast(), m);
            }
            out
        }
    }

    /// [`Noise::noise`] at 16 points in AVX-512 registers: [`Noise::noise8`]'s
    /// operations, 16 lanes at a time. A lane's rows for corners (0, dj, dk)
    /// and (1, dj, dk) are adjacent, so one 32-byte load fetches both: 64
    /// loads per 16 points rather than 128. Two lanes' pairs fill a
    /// register, the in-block shuffles transpose 4 registers at once, and
    /// a block shuffle per component sorts the lanes of the two corners. On
    /// Zen 4 this gives 1.12× the points per second of a 16-byte load per
    /// row, which itself gives 2.3× those of gathers (docs/benchmark-log.md).
    ///
    /// # Safety
    /// The CPU must have AVX-512F, BW and VBMI.
    #[cfg(target_arch = "x86_64")]
    #[inline(always)]
    pub(crate) unsafe fn noise16(
        &self,
        x: std::arch::x86_64::__m512,
        y: std::arch::x86_64::__m512,
        z: std::arch::x86_64::__m512,
    ) -> std::arch::x86_64::__m512 {
        use std::arch::x86_64::*;
        // SAFETY: AVX-512F, BW and VBMI by the caller's contract; the rows
        // are 16-byte aligned and in the table (below).
        unsafe {
            let (fx, fy, fz) = (floor16(x), floor16(y), floor16(z));
            let n = _mm512_set1_epi32(255);
            let i = _mm512_and_si512(lattice16(fx), n);
            let j = _mm512_and_si512(lattice16(fy), n);
            let k = _mm512_and_si512(lattice16(fz), n);
            let corners = self.corners16(i, j, k);
            let rows = self.gradient_of.as_ptr();
            let one = _mm512_set1_ps(1.0);
            let (u, v, w) = (
                _mm512_sub_ps(x, fx),
                _mm512_sub_ps(y, fy),
                _mm512_sub_ps(z, fz),
            );
            let xs = [u, _mm512_sub_ps(u, one)];
            let ys = [v, _mm512_sub_ps(v, one)];
            let zs = [w, _mm512_sub_ps(w, one)];
            let wx = knots16(xs[0], one);
            let wy = knots16(ys[0], one);
            let wz = knots16(zs[0], one);
            let mut sum = _mm512_setzero_ps();
            for dk in 0..2 {
                for dj in 0..2 {
                    let wyz = _mm512_mul_ps(wy[dj], wz[dk]);
                    // Rows m and m + 1 of a lane (corners (0, dj, dk) and
                    // (1, dj, dk)) are one 32-byte load. SAFETY: `corners`
                    // are < 511, so both rows are in the table.
                    // Macros: a closure's intrinsics would be calls.
                    macro_rules! pair {
                        ($l:expr) => {
                            _mm256_loadu_ps(
                                (*rows.add(corners[dj + 2 * dk][$l] as usize)).0.as_ptr(),
                            )
                        };
                    }
                    // The blocks of `quad(l)`: lane l's rows m and m + 1,
                    // then lane l + 4's. After the in-block transposes of
                    // quads 0..4 and 8..12, blocks 0 and 2 of the two hold
                    // corner (0, dj, dk)'s lanes 0..16 in order, blocks 1 and
                    // 3 corner (1, dj, dk)'s.
                    macro_rules! quad {
                        ($l:expr) => {
                            _mm512_castpd_ps(_mm512_insertf64x4::<1>(
                                _mm512_castps_pd(_mm512_castps256_ps512(pair!($l))),
                                _mm256_castps_pd(pair!($l + 4)),
                            ))
                        };
                    }
                    macro_rules! transpose {
                        ($r0:expr, $r1:expr, $r2:expr, $r3:expr) => {{
                            let (r0, r1, r2, r3) = ($r0, $r1, $r2, $r3);
                            let (lo01, lo23) = (
                                _mm512_castps_pd(_mm512_unpacklo_ps(r0, r1)),
                                _mm512_castps_pd(_mm512_unpacklo_ps(r2, r3)),
                            );
                            let (hi01, hi23) = (
                                _mm512_castps_pd(_mm512_unpackhi_ps(r0, r1)),
                                _mm512_castps_pd(_mm512_unpackhi_ps(r2, r3)),
                            );
                            [
                                _mm512_castpd_ps(_mm512_unpacklo_pd(lo01, lo23)),
                                _mm512_castpd_ps(_mm512_unpackhi_pd(lo01, lo23)),
                                _mm512_castpd_ps(_mm512_unpacklo_pd(hi01, hi23)),
                            ]
                        }};
                    }
                    let low = transpose!(quad!(0), quad!(1), quad!(2), quad!(3));
                    let high = transpose!(quad!(8), quad!(9), quad!(10), quad!(11));
                    // Blocks 0, 2 of each (0x88) or 1, 3 of each (0xdd).
                    let near = [
                        _mm512_shuffle_f32x4::<0x88>(low[0], high[0]),
                        _mm512_shuffle_f32x4::<0x88>(low[1], high[1]),
                        _mm512_shuffle_f32x4::<0x88>(low[2], high[2]),
                    ];
                    let far = [
                        _mm512_shuffle_f32x4::<0xdd>(low[0], high[0]),
                        _mm512_shuffle_f32x4::<0xdd>(low[1], high[1]),
                        _mm512_shuffle_f32x4::<0xdd>(low[2], high[2]),
                    ];
                    for (di, [gx, gy, gz]) in [near, far].into_iter().enumerate() {
                        let dot = _mm512_add_ps(
                            _mm512_add_ps(_mm512_mul_ps(gx, xs[di]), _mm512_mul_ps(gy, ys[dj])),
                            _mm512_mul_ps(gz, zs[dk]),
                        );
                        sum = _mm512_add_ps(sum, _mm512_mul_ps(_mm512_mul_ps(wx[di], wyz), dot));
                    }
                }
            }
            sum
        }
    }

    /// [`Noise::noise`] at each of the lanes' points (no SIMD path here).
    #[cfg(not(target_arch = "x86_64"))]
    #[inline(always)]
    pub(crate) fn noise_lanes(&self, px: &Lanes, py: &Lanes, pz: &Lanes) -> Lanes {
        std::array::from_fn(|l| self.noise(Vec3::new(px[l], py[l], pz[l])))
    }

    /// [`Noise::noise`] at 4 points in SSE registers (see [`Noise::noise_lanes`]).
    #[cfg(target_arch = "x86_64")]
    #[inline(always)]
    pub(crate) fn noise4(
        &self,
        x: std::arch::x86_64::__m128,
        y: std::arch::x86_64::__m128,
        z: std::arch::x86_64::__m128,
    ) -> std::arch::x86_64::__m128 {
        use std::arch::x86_64::*;
        {
            // SAFETY: the stores are of 4 i32 into arrays of 4; the rows are
            // 16-byte aligned (`Row`) and in the table (below).
            unsafe {
                let (fx, fy, fz) = (floor4(x), floor4(y), floor4(z));
                // The cells mod n.
                let mut cell = [[0u32; 4]; 3];
                let n = _mm_set1_epi32(255);
                _mm_storeu_si128(cell[0].as_mut_ptr().cast(), _mm_and_si128(lattice4(fx), n));
                _mm_storeu_si128(cell[1].as_mut_ptr().cast(), _mm_and_si128(lattice4(fy), n));
                _mm_storeu_si128(cell[2].as_mut_ptr().cast(), _mm_and_si128(lattice4(fz), n));
                let mut corners = [[0usize; 4]; 4];
                for (l, c) in corners.iter_mut().enumerate() {
                    *c = self.corners(
                        cell[0][l] as usize,
                        cell[1][l] as usize,
                        cell[2][l] as usize,
                    );
                }
                let rows = self.gradient_of.as_ptr();
                let one = _mm_set1_ps(1.0);
                let (u, v, w) = (_mm_sub_ps(x, fx), _mm_sub_ps(y, fy), _mm_sub_ps(z, fz));
                let xs = [u, _mm_sub_ps(u, one)];
                let ys = [v, _mm_sub_ps(v, one)];
                let zs = [w, _mm_sub_ps(w, one)];
                let wx = knots4(xs[0], one);
                let wy = knots4(ys[0], one);
                let wz = knots4(zs[0], one);
                let mut sum = _mm_setzero_ps();
                for dk in 0..2 {
                    for dj in 0..2 {
                        let wyz = _mm_mul_ps(wy[dj], wz[dk]);
                        for di in 0..2 {
                            // SAFETY: `corners` are < 511, so the row is in the table.
                            let row = |l: usize| {
                                _mm_load_ps((*rows.add(corners[l][dj + 2 * dk] + di)).0.as_ptr())
                            };
                            // Rows (gx, gy, gz, 0) of lanes 0..4 → gx, gy, gz.
                            let (r0, r1, r2, r3) = (row(0), row(1), row(2), row(3));
                            let (lo01, lo23) = (_mm_unpacklo_ps(r0, r1), _mm_unpacklo_ps(r2, r3));
                            let (hi01, hi23) = (_mm_unpackhi_ps(r0, r1), _mm_unpackhi_ps(r2, r3));
                            let gx = _mm_movelh_ps(lo01, lo23);
                            let gy = _mm_movehl_ps(lo23, lo01);
                            let gz = _mm_movelh_ps(hi01, hi23);
                            let dot = _mm_add_ps(
                                _mm_add_ps(_mm_mul_ps(gx, xs[di]), _mm_mul_ps(gy, ys[dj])),
                                _mm_mul_ps(gz, zs[dk]),
                            );
                            sum = _mm_add_ps(sum, _mm_mul_ps(_mm_mul_ps(wx[di], wyz), dot));
                        }
                    }
                }
                sum
            }
        }
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

/// The lane kernels behind the instruction-set dispatch.
impl Noise {
    /// `noise` at each of the lanes' points on `isa`, through that path's
    /// `#[target_feature]` copy.
    #[inline]
    pub fn noise_on(&self, isa: Isa, x: &Lanes, y: &Lanes, z: &Lanes) -> Lanes {
        self.noise_runs_on(isa, false, x, y, z)
    }

    /// [`Noise::noise_on`]; with `runs` (points along a ray, [`runs`]), the
    /// AVX2 kernel tries a register's first and last cells first.
    #[inline]
    fn noise_runs_on(&self, isa: Isa, runs: bool, x: &Lanes, y: &Lanes, z: &Lanes) -> Lanes {
        crate::math::simd::per_isa!(isa, (
            n: &Noise = self, runs: bool = runs, x: &Lanes = x, y: &Lanes = y, z: &Lanes = z,
        ) -> Lanes {
            scalar => std::array::from_fn(|l| n.noise(Vec3::new(x[l], y[l], z[l]))),
            lanes => n.noise_lanes_along(lanes, u32::MAX, runs, x, y, z),
        })
    }

    /// [`Noise::noise_on`] for points along a ray ([`runs`]): on AVX2, the
    /// kernel that tries a register's first and last cells first.
    #[cfg(test)]
    fn noise_along_on(&self, isa: Isa, x: &Lanes, y: &Lanes, z: &Lanes) -> Lanes {
        self.noise_runs_on(isa, true, x, y, z)
    }

    /// [`Noise::turbulence`] on `isa`: the octaves of the one point in the
    /// lanes of a kernel (8 at a time in AVX registers on AVX2 and AVX-512, 4
    /// in SSE ones), each lane the scalar noise's bits, summed in the scalar
    /// order.
    #[inline]
    pub fn turbulence_on(&self, isa: Isa, p: Vec3, octaves: u32) -> f32 {
        crate::math::simd::per_isa!(isa, (n: &Noise = self, p: Vec3 = p, octaves: u32 = octaves) -> f32 {
            scalar => n.turbulence(p, octaves),
            lanes => turbulence_lanes(n, lanes, p, octaves),
        })
    }

    /// `noise` at every point of `points`, into `out` (at least as long).
    pub fn noise_batch(&self, isa: Isa, points: &[Vec3], out: &mut [f32]) {
        crate::math::simd::per_isa!(isa, (n: &Noise = self, points: &[Vec3] = points, out: &mut [f32] = out) -> () {
            scalar => {
                for (o, &p) in out.iter_mut().zip(points) {
                    *o = n.noise(p);
                }
            },
            lanes => noise_batch_lanes_on(n, lanes, points, out),
        })
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

/// [`Noise::noise_batch`] on a SIMD path (inlined into its copy): 16 points
/// at a time in AVX-512 registers on AVX-512, 8 at a time in AVX registers
/// on AVX2 (and for AVX-512's last 8 to 15), 4 at a time otherwise.
#[inline(always)]
fn noise_batch_lanes_on(n: &Noise, isa: Isa, points: &[Vec3], out: &mut [f32]) {
    #[cfg(target_arch = "x86_64")]
    let (points, out) = if isa == Isa::Avx512 {
        use std::arch::x86_64::*;
        /// The register of the blocks a, b, c, d (lanes 0..4, 4..8, ...).
        ///
        /// # Safety
        /// AVX-512F, by the caller's contract: it is inlined into the
        /// AVX-512 copy.
        #[inline(always)]
        unsafe fn join(a: __m128, b: __m128, c: __m128, d: __m128) -> __m512 {
            // SAFETY: AVX-512F by the contract.
            unsafe {
                let ab = _mm512_insertf32x4::<1>(_mm512_castps128_ps512(a), b);
                _mm512_insertf32x4::<3>(_mm512_insertf32x4::<2>(ab, c), d)
            }
        }
        let out = &mut out[..points.len()];
        let mut sixteens = points.chunks_exact(16);
        let mut outs = out.chunks_exact_mut(16);
        for (p, o) in (&mut sixteens).zip(&mut outs) {
            let (x0, y0, z0) = deinterleave(&p[..4]);
            let (x1, y1, z1) = deinterleave(&p[4..8]);
            let (x2, y2, z2) = deinterleave(&p[8..12]);
            let (x3, y3, z3) = deinterleave(&p[12..]);
            // SAFETY: the path is AVX-512 only in its copy, on CPUs that
            // have it (`per_isa!`); `o` holds 16 f32.
            unsafe {
                let n = n.noise16(
                    join(x0, x1, x2, x3),
                    join(y0, y1, y2, y3),
                    join(z0, z1, z2, z3),
                );
                _mm512_storeu_ps(o.as_mut_ptr(), n);
            }
        }
        (sixteens.remainder(), outs.into_remainder())
    } else {
        (points, out)
    };
    #[cfg(target_arch = "x86_64")]
    if matches!(isa, Isa::Avx2 | Isa::Avx512) {
        use std::arch::x86_64::*;
        let out = &mut out[..points.len()];
        let mut eights = points.chunks_exact(8);
        let mut outs = out.chunks_exact_mut(8);
        for (p, o) in (&mut eights).zip(&mut outs) {
            let ((x0, y0, z0), (x1, y1, z1)) = (deinterleave(&p[..4]), deinterleave(&p[4..]));
            // SAFETY: the path is AVX2 or AVX-512 only in its copy, on CPUs
            // that have it (`per_isa!`); `o` holds 8 f32.
            unsafe {
                let n = n.noise8(
                    _mm256_set_m128(x1, x0),
                    _mm256_set_m128(y1, y0),
                    _mm256_set_m128(z1, z0),
                );
                _mm256_storeu_ps(o.as_mut_ptr(), n);
            }
        }
        return noise_batch_lanes(n, eights.remainder(), outs.into_remainder());
    }
    let _ = isa;
    #[cfg(target_arch = "x86_64")]
    noise_batch_lanes(n, points, out);
    #[cfg(not(target_arch = "x86_64"))]
    for (o, &p) in out.iter_mut().zip(points) {
        *o = n.noise(p);
    }
}

/// [`Noise::turbulence`] on a SIMD path (inlined into its copy): the
/// octaves 8 at a time in AVX registers on AVX2 and AVX-512, 4 at a time
/// otherwise.
#[inline(always)]
fn turbulence_lanes(n: &Noise, isa: Isa, p: Vec3, octaves: u32) -> f32 {
    #[cfg(target_arch = "x86_64")]
    {
        use std::arch::x86_64::*;
        if matches!(isa, Isa::Avx2 | Isa::Avx512) {
            return turbulence_by::<8>(p, octaves, |x, y, z| {
                let mut out = [0.0; 8];
                // SAFETY: the path is AVX2 or AVX-512 only in its copy, on
                // CPUs that have it (`per_isa!`); the loads and the store are
                // of 8 f32 within arrays of 8.
                unsafe {
                    let v = n.noise8(
                        _mm256_loadu_ps(x.as_ptr()),
                        _mm256_loadu_ps(y.as_ptr()),
                        _mm256_loadu_ps(z.as_ptr()),
                    );
                    _mm256_storeu_ps(out.as_mut_ptr(), v);
                }
                out
            });
        }
        let _ = isa;
        turbulence_by::<4>(p, octaves, |x, y, z| {
            let mut out = [0.0; 4];
            // SAFETY: the loads and the store are of 4 f32 within arrays of 4.
            unsafe {
                let v = n.noise4(
                    _mm_loadu_ps(x.as_ptr()),
                    _mm_loadu_ps(y.as_ptr()),
                    _mm_loadu_ps(z.as_ptr()),
                );
                _mm_storeu_ps(out.as_mut_ptr(), v);
            }
            out
        })
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        let _ = isa;
        turbulence_by::<4>(p, octaves, |x, y, z| {
            std::array::from_fn(|l| n.noise(Vec3::new(x[l], y[l], z[l])))
        })
    }
}

/// [`Noise::turbulence`] with its octaves `WIDTH` at a time in the
/// lanes of `kernel`.
#[inline(always)]
fn turbulence_by<const WIDTH: usize>(
    p: Vec3,
    octaves: u32,
    kernel: impl Fn(&[f32; WIDTH], &[f32; WIDTH], &[f32; WIDTH]) -> [f32; WIDTH],
) -> f32 {
    let (mut sum, mut scale) = (0.0, 1.0f32);
    let mut left = octaves as usize;
    while left > 0 {
        let count = left.min(WIDTH);
        let (mut x, mut y, mut z) = ([0.0; WIDTH], [0.0; WIDTH], [0.0; WIDTH]);
        let mut s = scale;
        for i in 0..count {
            let q = p * s;
            (x[i], y[i], z[i]) = (q.x, q.y, q.z);
            s *= 2.0;
        }
        let n = kernel(&x, &y, &z);
        for v in &n[..count] {
            sum += v.abs() / scale;
            scale *= 2.0;
        }
        left -= count;
    }
    sum
}

/// The knot's cubic drop-off ω(t) = 2|t|³ − 3|t|² + 1 (0 for |t| ≥ 1) at
/// t in [−0, 1], where it needs no |t| and no test: (2t − 3)t² + 1. A
/// point's fraction u lies there, and so does 1 − u = |u − 1| (exactly:
/// rounding is symmetric about 0); at t = 1 the cubic gives +0, as ω does.
#[inline(always)]
fn knot(t: f32) -> f32 {
    (2.0 * t - 3.0) * t * t + 1.0
}

/// [`knot`] at a fraction u and at 1 − u on a register of lanes, with its
/// operations: the weights ω(u), ω(u − 1) of a cell's near and far knots.
/// One copy per register width, from that width's intrinsics.
macro_rules! knots {
    ($($(#[$attr:meta])* $name:ident: $ty:ident, $add:ident, $sub:ident, $mul:ident, $set1:ident;)*) => {$(
        $(#[$attr])*
        #[cfg(target_arch = "x86_64")]
        #[inline(always)]
        unsafe fn $name(
            u: std::arch::x86_64::$ty,
            one: std::arch::x86_64::$ty,
        ) -> [std::arch::x86_64::$ty; 2] {
            use std::arch::x86_64::*;
            // SAFETY: the width's features by the caller's contract. (A
            // macro, not a closure: a closure's intrinsics are left as calls.)
            unsafe {
                macro_rules! cubic {
                    ($t:expr) => {{
                        let t = $t;
                        $add($mul($mul($sub($mul($set1(2.0), t), $set1(3.0)), t), t), one)
                    }};
                }
                [cubic!(u), cubic!($sub(one, u))]
            }
        }
    )*};
}

knots! {
    /// 4 lanes (SSE).
    knots4: __m128, _mm_add_ps, _mm_sub_ps, _mm_mul_ps, _mm_set1_ps;
    /// 8 lanes (AVX).
    knots8: __m256, _mm256_add_ps, _mm256_sub_ps, _mm256_mul_ps, _mm256_set1_ps;
    /// 16 lanes (AVX-512F).
    knots16: __m512, _mm512_add_ps, _mm512_sub_ps, _mm512_mul_ps, _mm512_set1_ps;
}

/// ω'(t) = 6t(|t| − 1) for |t| < 1, else 0: the slope of [`knot`]'s ω.
#[inline(always)]
fn omega_slope(t: f32) -> f32 {
    if t.abs() < 1.0 {
        6.0 * t * (t.abs() - 1.0)
    } else {
        0.0
    }
}

/// [`floor`] on 4 lanes, with its operations: the rounding instruction,
/// plus +0.0 (so that −0 gives +0).
///
/// # Safety
/// SSE4.1, by the caller's contract: it is inlined only into the SSE4.1 and
/// AVX2 copies of the lane code.
#[cfg(target_arch = "x86_64")]
#[inline(always)]
unsafe fn floor4(x: std::arch::x86_64::__m128) -> std::arch::x86_64::__m128 {
    use std::arch::x86_64::*;
    // SAFETY: SSE4.1 by the caller's contract.
    unsafe { _mm_add_ps(_mm_floor_ps(x), _mm_setzero_ps()) }
}

/// [`lattice`] on 4 lanes, with its operations.
#[cfg(target_arch = "x86_64")]
#[inline(always)]
fn lattice4(x: std::arch::x86_64::__m128) -> std::arch::x86_64::__m128i {
    use std::arch::x86_64::*;
    // SAFETY: SSE and SSE2 are part of the x86-64 baseline.
    unsafe {
        let fits = _mm_cmplt_ps(abs4(x), _mm_set1_ps(2_147_483_520.0));
        _mm_cvttps_epi32(_mm_and_ps(fits, x))
    }
}

/// [`floor`] on 8 lanes (AVX), with its operations: the rounding
/// instruction, plus +0.0 (so that −0 gives +0).
#[cfg(target_arch = "x86_64")]
#[inline(always)]
unsafe fn floor8(x: std::arch::x86_64::__m256) -> std::arch::x86_64::__m256 {
    use std::arch::x86_64::*;
    // SAFETY: AVX by the caller's contract.
    unsafe { _mm256_add_ps(_mm256_floor_ps(x), _mm256_setzero_ps()) }
}

/// [`lattice`] on 8 lanes (AVX), with its operations.
#[cfg(target_arch = "x86_64")]
#[inline(always)]
unsafe fn lattice8(x: std::arch::x86_64::__m256) -> std::arch::x86_64::__m256i {
    use std::arch::x86_64::*;
    // SAFETY: AVX by the caller's contract.
    unsafe {
        let fits = _mm256_cmp_ps::<_CMP_LT_OQ>(abs8(x), _mm256_set1_ps(2_147_483_520.0));
        _mm256_cvttps_epi32(_mm256_and_ps(fits, x))
    }
}

/// |x| on 8 lanes (AVX).
#[cfg(target_arch = "x86_64")]
#[inline(always)]
unsafe fn abs8(x: std::arch::x86_64::__m256) -> std::arch::x86_64::__m256 {
    use std::arch::x86_64::*;
    // SAFETY: AVX by the caller's contract.
    unsafe { _mm256_andnot_ps(_mm256_set1_ps(-0.0), x) }
}

/// [`floor`] on 16 lanes (AVX-512), with its operations: rounding towards
/// −∞, plus +0.0 (so that −0 gives +0).
#[cfg(target_arch = "x86_64")]
#[inline(always)]
unsafe fn floor16(x: std::arch::x86_64::__m512) -> std::arch::x86_64::__m512 {
    use std::arch::x86_64::*;
    // SAFETY: AVX-512F by the caller's contract.
    unsafe {
        _mm512_add_ps(
            _mm512_roundscale_ps::<{ _MM_FROUND_TO_NEG_INF | _MM_FROUND_NO_EXC }>(x),
            _mm512_setzero_ps(),
        )
    }
}

/// [`lattice`] on 16 lanes (AVX-512), with its operations.
#[cfg(target_arch = "x86_64")]
#[inline(always)]
unsafe fn lattice16(x: std::arch::x86_64::__m512) -> std::arch::x86_64::__m512i {
    use std::arch::x86_64::*;
    // SAFETY: AVX-512F by the caller's contract.
    unsafe {
        let fits =
            _mm512_cmp_ps_mask::<_CMP_LT_OQ>(_mm512_abs_ps(x), _mm512_set1_ps(2_147_483_520.0));
        _mm512_cvttps_epi32(_mm512_maskz_mov_ps(fits, x))
    }
}

/// |x| on 4 lanes.
#[cfg(target_arch = "x86_64")]
#[inline(always)]
fn abs4(x: std::arch::x86_64::__m128) -> std::arch::x86_64::__m128 {
    use std::arch::x86_64::*;
    // SAFETY: SSE and SSE2 are part of the x86-64 baseline.
    unsafe { _mm_andnot_ps(_mm_set1_ps(-0.0), x) }
}

/// Whether the samples of a ray, `step` apart, lie often enough in at most
/// two cells of noise at `frequency` eight at a time (an AVX2 register's
/// worth) for the noise kernel to try those two cells first
/// ([`Noise::noise8_on`]): eight samples span at most 3 lattice units.
/// (At 1.1 units, 65% of the high amplitude sphere's registers lie in one or two cells.
/// Of the bounds 1.5, 3 and 6, 3 gave the fractal sphere and the eroded
/// cube the fewest instructions, and the fire ball within 0.1%.)
pub(crate) fn runs(frequency: f32, step: f32) -> bool {
    (frequency * step * 7.0).abs() <= 3.0
}

/// How many of the first `octaves` of a sum from `frequency` (doubling)
/// have [`runs`].
pub(crate) fn octaves_in_runs(frequency: f32, step: f32, octaves: u32) -> u32 {
    let mut f = frequency;
    let mut count = 0;
    while count < octaves && runs(f, step) {
        f *= 2.0;
        count += 1;
    }
    count
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
    DEFAULT.noise_batch(Isa::detect(), points, out);
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

    /// The table of cells gives Γ's rows as the paper's hash defines them:
    /// corner (di, dj, dk) of cell (i, j, k) is G[φ(i + di + φ(j + dj + φ(k + dk)))].
    #[test]
    fn cells_give_the_hash_of_every_corner() {
        for seed in [DEFAULT_SEED, 7] {
            let n = Noise::new(seed);
            let phi = |m: usize| usize::from(n.perm[m % 256]);
            for k in 0..256 {
                for j in 0..256 {
                    let i = (j * 7 + k * 13) % 256;
                    let corners = n.corners(i, j, k);
                    for dk in 0..2 {
                        for dj in 0..2 {
                            for di in 0..2 {
                                let row = n.gradient_of[corners[dj + 2 * dk] + di].0;
                                let g = n.gradients[phi(i + di + phi(j + dj + phi(k + dk)))];
                                assert_eq!(
                                    row,
                                    [g.x, g.y, g.z, 0.0],
                                    "({i}, {j}, {k}) + ({di}, {dj}, {dk})"
                                );
                            }
                        }
                    }
                }
            }
        }
    }

    /// Scenes of one seed share the table; another seed has its own.
    #[test]
    fn a_seed_builds_its_cells_once() {
        let (a, b, c) = (Noise::new(11), Noise::new(11), Noise::new(12));
        assert!(Arc::ptr_eq(&a.cells, &b.cells));
        assert!(!Arc::ptr_eq(&a.cells, &c.cells));
        assert_ne!(a.cells[..], c.cells[..]);
    }

    #[test]
    fn the_knots_give_the_drop_off_of_the_near_and_far_knot() {
        // ω as defined: |t|, and 0 from |t| = 1 on.
        let omega = |t: f32| {
            let t = t.abs();
            if t < 1.0 {
                (2.0 * t - 3.0) * t * t + 1.0
            } else {
                0.0
            }
        };
        // Fractions x − floor(x): a grid, the ends (−0 from x = −0, 1 from
        // a tiny negative x), the values next to them, and scattered bits.
        let ends = [
            -0.0,
            0.0,
            1e-30,
            f32::EPSILON / 2.0,
            1.0 - f32::EPSILON / 2.0,
            1.0,
        ];
        let grid = (0..=1 << 16).map(|i| i as f32 / 65536.0);
        let scattered = (0..100_000u32).map(|i| {
            let bits = i.wrapping_mul(2_654_435_761) >> 9;
            f32::from_bits(0x3f80_0000 | bits) - 1.0
        });
        for u in ends.into_iter().chain(grid).chain(scattered) {
            assert_eq!(knot(u).to_bits(), omega(u).to_bits(), "near knot at {u:e}");
            let far = omega(u - 1.0).to_bits();
            assert_eq!(knot(1.0 - u).to_bits(), far, "far knot at {u:e}");
        }
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
    fn within_the_bound_the_marcher_relies_on() {
        // √(3/4) (see `NOISE_BOUND`), reached where every knot's gradient
        // points at the centre of its cell; random tables stay below it.
        let mut worst = 0.0f32;
        for seed in 0..20 {
            let n = Noise::new(seed);
            for p in points(20_000, seed, 40.0) {
                worst = worst.max(n.noise(p).abs());
            }
        }
        assert!(worst <= NOISE_BOUND, "{worst}");
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
    fn the_gradient_is_the_derivative() {
        let n = Noise::default();
        let h = 1e-3;
        for p in points(2000, 11, 20.0) {
            let (value, g) = n.noise_gradient(p);
            assert_eq!(value.to_bits(), n.noise(p).to_bits());
            let d = |e: Vec3| (n.noise(p + e * h) - n.noise(p - e * h)) / (2.0 * h);
            let fd = Vec3::new(d(Vec3::X), d(Vec3::Y), d(Vec3::Z));
            assert!((g - fd).length() < 2e-3, "{p:?}: {g:?} vs {fd:?}");
        }
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
        // Every remainder of the 16-, 8- and 4-point batches; `out` may be
        // longer.
        for n in 0..20 {
            let mut out = vec![7.0; n + 3];
            perlin_batch(&pts[..n], &mut out);
            for (p, o) in pts[..n].iter().zip(&out) {
                assert_eq!(perlin(*p).to_bits(), o.to_bits());
            }
            assert_eq!(out[n..], [7.0; 3]);
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

    #[test]
    fn every_path_gives_the_scalar_noise() {
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
            // Lattice points too.
            if round == 0 {
                let lattice = [0.0, -0.0, 1.0, -1.0, 255.0, 256.0, -300.0, 1.0e9];
                let more = [0.5, -0.5, 1.0e-30, -1.0e9, 2.5, -2.5, 65536.0, -65537.0];
                for (v, &l) in p[0].iter_mut().zip(lattice.iter().chain(&more)) {
                    *v = l;
                }
            }
            let reference = n.noise_on(Isa::Scalar, &p[0], &p[1], &p[2]);
            for isa in Isa::available() {
                let got = n.noise_on(isa, &p[0], &p[1], &p[2]);
                assert_eq!(
                    got.map(f32::to_bits),
                    reference.map(f32::to_bits),
                    "{isa:?}"
                );
            }
        }
    }

    /// Lanes along short rays, as the marcher's chunks lie: in one cell, in
    /// the cells of the first and last lanes (in runs or alternating, and a
    /// cell 256 apart, the same after reduction), or in more.
    #[test]
    fn lanes_in_one_or_two_cells_give_the_scalar_noise() {
        let n = Noise::new(77);
        let mut r = SplitMix64::new(11);
        let mut cells = [0usize; 4];
        for round in 0..20_000u32 {
            let origin = Vec3::new(r.next_f32(), r.next_f32(), r.next_f32()) * 40.0 - 20.0;
            let direction = Vec3::new(r.next_f32(), r.next_f32(), r.next_f32()) - 0.5;
            let step = [0.0, 0.01, 0.05, 0.15, 0.6][round as usize % 5];
            let points: [Vec3; LANES] = std::array::from_fn(|l| match round % 7 {
                // Alternating between two points' cells.
                5 => origin + direction * (step * (l % 2) as f32 * 4.0),
                // A lane a period away: the same cell mod 256.
                6 if l == 3 => origin + direction * (step * l as f32) + Vec3::Y * 256.0,
                _ => origin + direction * (step * l as f32),
            });
            let p = [
                points.map(|x| x.x),
                points.map(|x| x.y),
                points.map(|x| x.z),
            ];
            let mut distinct: Vec<[i32; 3]> = Vec::new();
            for x in &points[..8] {
                let c = x.to_array().map(|a| (a.floor() as i32) & 255);
                if !distinct.contains(&c) {
                    distinct.push(c);
                }
            }
            cells[distinct.len().min(4) - 1] += 1;
            let reference = n.noise_on(Isa::Scalar, &p[0], &p[1], &p[2]);
            for isa in Isa::available() {
                for got in [
                    n.noise_on(isa, &p[0], &p[1], &p[2]),
                    n.noise_along_on(isa, &p[0], &p[1], &p[2]),
                ] {
                    assert_eq!(
                        got.map(f32::to_bits),
                        reference.map(f32::to_bits),
                        "{isa:?}, round {round}"
                    );
                }
            }
        }
        // Every case came up often.
        assert!(cells.iter().all(|&c| c > 1_000), "{cells:?}");
    }

    #[test]
    fn every_path_gives_the_scalar_turbulence() {
        let n = Noise::new(77);
        let mut r = SplitMix64::new(10);
        for round in 0..2_000u32 {
            let scale = if round % 2 == 0 { 8.0 } else { 3.0e3 };
            let p = (Vec3::new(r.next_f32(), r.next_f32(), r.next_f32()) - 0.5) * scale;
            let octaves = round % 20;
            let reference = n.turbulence(p, octaves);
            for isa in Isa::available() {
                assert_eq!(
                    n.turbulence_on(isa, p, octaves).to_bits(),
                    reference.to_bits(),
                    "{isa:?}, {octaves} octaves at {p}"
                );
            }
        }
    }
}
