//! Nanoseconds per pixel of encoding a film's samples as 8-bit sRGB: the whole
//! film at once (cold), and in tiles of 4096 samples just written (warm), as a
//! worker encodes a unit's tile.
use hypertexture::{PixelFormat, Sample};
use std::time::Instant;

fn main() {
    let n = 2048 * 2048;
    let mut samples = Vec::with_capacity(n);
    let mut x = 0x9E37_79B9u32;
    for _ in 0..n {
        let mut next = || {
            x ^= x << 13;
            x ^= x >> 17;
            x ^= x << 5;
            (x >> 8) as f32 / (1 << 24) as f32
        };
        let a = next();
        samples.push(Sample {
            rgba: [next() * a, next() * a, next() * a, a],
            ..Sample::default()
        });
    }
    for _ in 0..3 {
        let t = Instant::now();
        std::hint::black_box(PixelFormat::Srgb8.encode(&samples));
        let whole = t.elapsed().as_secs_f64() * 1e9 / n as f64;
        let t = Instant::now();
        for chunk in samples.chunks(4096) {
            std::hint::black_box(PixelFormat::Srgb8.encode(chunk));
        }
        let tiles = t.elapsed().as_secs_f64() * 1e9 / n as f64;
        println!("whole film {whole:.2} ns/px, tiles of 4096 {tiles:.2} ns/px");
    }
}
