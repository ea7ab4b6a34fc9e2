//! Cost growth of the furry donut with resolution: with the
//! marching step tied to the pixel size the work per pixel grows with n, so the
//! frame costs O(n³), as the paper says; with the step fixed it costs O(n²).
//!
//! `cargo run --release -p hypertexture --example growth [-- 128,256,512,1024]`
//! prints the median of three in-process renders on every core.

use std::time::Instant;

use hypertexture::{Overrides, Scene};

fn main() {
    let sizes: Vec<u32> = std::env::args()
        .nth(1)
        .unwrap_or_else(|| "128,256,512,1024".into())
        .split(',')
        .map(|s| s.parse().expect("sizes: N,N,…"))
        .collect();
    let path = concat!(env!("CARGO_MANIFEST_DIR"), "/../scenes/fur.ron");
    let text = std::fs::read_to_string(path).expect("scenes/fur.ron");
    println!("| size | step tied to pixel (Diagonal(200·n/512)) | step fixed (Diagonal(200)) |");
    println!("|---|---|---|");
    for n in sizes {
        let tied = text.replace(
            "Diagonal(200)",
            &format!("Diagonal({})", (200 * n).div_ceil(512)),
        );
        let time = |text: &str| {
            let scene = Scene::from_text(
                text,
                "fur.ron",
                Overrides {
                    width: Some(n),
                    height: Some(n),
                    ..Overrides::default()
                },
            )
            .expect("scene");
            let mut runs: Vec<f64> = (0..3)
                .map(|_| {
                    let t = Instant::now();
                    std::hint::black_box(hypertexture::render::render(&scene, 0, &|_| {}));
                    t.elapsed().as_secs_f64()
                })
                .collect();
            runs.sort_by(f64::total_cmp);
            runs[1]
        };
        println!("| {n}² | {:.3} s | {:.3} s |", time(&tied), time(&text));
    }
}
