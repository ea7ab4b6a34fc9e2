//! Known-answer images: 64×64 renders of gallery scenes compared pixel for pixel
//! with the PNGs in tests/golden/. They change only on purpose:
//! `HYPERTEXTURE_BLESS=1 cargo test -p coordinator --test render golden::` rewrites them.

use crate::support::*;

const SCENES: [&str; 5] = ["fur", "tribble", "fire_ball", "blue_glass", "eroded_cube"];

#[test]
fn gallery_matches_golden_images() {
    let bless = std::env::var_os("HYPERTEXTURE_BLESS").is_some_and(|v| v == "1");
    let dir = scratch("golden");
    let mut failures = Vec::new();
    for name in SCENES {
        let out_path = dir.join(format!("{name}.png"));
        let out = coordinator(&[
            "--scene",
            scene(name).to_str().unwrap(),
            "--out",
            out_path.to_str().unwrap(),
            "--width",
            "64",
            "--height",
            "64",
            "--quiet",
        ]);
        assert!(
            out.status.success(),
            "{name}: {}",
            String::from_utf8_lossy(&out.stderr)
        );
        let golden = root().join("tests/golden").join(format!("{name}.png"));
        if bless {
            std::fs::copy(&out_path, &golden).unwrap();
            continue;
        }
        assert!(
            golden.exists(),
            "{} is missing: run HYPERTEXTURE_BLESS=1 cargo test -p coordinator --test render golden::",
            golden.display()
        );
        let (got, want) = (decode_png(&out_path), decode_png(&golden));
        if got.as_raw() != want.as_raw() {
            let differing = got
                .pixels()
                .zip(want.pixels())
                .filter(|(a, b)| a != b)
                .count();
            failures.push(format!("{name}: {differing} of {} pixels differ", 64 * 64));
        }
    }
    std::fs::remove_dir_all(&dir).unwrap();
    assert!(
        failures.is_empty(),
        "golden images differ (bless with HYPERTEXTURE_BLESS=1 if intended):\n{}",
        failures.join("\n")
    );
}

/// The golden images hold on every instruction-set path this CPU has, not
/// only the fastest the binary picks: each scene is rendered in-process on
/// scalar, SSE4.1, AVX2 and AVX-512 (as available) and compared byte for byte.
#[test]
fn golden_images_hold_on_every_isa_path() {
    if std::env::var_os("HYPERTEXTURE_BLESS").is_some_and(|v| v == "1") {
        return;
    }
    let dir = scratch("golden-isa");
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(2)
        .build()
        .unwrap();
    let mut failures = Vec::new();
    for name in SCENES {
        let want = decode_png(&root().join("tests/golden").join(format!("{name}.png")));
        let overrides = hypertexture::Overrides {
            width: Some(64),
            height: Some(64),
            ..Default::default()
        };
        for isa in hypertexture::math::simd::Isa::available() {
            let mut scene = hypertexture::Scene::load(scene(name), overrides.clone()).unwrap();
            assert!(scene.set_isa(isa));
            let film = pool.install(|| hypertexture::render::render(&scene, 0, &|_| {}));
            let out = dir.join(format!("{name}-{}.png", isa.name()));
            let metadata =
                coordinator::image::output::ImageMetadata::without_scene(64, 64, None, None);
            coordinator::image::output::write_image(&film, &out, &metadata).unwrap();
            let got = decode_png(&out);
            if got.as_raw() != want.as_raw() {
                let differing = got
                    .pixels()
                    .zip(want.pixels())
                    .filter(|(a, b)| a != b)
                    .count();
                failures.push(format!(
                    "{name} on {}: {differing} of {} pixels differ",
                    isa.name(),
                    64 * 64
                ));
            }
        }
    }
    std::fs::remove_dir_all(&dir).unwrap();
    assert!(failures.is_empty(), "{}", failures.join("\n"));
}
