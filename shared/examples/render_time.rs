//! Render times on a shared machine: each scene rendered in-process `runs`
//! times on `threads` threads (no file written), the best run printed in ms.
//! Build it from two versions and let them take turns (docs/benchmark-log.md,
//! "Fair comparisons on a shared machine") to compare them fairly while other
//! processes come and go.
//!
//! `cargo run --release -p hypertexture --example render_time -- SIZE RUNS THREADS SCENE...`
//! (`ISA=scalar`, `sse4.1`, `avx2` or `avx512` in the environment times that path;
//! `QUALITY=interactive` the interactive preset, four times the step).

use std::path::Path;
use std::time::Instant;

use hypertexture::{Overrides, Quality, Scene};

const USAGE: &str = "usage: render_time SIZE RUNS THREADS SCENE... (scenes by name under scenes/)";

fn main() -> std::process::ExitCode {
    match run() {
        Ok(()) => std::process::ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("render_time: {e}");
            std::process::ExitCode::from(2)
        }
    }
}

fn run() -> Result<(), String> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let [size, runs, threads, scenes @ ..] = args.as_slice() else {
        return Err(USAGE.into());
    };
    if scenes.is_empty() {
        return Err(USAGE.into());
    }
    let number = |what: &str, v: &str| -> Result<usize, String> {
        v.parse()
            .ok()
            .filter(|&n| n > 0)
            .ok_or_else(|| format!("{what} must be a positive integer, not {v:?}; {USAGE}"))
    };
    let size = u32::try_from(number("SIZE", size)?).map_err(|_| "SIZE is too large".to_string())?;
    let (runs, threads) = (number("RUNS", runs)?, number("THREADS", threads)?);
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()
        .map_err(|e| format!("cannot start {threads} threads: {e}"))?;
    for name in scenes {
        let path = Path::new(env!("CARGO_MANIFEST_DIR")).join(format!("../scenes/{name}.ron"));
        let mut scene = Scene::load(
            path,
            Overrides {
                width: Some(size),
                height: Some(size),
                quality: match std::env::var("QUALITY") {
                    Ok(q) => Some(q.parse::<Quality>().map_err(|e| format!("QUALITY={e}"))?),
                    Err(_) => None,
                },
                ..Overrides::default()
            },
        )
        .map_err(|e| e.to_string())?;
        if let Ok(isa) = std::env::var("ISA") {
            let isa = hypertexture::math::simd::Isa::available()
                .into_iter()
                .find(|i| i.name() == isa)
                .ok_or_else(|| {
                    format!("ISA={isa}: not a path this CPU has (scalar, sse4.1, avx2, avx512)")
                })?;
            scene.set_isa(isa);
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
    Ok(())
}
