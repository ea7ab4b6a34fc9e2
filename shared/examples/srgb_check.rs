//! Checks [`hypertexture::render::film::srgb_byte`] (a table of thresholds) against the
//! `powf` it replaces, `to_byte(linear_to_srgb(c))`, for every `f32` in [0, 1]:
//! about 1.07·10⁹ values, a few seconds in release on all cores. The test suite
//! checks the neighbourhood of every threshold and a sweep; this is the proof.
//!
//! `cargo run --release -p hypertexture --example srgb_check`

use hypertexture::render::film::{linear_to_srgb, srgb_byte, to_byte};

fn main() {
    let threads = std::thread::available_parallelism().map_or(1, |n| n.get()) as u32;
    let top = 1.0f32.to_bits() + 1;
    let start = std::time::Instant::now();
    let mismatches: u64 = std::thread::scope(|s| {
        let workers: Vec<_> = (0..threads)
            .map(|i| {
                s.spawn(move || {
                    let from = top / threads * i;
                    let to = if i + 1 == threads {
                        top
                    } else {
                        top / threads * (i + 1)
                    };
                    let mut bad = 0u64;
                    for bits in from..to {
                        let c = f32::from_bits(bits);
                        if srgb_byte(c) != to_byte(linear_to_srgb(c)) {
                            if bad < 10 {
                                eprintln!(
                                    "mismatch at {c:e}: table {} powf {}",
                                    srgb_byte(c),
                                    to_byte(linear_to_srgb(c))
                                );
                            }
                            bad += 1;
                        }
                    }
                    bad
                })
            })
            .collect();
        workers
            .into_iter()
            .map(|w| w.join().expect("a checker thread"))
            .sum()
    });
    println!(
        "{top} floats in [0, 1] checked in {:.1} s: {mismatches} mismatches",
        start.elapsed().as_secs_f64()
    );
    if mismatches > 0 {
        std::process::exit(1);
    }
}
