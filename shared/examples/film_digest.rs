//! The digest of whole renders: for each scene, on every instruction-set
//! path this CPU has, FNV-1a over the bits of every channel of every pixel.
//! Built from two versions, equal digests say a change left every pixel's
//! bits alone (speed work must); it also shows the paths agree.
//!
//! `cargo run --release -p hypertexture --example film_digest -- SIZE SCENE...`
//! (scenes by path, e.g. `scenes/fur.ron`; `QUALITY=interactive` the
//! interactive preset).

use hypertexture::math::simd::Isa;
use hypertexture::{Overrides, Quality, Scene};

const USAGE: &str = "usage: film_digest SIZE SCENE... (scene files by path)";

fn main() -> std::process::ExitCode {
    match run() {
        Ok(()) => std::process::ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("film_digest: {e}");
            std::process::ExitCode::from(2)
        }
    }
}

fn run() -> Result<(), String> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let [size, scenes @ ..] = args.as_slice() else {
        return Err(USAGE.into());
    };
    if scenes.is_empty() {
        return Err(USAGE.into());
    }
    let size: u32 = size
        .parse()
        .ok()
        .filter(|&n| n > 0)
        .ok_or_else(|| format!("SIZE must be a positive integer, not {size:?}; {USAGE}"))?;
    let quality = match std::env::var("QUALITY") {
        Ok(q) => Some(q.parse::<Quality>().map_err(|e| format!("QUALITY={e}"))?),
        Err(_) => None,
    };
    for path in scenes {
        let mut scene = Scene::load(
            path,
            Overrides {
                width: Some(size),
                height: Some(size),
                quality,
                ..Overrides::default()
            },
        )
        .map_err(|e| e.to_string())?;
        let digests: Vec<String> = Isa::available()
            .into_iter()
            .map(|isa| {
                scene.set_isa(isa);
                let film = hypertexture::render::render(&scene, 0, &|_| {});
                format!("{}={:016x}", isa.name(), fnv1a(film.pixels()))
            })
            .collect();
        println!("{path} {}", digests.join(" "));
    }
    Ok(())
}

/// FNV-1a over the little-endian bits of every channel.
fn fnv1a(pixels: &[hypertexture::render::film::Sample]) -> u64 {
    let mut h: u64 = 0xcbf2_9ce4_8422_2325;
    for p in pixels {
        for c in p.to_array() {
            for b in c.to_bits().to_le_bytes() {
                h = (h ^ u64::from(b)).wrapping_mul(0x0000_0100_0000_01b3);
            }
        }
    }
    h
}
