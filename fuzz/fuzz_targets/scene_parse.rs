//! Any bytes as a scene file: loading must never panic or hang.
#![no_main]

use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    if let Ok(text) = std::str::from_utf8(data) {
        let overrides = hypertexture::Overrides {
            width: Some(4),
            height: Some(4),
            ..Default::default()
        };
        if let Ok(scene) = hypertexture::Scene::from_text(text, "fuzz.ron", overrides) {
            for x in [glam::Vec3::ZERO, glam::Vec3::new(0.3, -0.7, 0.2)] {
                let _ = scene.density_at(x, 3);
            }
        }
    }
});
