//! The Pixel Stream Editor in whole scenes: expressions of the native DMFs give
//! the same image, knobs override, and mistakes are reported where they are.

use hypertexture::{Film, Overrides, Scene, SceneError};

fn scene_text(name: &str) -> String {
    let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../scenes")
        .join(name);
    std::fs::read_to_string(path).unwrap()
}

fn load(name: &str, size: u32, knobs: &[(&str, f64)]) -> Result<Scene, SceneError> {
    Scene::from_text(
        &scene_text(name),
        name,
        Overrides {
            width: Some(size),
            height: Some(size),
            knobs: knobs.iter().map(|(k, v)| (k.to_string(), *v)).collect(),
            ..Overrides::default()
        },
    )
}

fn render(scene: &Scene) -> Film {
    hypertexture::render::render(scene, 0, &|_| {})
}

fn assert_same(a: &Film, b: &Film, what: &str) {
    let differing = a
        .pixels()
        .iter()
        .zip(b.pixels())
        .filter(|(p, q)| p.to_array().map(f32::to_bits) != q.to_array().map(f32::to_bits))
        .count();
    assert_eq!(differing, 0, "{what}: {differing} pixels differ");
}

#[test]
fn fur_as_an_expression_is_the_native_fur_bit_for_bit() {
    let native = render(&load("fur.ron", 48, &[]).unwrap());
    let expression = render(&load("pse/fur.ron", 48, &[]).unwrap());
    assert!(
        native.pixels().iter().any(|p| p.rgba[3] > 0.5),
        "the donut is visible"
    );
    assert_same(&native, &expression, "fur");
}

#[test]
fn tribble_as_an_expression_is_the_native_tribble_bit_for_bit() {
    let native = render(&load("tribble.ron", 40, &[]).unwrap());
    let expression = render(&load("pse/tribble.ron", 40, &[]).unwrap());
    assert_same(&native, &expression, "tribble");
}

#[test]
fn knobs_change_the_image_and_are_checked() {
    let plain = render(&load("pse/fur.ron", 32, &[]).unwrap());
    let curly = render(&load("pse/fur.ron", 32, &[("curliness", 0.8)]).unwrap());
    let short = render(&load("pse/fur.ron", 32, &[("length", 0.5)]).unwrap());
    let coverage = |f: &Film| f.pixels().iter().filter(|p| p.depth > 0.0).count();
    assert_ne!(plain.pixels(), curly.pixels());
    assert!(
        coverage(&short) < coverage(&plain),
        "shorter hair covers less: {} vs {}",
        coverage(&short),
        coverage(&plain)
    );
    let e = load("pse/fur.ron", 32, &[("curliness", 5.0)])
        .unwrap_err()
        .to_string();
    assert!(e.contains("curliness") && e.contains("[0, 2]"), "{e}");
    let e = load("pse/fur.ron", 32, &[("curlyness", 0.5)])
        .unwrap_err()
        .to_string();
    assert!(e.contains("unknown knob") && e.contains("curliness"), "{e}");
    let e = load("fur.ron", 32, &[("curliness", 0.5)])
        .unwrap_err()
        .to_string();
    assert!(e.contains("no knobs"), "{e}");
}

#[test]
fn expression_errors_name_the_file_position_the_expression_position_and_a_caret() {
    let text = scene_text("pse/fur.ron").replace("if d > 0 { if d < 1", "if d > x { if d < 1");
    let e = Scene::from_text(&text, "bad.ron", Overrides::default())
        .unwrap_err()
        .to_string();
    let line = text.lines().position(|l| l.contains("if d > x")).unwrap() + 1;
    let column = text.lines().nth(line - 1).unwrap().find("x {").unwrap() + 1;
    assert!(
        e.starts_with(&format!("bad.ron:{line}:{column}: density: 1:")),
        "{e}"
    );
    assert!(e.contains("compares numbers, but this is a vector"), "{e}");
    let caret_line = e.lines().last().unwrap();
    let source_line = e.lines().nth(1).unwrap();
    assert_eq!(
        &source_line[caret_line.len() - 1..caret_line.len()],
        "x",
        "caret under the spot:\n{e}"
    );
    let text = scene_text("pse/fur.ron").replace("fn fur(p, d)", "fn fur(p d)");
    let e = Scene::from_text(&text, "bad.ron", Overrides::default())
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("functions: ") && e.contains("expected `,`"),
        "{e}"
    );
}

/// The notes' crawling-texture problem: with the scene's `transform`, the
/// density stays with a point of the moving, spinning sphere.
#[test]
fn a_moving_objects_density_follows_its_transform() {
    let scene = load("pse/spinning_marble.ron", 16, &[]).unwrap();
    let (speed, spin) = (0.03f32, 4.5f32.to_radians());
    let centre = glam::Vec3::new(-0.4, 0.0, 0.0);
    // A point of the sphere's soft region, in object space (its place at frame 0).
    let o = centre + glam::Vec3::new(0.5, 0.3, 0.55);
    let at0 = scene.density_at(o, 0);
    assert!(at0 > 0.0 && at0 < 1.0, "in the soft region: {at0}");
    for frame in 1..8u32 {
        // Where the object point is in the world at this frame.
        let a = spin * frame as f32;
        let q = o - centre;
        let rotated = glam::Vec3::new(
            q.x * a.cos() + q.z * a.sin(),
            q.y,
            -q.x * a.sin() + q.z * a.cos(),
        );
        let world = centre + rotated + glam::Vec3::new(speed * frame as f32, 0.0, 0.0);
        let now = scene.density_at(world, frame);
        assert!((now - at0).abs() < 1e-4, "frame {frame}: {now} vs {at0}");
        assert!(
            (scene.density_at(o, frame) - at0).abs() > 1e-3,
            "the world point itself has moved on"
        );
    }
}

/// A marble sphere moved two pixels a frame: with `transform` the frame-1 image
/// is the frame-0 image two pixels on, marble included (the texture sticks);
/// moving only the density (`D(x - frame·v)`), the marble crawls.
#[test]
fn a_solid_texture_sticks_to_its_moving_object() {
    // Orthographic, 2 units over 64 pixels: 1/32 a pixel; the object moves 1/16.
    let scene = |moving: &str| {
        let text = format!(
            r#"Scene(
                image: (width: 64, height: 64),
                camera: (eye: (0, 0, 4), look_at: (0, 0, 0), projection: Orthographic(height: 2.0)),
                lights: (ambient: (0.2, 0.2, 0.2), sources: [Directional(direction: (0, 0, 1), colour: (1, 1, 1))]),
                march: (bounds: (min: (-1, -1, -1), max: (1, 1, 1)), step: Length(0.02), opacity: 200.0),
                object: Sphere(centre: (0, 0, 0), radius: 0.55, softness: 0.1),
                functions: "fn marble(p) {{ sin(12 * p.x + 4 * turbulence(p * 3, 4)) }}",
                colour_map: (points: [(0.0, (0.1, 0.1, 0.3)), (1.0, (1.0, 0.9, 0.8))]),
                {moving}
            )"#
        );
        Scene::from_text(&text, "moving.ron", Overrides::default()).unwrap()
    };
    let sticks = scene(
        r#"transform: (velocity: (0.0625, 0, 0)), colour: "colour_map(0.5 + 0.5 * marble(x))","#,
    );
    let crawls = scene(
        r#"density: "D(x - frame * [0.0625, 0, 0])", colour: "colour_map(0.5 + 0.5 * marble(x))","#,
    );
    let difference = |scene: &Scene| {
        let (a, b) = (
            hypertexture::render::render(scene, 0, &|_| {}),
            hypertexture::render::render(scene, 1, &|_| {}),
        );
        let (mut worst, mut coverage) = (0.0f32, 0.0f32);
        for y in 0..64 {
            for x in 0..62 {
                let (p, q) = (a.get(x, y).rgba, b.get(x + 2, y).rgba);
                coverage += p[3];
                for c in 0..4 {
                    worst = worst.max((p[c] - q[c]).abs());
                }
            }
        }
        assert!(coverage > 500.0, "the sphere is in the picture: {coverage}");
        worst
    };
    let stuck = difference(&sticks);
    assert!(stuck < 2e-3, "the texture moves with its object: {stuck}");
    let crawled = difference(&crawls);
    assert!(
        crawled > 0.05,
        "in world space the texture would crawl: {crawled}"
    );
}
