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
    let text =
        scene_text("pse/fur.ron").replace("if d > 0 { fur(p, d) }", "if d > x { fur(p, d) }");
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

/// The notes' crawling-texture problem: evaluated at the object-space point, the
/// marble and the density stay with a point of the moving, spinning sphere.
#[test]
fn a_solid_texture_in_object_space_sticks_to_its_moving_object() {
    let text = scene_text("pse/spinning_marble.ron");
    let desc = hypertexture::scene::parse(&text, "spinning_marble.ron").unwrap();
    let knobs = hypertexture::scene::knob_values(&desc, &[]).unwrap();
    let (speed, spin) = (knobs["speed"] as f32, knobs["spin"] as f32);
    let centre = glam::Vec3::new(-0.4, 0.0, 0.0);
    // A point of the sphere's soft region, in object space (its place at frame 0).
    let o = centre + glam::Vec3::new(0.5, 0.3, 0.55);
    let probe = |frame: u32, x: glam::Vec3| {
        hypertexture::pse::surface::probe(
            "[D(object(x)), marble(object(x)), marble(x)]",
            Some(&desc),
            &knobs,
            x,
            frame,
        )
        .unwrap()
        .components
    };
    let at0 = probe(0, o);
    assert!(at0[0] > 0.0 && at0[0] < 1.0, "in the soft region: {at0:?}");
    let mut crawled = 0.0f64;
    for frame in 1..8u32 {
        // Where the object point is in the world at this frame.
        let a = spin * frame as f32;
        let q = o - centre;
        let rotated = glam::Vec3::new(
            q.x * libm::cosf(a) + q.z * libm::sinf(a),
            q.y,
            -q.x * libm::sinf(a) + q.z * libm::cosf(a),
        );
        let world = centre + rotated + glam::Vec3::new(speed * frame as f32, 0.0, 0.0);
        let now = probe(frame, world);
        assert!(
            (now[0] - at0[0]).abs() < 1e-4,
            "density sticks: {now:?} vs {at0:?}"
        );
        assert!(
            (now[1] - at0[1]).abs() < 1e-3,
            "marble sticks: {now:?} vs {at0:?}"
        );
        crawled += (now[2] - at0[2]).abs();
    }
    assert!(
        crawled > 0.1,
        "in world space the texture would crawl: {crawled}"
    );
}
