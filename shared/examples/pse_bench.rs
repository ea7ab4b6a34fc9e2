//! Expression fur against native fur: renders the furry donut and the tribble
//! with the built-in Fur DMF and as Pixel Stream Editor expressions
//! (scenes/pse/), on one thread, alternating, and prints the timings and whether
//! the images are bit-for-bit identical.
//!
//! ```sh
//! nice -n 19 cargo run --release -p hypertexture --example pse_bench -- 128 5
//! ```

use std::time::{Duration, Instant};

use hypertexture::{Film, Overrides, Scene};

fn load(name: &str, size: u32) -> Scene {
    let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../scenes")
        .join(name);
    let text = std::fs::read_to_string(&path).expect("scene file");
    Scene::from_text(
        &text,
        name,
        Overrides {
            width: Some(size),
            height: Some(size),
            ..Overrides::default()
        },
    )
    .expect("scene loads")
}

fn time(pool: &rayon::ThreadPool, scene: &Scene) -> (Film, Duration) {
    let start = Instant::now();
    let film = pool.install(|| hypertexture::render::render(scene, 0, &|_| {}));
    (film, start.elapsed())
}

fn main() {
    let mut args = std::env::args().skip(1);
    let size: u32 = args.next().and_then(|s| s.parse().ok()).unwrap_or(128);
    let runs: usize = args.next().and_then(|s| s.parse().ok()).unwrap_or(5);
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(1)
        .build()
        .expect("a thread");
    println!("{size}×{size}, 1 thread, {runs} runs each (alternating), min / median:");
    for (native, expression) in [
        ("fur.ron", "pse/fur.ron"),
        ("tribble.ron", "pse/tribble.ron"),
    ] {
        let (a, b) = (load(native, size), load(expression, size));
        let (mut ta, mut tb) = (Vec::new(), Vec::new());
        let mut identical = true;
        for _ in 0..runs {
            let (fa, da) = time(&pool, &a);
            let (fb, db) = time(&pool, &b);
            identical &= fa
                .pixels()
                .iter()
                .zip(fb.pixels())
                .all(|(p, q)| p.to_array().map(f32::to_bits) == q.to_array().map(f32::to_bits));
            ta.push(da);
            tb.push(db);
        }
        ta.sort();
        tb.sort();
        let (min_a, med_a) = (ta[0].as_secs_f64(), ta[runs / 2].as_secs_f64());
        let (min_b, med_b) = (tb[0].as_secs_f64(), tb[runs / 2].as_secs_f64());
        println!(
            "{native:<12} native {min_a:.3} s / {med_a:.3} s   {expression:<16} expression {min_b:.3} s / {med_b:.3} s   ratio {:.2} (median {:.2})   identical: {identical}",
            min_b / min_a,
            med_b / med_a
        );
    }
}
