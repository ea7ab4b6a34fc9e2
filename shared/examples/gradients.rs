//! The shading normal three ways: each scene rendered in-process with the
//! paper's forward differences (the default), central differences and the
//! dual-number derivative, with the best of `runs` times and how far each image
//! is from the forward differences' in 8-bit sRGB: the mean and largest
//! difference of a channel, the share of pixels that differ by more than 2
//! levels in any channel, and the PSNR.
//!
//! `cargo run --release -p hypertexture --example gradients -- SIZE RUNS THREADS SCENE...`

use std::path::Path;
use std::time::Instant;

use hypertexture::scene::Gradient;
use hypertexture::{Film, Overrides, Scene};

fn main() {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let [size, runs, threads, scenes @ ..] = args.as_slice() else {
        eprintln!("usage: gradients SIZE RUNS THREADS SCENE...");
        std::process::exit(2);
    };
    let parse = |what: &str, v: &str| -> usize {
        v.parse().unwrap_or_else(|_| {
            eprintln!("gradients: {what} must be a whole number, got {v:?}");
            std::process::exit(2)
        })
    };
    let (size, runs, threads) = (
        parse("SIZE", size) as u32,
        parse("RUNS", runs).max(1),
        parse("THREADS", threads),
    );
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()
        .expect("thread pool");
    println!(
        "| scene | gradient | time (ms) | mean Δ | max Δ | pixels > 2 | PSNR (dB) |\n|---|---|---:|---:|---:|---:|---:|"
    );
    for name in scenes {
        let path = Path::new(env!("CARGO_MANIFEST_DIR")).join(format!("../scenes/{name}.ron"));
        let mut scene = match Scene::load(
            path,
            Overrides {
                width: Some(size),
                height: Some(size),
                ..Overrides::default()
            },
        ) {
            Ok(scene) => scene,
            Err(e) => {
                eprintln!("gradients: {e}");
                std::process::exit(1);
            }
        };
        let mut reference: Option<Vec<u8>> = None;
        for gradient in [Gradient::Forward, Gradient::Central, Gradient::Dual] {
            scene.set_gradient(gradient);
            let mut film = Film::new(1, 1);
            let best = (0..runs)
                .map(|_| {
                    let start = Instant::now();
                    film = pool.install(|| hypertexture::render::render(&scene, 0, &|_| {}));
                    start.elapsed().as_secs_f64()
                })
                .fold(f64::INFINITY, f64::min);
            let bytes = film.to_srgb8();
            let reference = reference.get_or_insert_with(|| bytes.clone());
            let d = Difference::between(reference, &bytes);
            println!(
                "| {name} | {gradient:?} | {:.0} | {:.3} | {} | {:.2}% | {} |",
                best * 1e3,
                d.mean,
                d.max,
                d.share_over_2 * 100.0,
                if d.psnr.is_finite() {
                    format!("{:.1}", d.psnr)
                } else {
                    "∞".to_string()
                }
            );
        }
    }
}

/// How far two 8-bit RGBA images are apart, over the RGB channels.
struct Difference {
    mean: f64,
    max: u8,
    share_over_2: f64,
    psnr: f64,
}

impl Difference {
    fn between(a: &[u8], b: &[u8]) -> Difference {
        let (mut sum, mut squares, mut max, mut over) = (0u64, 0u64, 0u8, 0usize);
        let pixels = a.len() / 4;
        for (p, q) in a.chunks_exact(4).zip(b.chunks_exact(4)) {
            let mut worst = 0;
            for c in 0..3 {
                let d = p[c].abs_diff(q[c]);
                sum += u64::from(d);
                squares += u64::from(d) * u64::from(d);
                worst = worst.max(d);
            }
            max = max.max(worst);
            over += usize::from(worst > 2);
        }
        let n = (3 * pixels) as f64;
        let mse = squares as f64 / n;
        Difference {
            mean: sum as f64 / n,
            max,
            share_over_2: over as f64 / pixels as f64,
            psnr: 10.0 * (255.0f64 * 255.0 / mse).log10(),
        }
    }
}
