//! Noise throughput on a shared machine: our `perlin_batch` and `perlin`,
//! FastNoise Lite's and the `noise` crate's Perlin 3D over the same 2^20
//! scattered points (the criterion bench's), one thread, the four taking turns
//! round after round; the best round of each is printed. Other processes only
//! ever slow a round down, so the minimum is the figure least disturbed by them
//! and the ratios are fair.
//!
//! `cargo run --release -p hypertexture --example noise_ab [-- rounds]`

use std::hint::black_box;
use std::time::Instant;

use glam::Vec3;
use hypertexture::field::noise::{self, Noise};
use hypertexture::math::random::SplitMix64;

fn main() {
    let rounds: usize = std::env::args()
        .nth(1)
        .map_or(15, |s| s.parse().expect("rounds"));
    let mut r = SplitMix64::new(7);
    let pts: Vec<Vec3> = (0..1 << 20)
        .map(|_| Vec3::new(r.next_f32(), r.next_f32(), r.next_f32()) * 64.0 - Vec3::splat(32.0))
        .collect();
    let mut out = vec![0.0f32; pts.len()];
    let tables = Noise::default();
    let mut fnl = fastnoise_lite::FastNoiseLite::with_seed(1989);
    fnl.set_noise_type(Some(fastnoise_lite::NoiseType::Perlin));
    fnl.set_frequency(Some(1.0));
    let noise_rs = ::noise::Perlin::new(1989);

    let mut best = [f64::INFINITY; 4];
    for _ in 0..rounds {
        let mut time = |i: usize, f: &mut dyn FnMut(&mut [f32])| {
            let start = Instant::now();
            f(&mut out);
            black_box(&out);
            best[i] = best[i].min(start.elapsed().as_secs_f64());
        };
        time(0, &mut |o| noise::perlin_batch(&pts, o));
        time(1, &mut |o| {
            for (o, &p) in o.iter_mut().zip(&pts) {
                *o = tables.noise(p);
            }
        });
        time(2, &mut |o| {
            for (o, p) in o.iter_mut().zip(&pts) {
                *o = fnl.get_noise_3d(p.x, p.y, p.z);
            }
        });
        time(3, &mut |o| {
            use ::noise::NoiseFn;
            for (o, p) in o.iter_mut().zip(&pts) {
                *o = noise_rs.get([f64::from(p.x), f64::from(p.y), f64::from(p.z)]) as f32;
            }
        });
    }
    let rate = |t: f64| pts.len() as f64 / t / 1e6;
    let names = [
        "perlin_batch",
        "perlin (point by point)",
        "fastnoise-lite Perlin 3D",
        "noise crate Perlin 3D",
    ];
    for (name, t) in names.iter().zip(best) {
        println!("{name:26} {:7.1} M/s", rate(t));
    }
    println!(
        "perlin_batch / fastnoise-lite = {:.2}, / noise crate = {:.2}",
        best[2] / best[0],
        best[3] / best[0]
    );
}
