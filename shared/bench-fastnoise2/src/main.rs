//! 3D gradient noise throughput, one thread: FastNoise2's Perlin (at the
//! AVX-512 and AVX2 feature sets, forced, and the one it picks), our
//! `Noise::noise_on` on each instruction set (points in x, y and z arrays,
//! 16 at a time), our `perlin_batch` (an array of `Vec3`) and FastNoise
//! Lite's Perlin, over 2^20 scattered points and over a 64³ grid (four grids
//! per timing). The contenders take turns, round after round; the median
//! round of each is printed, with the median of the per-round ratios to
//! FastNoise2. The noises differ (FastNoise2 and FastNoise Lite hash the
//! lattice and pick among 12 gradients, with quintic fades; ours looks up the
//! paper's 256 random gradients, with cubic drop-offs): only speed compares.
//!
//! Times are the thread's CPU time (`CLOCK_THREAD_CPUTIME_ID`): on a machine
//! shared with other work, the time the thread waits descheduled is left
//! out; the wall-clock figures are printed beside them.
//!
//! `scripts/bench-fastnoise2.sh [rounds [name]]`: 11 rounds by default; with
//! a name, only the contenders whose name holds it (for a profiler).

use std::ffi::{CStr, c_void};
use std::hint::black_box;
use std::time::Instant;

use fastnoise2_sys::{
    fnDeleteNodeRef, fnGenPositionArray3D, fnGenUniformGrid3D, fnGetMetadataCount,
    fnGetMetadataName, fnGetMetadataVariableCount, fnGetMetadataVariableName, fnGetSIMDLevel,
    fnNewFromMetadata, fnSetVariableFloat,
};
use glam::Vec3;
use hypertexture::field::noise::{self, Noise};
use hypertexture::math::random::SplitMix64;
use hypertexture::math::simd::{Isa, LANES, Lanes};

/// Points of the scattered set.
const POINTS: usize = 1 << 20;
/// Points along an edge of the grid.
const EDGE: usize = 64;
/// Grids per timing of the grid.
const GRIDS: usize = 4;
/// The grid's spacing in lattice units: 8 samples a cell along each axis.
const STEP: f32 = 0.125;
/// The grid's corner.
const ORIGIN: f32 = -3.7;

/// FastSIMD's feature sets (FastSIMD/Utility/FeatureEnums.h): each a mask of
/// 1 << FeatureFlag; x86 is flag 1, SSE…AVX2 flags 2–9, AVX-512 F, VL, DQ,
/// BW flags 10–13.
const AVX2: u32 = 0b11_1111_1110;
const AVX512: u32 = 0b11_1111_1111_1110;
const AUTO: u32 = u32::MAX;

/// A FastNoise2 Perlin node at a feature set, feature scale 1 (one lattice
/// cell per unit, as ours).
struct Fn2(*mut c_void);

impl Fn2 {
    fn perlin(level: u32) -> Fn2 {
        // SAFETY: ids below fnGetMetadataCount are valid; the names are
        // NUL-terminated strings owned by the library.
        unsafe {
            let id = (0..fnGetMetadataCount())
                .find(|&id| CStr::from_ptr(fnGetMetadataName(id)).to_bytes() == b"Perlin")
                .expect("FastNoise2 has a Perlin node");
            let node = fnNewFromMetadata(id, level);
            assert!(!node.is_null(), "FastNoise2 made no Perlin node");
            let scale = (0..fnGetMetadataVariableCount(id))
                .find(|&v| {
                    CStr::from_ptr(fnGetMetadataVariableName(id, v))
                        .to_string_lossy()
                        .to_ascii_lowercase()
                        .contains("scale")
                })
                .expect("FastNoise2's Perlin has a feature scale");
            assert!(fnSetVariableFloat(node, scale, 1.0));
            Fn2(node)
        }
    }

    /// FastSIMD's feature set the node runs.
    fn level(&self) -> u32 {
        // SAFETY: a live node.
        unsafe { fnGetSIMDLevel(self.0) }
    }

    fn positions(&self, x: &[f32], y: &[f32], z: &[f32], out: &mut [f32]) {
        assert!(x.len() == out.len() && y.len() == out.len() && z.len() == out.len());
        // SAFETY: a live node; the arrays hold `count` floats each.
        unsafe {
            fnGenPositionArray3D(
                self.0,
                out.as_mut_ptr(),
                out.len() as i32,
                x.as_ptr(),
                y.as_ptr(),
                z.as_ptr(),
                0.0,
                0.0,
                0.0,
                1989,
                std::ptr::null_mut(),
            );
        }
    }

    fn grid(&self, out: &mut [f32]) {
        assert_eq!(out.len(), EDGE * EDGE * EDGE);
        let n = EDGE as i32;
        // SAFETY: a live node; `out` holds the grid.
        unsafe {
            fnGenUniformGrid3D(
                self.0,
                out.as_mut_ptr(),
                ORIGIN,
                ORIGIN,
                ORIGIN,
                n,
                n,
                n,
                STEP,
                STEP,
                STEP,
                1989,
                std::ptr::null_mut(),
            );
        }
    }
}

impl Drop for Fn2 {
    fn drop(&mut self) {
        // SAFETY: the node is ours and dropped once.
        unsafe { fnDeleteNodeRef(self.0) }
    }
}

/// FastSIMD's name of a feature set.
fn level_name(level: u32) -> String {
    match level {
        AVX512 => "AVX-512".into(),
        AVX2 => "AVX2".into(),
        l => format!("feature set {l:#x}"),
    }
}

/// `noise_on` over the points in x, y and z arrays, [`LANES`] at a time.
fn ours_soa(n: &Noise, isa: Isa, x: &[f32], y: &[f32], z: &[f32], out: &mut [f32]) {
    fn lanes(s: &[f32]) -> &Lanes {
        s.try_into().unwrap()
    }
    for (((o, x), y), z) in out
        .chunks_exact_mut(LANES)
        .zip(x.chunks_exact(LANES))
        .zip(y.chunks_exact(LANES))
        .zip(z.chunks_exact(LANES))
    {
        o.copy_from_slice(&n.noise_on(isa, lanes(x), lanes(y), lanes(z)));
    }
}

/// The grid's coordinate at index `i`.
fn at(i: usize) -> f32 {
    ORIGIN + i as f32 * STEP
}

/// `noise_on` over the grid, x fastest, [`LANES`] points along x at a time.
fn ours_grid(n: &Noise, isa: Isa, out: &mut [f32]) {
    let xs: Vec<Lanes> = (0..EDGE / LANES)
        .map(|c| std::array::from_fn(|l| at(c * LANES + l)))
        .collect();
    let mut chunks = out.chunks_exact_mut(LANES);
    for zi in 0..EDGE {
        let z = [at(zi); LANES];
        for yi in 0..EDGE {
            let y = [at(yi); LANES];
            for x in &xs {
                chunks
                    .next()
                    .unwrap()
                    .copy_from_slice(&n.noise_on(isa, x, &y, &z));
            }
        }
    }
}

/// The calling thread's CPU time, in seconds.
fn cpu_time() -> f64 {
    let mut t = libc::timespec {
        tv_sec: 0,
        tv_nsec: 0,
    };
    // SAFETY: `t` is a valid timespec to write.
    let rc = unsafe { libc::clock_gettime(libc::CLOCK_THREAD_CPUTIME_ID, &mut t) };
    assert_eq!(rc, 0, "clock_gettime");
    t.tv_sec as f64 + t.tv_nsec as f64 * 1e-9
}

/// `run`'s CPU time and wall time, in seconds.
fn timed(run: impl FnOnce()) -> (f64, f64) {
    let (cpu, wall) = (cpu_time(), Instant::now());
    run();
    (cpu_time() - cpu, wall.elapsed().as_secs_f64())
}

fn median(v: &mut [f64]) -> f64 {
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

fn main() {
    let rounds: usize = std::env::args()
        .nth(1)
        .map_or(11, |s| s.parse().expect("rounds"));
    // Only the contenders whose name holds this (for a profiler).
    let only = std::env::args().nth(2).unwrap_or_default();

    // The scattered points of shared/benches/noise.rs: a 64-unit cube.
    let mut r = SplitMix64::new(7);
    let pts: Vec<Vec3> = (0..POINTS)
        .map(|_| Vec3::new(r.next_f32(), r.next_f32(), r.next_f32()) * 64.0 - Vec3::splat(32.0))
        .collect();
    let (px, py, pz): (Vec<f32>, Vec<f32>, Vec<f32>) = (
        pts.iter().map(|p| p.x).collect(),
        pts.iter().map(|p| p.y).collect(),
        pts.iter().map(|p| p.z).collect(),
    );
    let grid_pts: Vec<Vec3> = (0..EDGE * EDGE * EDGE)
        .map(|m| Vec3::new(at(m % EDGE), at(m / EDGE % EDGE), at(m / (EDGE * EDGE))))
        .collect();

    let tables = Noise::default();
    let mut fnl = fastnoise_lite::FastNoiseLite::with_seed(1989);
    fnl.set_noise_type(Some(fastnoise_lite::NoiseType::Perlin));
    fnl.set_frequency(Some(1.0));
    let fn2: Vec<(String, Fn2)> = [AVX512, AVX2, AUTO]
        .into_iter()
        .map(|level| {
            let node = Fn2::perlin(level);
            let asked = if level == AUTO {
                "auto".into()
            } else {
                level_name(level)
            };
            (
                format!(
                    "FastNoise2 Perlin ({asked}: runs {})",
                    level_name(node.level())
                ),
                node,
            )
        })
        .collect();
    let isas: Vec<Isa> = [Isa::Scalar, Isa::Sse41, Isa::Avx2, Isa::Avx512]
        .into_iter()
        .filter(|isa| isa.is_available())
        .collect();

    type Run<'a> = Box<dyn FnMut(&mut [f32]) + 'a>;
    let mut scattered: Vec<(String, Run)> = Vec::new();
    let mut grid: Vec<(String, Run)> = Vec::new();
    for (name, node) in &fn2 {
        let (x, y, z) = (&px, &py, &pz);
        scattered.push((name.clone(), Box::new(move |o| node.positions(x, y, z, o))));
        grid.push((name.clone(), Box::new(move |o| node.grid(o))));
    }
    for &isa in &isas {
        let (t, x, y, z) = (&tables, &px, &py, &pz);
        let name = format!("ours noise_on {} (SoA)", isa.name());
        scattered.push((
            name.clone(),
            Box::new(move |o| ours_soa(t, isa, x, y, z, o)),
        ));
        grid.push((name, Box::new(move |o| ours_grid(t, isa, o))));
    }
    let (fnl, pts, grid_pts) = (&fnl, &pts, &grid_pts);
    let name = format!("ours perlin_batch (AoS, {})", Isa::detect().name());
    scattered.push((name.clone(), Box::new(|o| noise::perlin_batch(pts, o))));
    grid.push((name, Box::new(|o| noise::perlin_batch(grid_pts, o))));
    scattered.push((
        "FastNoise Lite Perlin".into(),
        Box::new(move |o| {
            for (o, p) in o.iter_mut().zip(pts) {
                *o = fnl.get_noise_3d(p.x, p.y, p.z);
            }
        }),
    ));
    grid.push((
        "FastNoise Lite Perlin".into(),
        Box::new(move |o| {
            for (o, p) in o.iter_mut().zip(grid_pts) {
                *o = fnl.get_noise_3d(p.x, p.y, p.z);
            }
        }),
    ));

    scattered.retain(|(name, _)| name.contains(&only));
    grid.retain(|(name, _)| name.contains(&only));

    let mut out = vec![0.0f32; POINTS];
    let mut grid_out = vec![0.0f32; EDGE * EDGE * EDGE];
    // Per set, per contender: M points/s of each round, by CPU time and by
    // wall time.
    let mut rates = [
        vec![Vec::new(); scattered.len()],
        vec![Vec::new(); grid.len()],
    ];
    let mut walls = rates.clone();
    let mut ranges = [
        vec![(0.0, 0.0); scattered.len()],
        vec![(0.0, 0.0); grid.len()],
    ];
    for round in 0..=rounds {
        // Round 0 warms up and is not counted.
        for (c, (_, run)) in scattered.iter_mut().enumerate() {
            let (t, wall) = timed(|| {
                run(&mut out);
                black_box(&out);
            });
            if round > 0 {
                rates[0][c].push(POINTS as f64 / t / 1e6);
                walls[0][c].push(POINTS as f64 / wall / 1e6);
            } else {
                ranges[0][c] = range(&out);
            }
        }
        for (c, (_, run)) in grid.iter_mut().enumerate() {
            let (t, wall) = timed(|| {
                for _ in 0..GRIDS {
                    run(&mut grid_out);
                    black_box(&grid_out);
                }
            });
            if round > 0 {
                let points = (GRIDS * grid_out.len()) as f64;
                rates[1][c].push(points / t / 1e6);
                walls[1][c].push(points / wall / 1e6);
            } else {
                ranges[1][c] = range(&grid_out);
            }
        }
    }

    let sets = [
        ("2^20 scattered points (64-unit cube)", &scattered),
        ("64³ grid, spacing 1/8 (4 grids a timing)", &grid),
    ];
    for (s, (title, contenders)) in sets.iter().enumerate() {
        println!(
            "{title}, {rounds} rounds: median M points/s [min–max], median ratio to the first, value range"
        );
        let base = rates[s][0].clone();
        for (c, (name, _)) in contenders.iter().enumerate() {
            let r = &rates[s][c];
            let mut ratios: Vec<f64> = r.iter().zip(&base).map(|(a, b)| a / b).collect();
            let (lo, hi) = r.iter().fold((f64::INFINITY, 0.0f64), |(lo, hi), &v| {
                (lo.min(v), hi.max(v))
            });
            println!(
                "  {name:44} {:7.1} [{lo:6.1}–{hi:6.1}]  ×{:.3}  [{:+.3}, {:+.3}]  wall {:.1}",
                median(&mut r.clone()),
                median(&mut ratios),
                ranges[s][c].0,
                ranges[s][c].1,
                median(&mut walls[s][c].clone()),
            );
        }
        println!("  raw M points/s per round, CPU time / wall time:");
        for (c, (name, _)) in contenders.iter().enumerate() {
            let raw: Vec<String> = rates[s][c]
                .iter()
                .zip(&walls[s][c])
                .map(|(v, w)| format!("{v:.1}/{w:.1}"))
                .collect();
            println!("    {name}: {}", raw.join(" "));
        }
    }
}

/// The least and greatest of the values.
fn range(v: &[f32]) -> (f32, f32) {
    v.iter()
        .fold((f32::INFINITY, f32::NEG_INFINITY), |(lo, hi), &x| {
            (lo.min(x), hi.max(x))
        })
}
