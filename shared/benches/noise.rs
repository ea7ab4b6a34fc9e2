//! Noise throughput: evaluations per second over 2^20 scattered points, one
//! thread, beside the `noise` crate's and FastNoise Lite's Perlin 3D.
//!
//! `cargo bench -p hypertexture --bench noise`

use std::hint::black_box;

use criterion::{Criterion, Throughput, criterion_group, criterion_main};
use glam::Vec3;
use hypertexture::field::noise::{self, Noise};
use hypertexture::math::random::SplitMix64;

const POINTS: usize = 1 << 20;

/// Scattered points in a 64-unit cube: every evaluation meets fresh lattice cells.
fn points() -> Vec<Vec3> {
    let mut r = SplitMix64::new(7);
    (0..POINTS)
        .map(|_| Vec3::new(r.next_f32(), r.next_f32(), r.next_f32()) * 64.0 - Vec3::splat(32.0))
        .collect()
}

fn bench(c: &mut Criterion) {
    let pts = points();
    let mut out = vec![0.0f32; POINTS];
    let tables = Noise::default();
    let mut g = c.benchmark_group("noise");
    g.throughput(Throughput::Elements(POINTS as u64));
    g.sample_size(10);

    g.bench_function("perlin", |b| {
        b.iter(|| {
            for (o, &p) in out.iter_mut().zip(&pts) {
                *o = tables.noise(p);
            }
            black_box(&out);
        })
    });
    g.bench_function("perlin_batch", |b| {
        b.iter(|| {
            noise::perlin_batch(&pts, &mut out);
            black_box(&out);
        })
    });
    g.bench_function("improved", |b| {
        b.iter(|| {
            let mut acc = 0.0f64;
            for p in &pts {
                acc += noise::improved(f64::from(p.x), f64::from(p.y), f64::from(p.z));
            }
            black_box(acc)
        })
    });
    g.bench_function("turbulence_6_octaves", |b| {
        b.iter(|| {
            for (o, &p) in out.iter_mut().zip(&pts) {
                *o = tables.turbulence(p, 6);
            }
            black_box(&out);
        })
    });

    // The same points through the `noise` crate (f64 only) ...
    let noise_rs = ::noise::Perlin::new(1989);
    g.bench_function("noise-rs_perlin", |b| {
        use ::noise::NoiseFn;
        b.iter(|| {
            for (o, p) in out.iter_mut().zip(&pts) {
                *o = noise_rs.get([f64::from(p.x), f64::from(p.y), f64::from(p.z)]) as f32;
            }
            black_box(&out);
        })
    });
    // ... and FastNoise Lite (frequency 1 so the lattice matches ours).
    let mut fnl = fastnoise_lite::FastNoiseLite::with_seed(1989);
    fnl.set_noise_type(Some(fastnoise_lite::NoiseType::Perlin));
    fnl.set_frequency(Some(1.0));
    g.bench_function("fastnoise-lite_perlin", |b| {
        b.iter(|| {
            for (o, p) in out.iter_mut().zip(&pts) {
                *o = fnl.get_noise_3d(p.x, p.y, p.z);
            }
            black_box(&out);
        })
    });
    g.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);
