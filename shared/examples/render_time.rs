//! Render times on a shared machine: each scene rendered in-process `runs`
//! times on `threads` threads (no file written), the best run printed in ms.
//! Build it from two versions and let them take turns (see BENCHMARKS.md) to
//! compare them fairly while other processes come and go.
//!
//! `cargo run --release -p hypertexture --example render_time -- SIZE RUNS THREADS SCENE...`
//! (`ISA=scalar`, `sse4.1` or `avx2` in the environment times that path).

use std::path::Path;
use std::time::Instant;

use hypertexture::{Overrides, Scene};

fn main() {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let [size, runs, threads, scenes @ ..] = args.as_slice() else {
        panic!("usage: render_time SIZE RUNS THREADS SCENE...");
    };
    let (size, runs, threads): (u32, usize, usize) = (
        size.parse().expect("size"),
        runs.parse().expect("runs"),
        threads.parse().expect("threads"),
    );
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()
        .expect("thread pool");
    for name in scenes {
        let path = Path::new(env!("CARGO_MANIFEST_DIR")).join(format!("../scenes/{name}.ron"));
        let mut scene = Scene::load(
            path,
            Overrides {
                width: Some(size),
                height: Some(size),
                ..Overrides::default()
            },
        )
        .expect("scene");
        if let Ok(isa) = std::env::var("ISA") {
            let isa = hypertexture::simd::Isa::available()
                .into_iter()
                .find(|i| i.name() == isa)
                .expect("ISA: an available path (scalar, sse4.1, avx2)");
            assert!(scene.set_isa(isa));
        }
        let best = (0..runs)
            .map(|_| {
                let start = Instant::now();
                std::hint::black_box(
                    pool.install(|| hypertexture::render::render(&scene, 0, &|_| {})),
                );
                start.elapsed().as_secs_f64()
            })
            .fold(f64::INFINITY, f64::min);
        println!("{name} {size} {:.1}", best * 1e3);
    }
}
