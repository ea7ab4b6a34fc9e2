//! The fur density function and whole renders: `scenes/fur.ron` at 256² and
//! 512², every gallery scene at 256², in-process on all threads.
//!
//! `cargo bench -p hypertexture --bench render`

use std::hint::black_box;
use std::path::Path;

use criterion::{Criterion, Throughput, criterion_group, criterion_main};
use glam::Vec3;
use hypertexture::math::random::SplitMix64;
use hypertexture::{Overrides, Scene};

const GALLERY: [&str; 10] = [
    "noisy_sphere",
    "noisy_sphere_high_frequency",
    "noisy_sphere_high_amplitude",
    "fractal_sphere",
    "dripping_sphere",
    "eroded_cube",
    "blue_glass",
    "fire_ball",
    "fur",
    "tribble",
];

fn scene(name: &str, size: u32) -> Scene {
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join(format!("../scenes/{name}.ron"));
    Scene::load(
        path,
        Overrides {
            width: Some(size),
            height: Some(size),
            ..Overrides::default()
        },
    )
    .expect("gallery scene")
}

fn fur_density(c: &mut Criterion) {
    let fur = scene("fur", 64);
    // Points in the torus's soft region and around it, where the marcher samples.
    let mut r = SplitMix64::new(11);
    let pts: Vec<Vec3> = (0..1 << 16)
        .map(|_| {
            Vec3::new(
                r.next_f32() * 3.2 - 1.6,
                r.next_f32() * 1.2 - 0.6,
                r.next_f32() * 3.2 - 1.6,
            )
        })
        .collect();
    let mut g = c.benchmark_group("density");
    g.throughput(Throughput::Elements(pts.len() as u64));
    g.bench_function("fur", |b| {
        b.iter(|| pts.iter().map(|&p| fur.density_at(p, 0)).sum::<f32>())
    });
    g.finish();
}

fn renders(c: &mut Criterion) {
    let mut g = c.benchmark_group("render");
    g.sample_size(10);
    for size in [256, 512] {
        let s = scene("fur", size);
        g.bench_function(format!("fur_{size}"), |b| {
            b.iter(|| black_box(hypertexture::render::render(&s, 0, &|_| {})))
        });
    }
    // fur_256 is above.
    for name in GALLERY.into_iter().filter(|&n| n != "fur") {
        let s = scene(name, 256);
        g.bench_function(format!("{name}_256"), |b| {
            b.iter(|| black_box(hypertexture::render::render(&s, 0, &|_| {})))
        });
    }
    g.finish();
}

criterion_group!(benches, fur_density, renders);
criterion_main!(benches);
