//! Loading scene files: every gallery scene loads, and bad input is reported with
//! file:line:column and what was expected.

use hypertexture::{Overrides, Scene, SceneError};

fn gallery() -> Vec<std::path::PathBuf> {
    let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../scenes");
    let mut scenes: Vec<_> = std::fs::read_dir(&dir)
        .expect("scenes/ exists")
        .map(|e| e.expect("readable entry").path())
        .filter(|p| p.extension().is_some_and(|e| e == "ron"))
        .collect();
    scenes.sort();
    scenes
}

#[test]
fn every_gallery_scene_loads() {
    let scenes = gallery();
    assert!(
        scenes.len() >= 10,
        "the 1989 gallery has ten scenes, found {}",
        scenes.len()
    );
    for path in scenes {
        let scene = Scene::load(&path, Overrides::default()).unwrap_or_else(|e| panic!("{e}"));
        assert!(scene.width() > 0 && scene.step() > 0.0);
    }
}

#[test]
fn fur_is_the_scene_the_issue_specifies() {
    let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../scenes/fur.ron");
    let scene = Scene::load(&path, Overrides::default()).unwrap();
    assert_eq!((scene.width(), scene.height()), (512, 512));
    // step = bounding-box diagonal / 200 for the box ±1.6 × ±0.6 × ±1.6.
    let diagonal = (3.2f32 * 3.2 + 1.2 * 1.2 + 3.2 * 3.2).sqrt();
    assert!((scene.step() - diagonal / 200.0).abs() < 1e-6);
    // D = 1 inside minor radius 0.35, 0 beyond 0.60 (fur only thins the soft region).
    assert_eq!(scene.density_at(glam::Vec3::new(0.0, 0.0, 1.61), 0), 0.0);
    assert_eq!(scene.density_at(glam::Vec3::new(0.0, 0.61, 0.0), 0), 0.0);
    // The hard region is solid by default; `hard_core: Shaped` applies the
    // fur's formula there too, leaving most of it below 1.
    let core: Vec<glam::Vec3> = (0..64)
        .map(|i| {
            let a = i as f32 * 0.1;
            glam::Vec3::new(a.cos(), 0.2 * a.sin(), a.sin())
        })
        .collect();
    assert!(core.iter().all(|&p| scene.density_at(p, 0) == 1.0));
    let text = std::fs::read_to_string(&path).unwrap().replace(
        "modulation: [Fur(",
        "hard_core: Shaped,\n    modulation: [Fur(",
    );
    let shaped = Scene::from_text(&text, "fur.ron", Overrides::default()).unwrap();
    let below = core
        .iter()
        .filter(|&&p| shaped.density_at(p, 0) < 1.0)
        .count();
    assert!(below > 32, "{below} of 64 core points below 1");
    let bad = text.replace("hard_core: Shaped", "hard_core: Soft");
    let e = Scene::from_text(&bad, "fur.ron", Overrides::default())
        .unwrap_err()
        .to_string();
    assert!(e.contains("Soft") && e.contains("Solid"), "{e}");
}

const GOOD: &str = r#"Scene(
    image: (width: 32, height: 32),
    camera: (eye: (0.0, 0.0, 4.0), look_at: (0.0, 0.0, 0.0), projection: Perspective(fov_y: 45.0)),
    march: (bounds: (min: (-1.0, -1.0, -1.0), max: (1.0, 1.0, 1.0)), step: Diagonal(100), opacity: 10.0),
    object: Sphere(radius: 0.8, softness: 0.2),
)"#;

fn error_of(text: &str) -> (usize, usize, String) {
    match Scene::from_text(text, "bad.ron", Overrides::default()) {
        Err(SceneError::Parse {
            path,
            line,
            column,
            message,
        }) => {
            assert_eq!(path, "bad.ron");
            (line, column, message)
        }
        Err(other) => panic!("expected a parse error, got {other}"),
        Ok(_) => panic!("expected an error for:\n{text}"),
    }
}

#[test]
fn a_minimal_scene_loads() {
    let scene = Scene::from_text(GOOD, "good.ron", Overrides::default()).unwrap();
    assert_eq!(scene.width(), 32);
}

#[test]
fn unknown_field_names_line_and_column() {
    let (line, column, message) =
        error_of(&GOOD.replace("softness: 0.2", "softness: 0.2, colour: 3"));
    assert_eq!(line, 5);
    assert!(column > 40, "column {column}");
    assert!(message.contains("colour"), "{message}");
}

#[test]
fn a_bad_transform_is_named_where_it_is() {
    let with = |t: &str| {
        GOOD.replace(
            "    object: Sphere(radius: 0.8, softness: 0.2),\n",
            &format!("    object: Sphere(radius: 0.8, softness: 0.2),\n    transform: {t},\n"),
        )
    };
    Scene::from_text(
        &with("(velocity: (0.1, 0, 0), spin: 5)"),
        "t.ron",
        Overrides::default(),
    )
    .unwrap();
    let (line, _, message) = error_of(&with("(spin: 5, wobble: 1)"));
    assert_eq!(line, 6);
    assert!(
        message.contains("unknown field `wobble` in transform"),
        "{message}"
    );
    let (line, _, message) = error_of(&with("(axis: (0, 0, 0))"));
    assert_eq!(line, 6);
    assert!(message.contains("non-zero direction"), "{message}");
}

#[test]
fn negative_radius_is_out_of_range() {
    let (line, _, message) = error_of(&GOOD.replace("radius: 0.8", "radius: -0.8"));
    assert_eq!(line, 5);
    assert!(
        message.contains("positive") && message.contains("-0.8"),
        "{message}"
    );
}

#[test]
fn zero_step_and_nan_are_rejected() {
    let (line, _, message) = error_of(&GOOD.replace("Diagonal(100)", "Length(0.0)"));
    assert_eq!(line, 4);
    assert!(message.contains("positive"), "{message}");
    let (line, _, message) = error_of(&GOOD.replace("opacity: 10.0", "opacity: NaN"));
    assert_eq!(line, 4);
    assert!(message.contains("NaN"), "{message}");
}

#[test]
fn wrong_type_is_reported() {
    let (line, _, message) = error_of(&GOOD.replace("width: 32", "width: \"wide\""));
    assert_eq!(line, 2);
    assert!(message.to_lowercase().contains("expected"), "{message}");
}

#[test]
fn huge_resolution_is_refused() {
    let (line, _, message) =
        error_of(&GOOD.replace("width: 32, height: 32", "width: 16384, height: 16384"));
    assert_eq!(line, 2);
    assert!(message.contains("pixels"), "{message}");
    let err = Scene::from_text(
        GOOD,
        "good.ron",
        Overrides {
            width: Some(0),
            ..Overrides::default()
        },
    )
    .map(|_| ())
    .expect_err("width 0 is refused");
    assert!(err.to_string().contains("at least 1"));
}

#[test]
fn syntax_error_points_at_the_spot() {
    let (line, column, _) =
        error_of(&GOOD.replace("look_at: (0.0, 0.0, 0.0)", "look_at: (0.0, 0.0 0.0)"));
    assert_eq!(line, 3);
    assert!(column > 40, "column {column}");
}

#[test]
fn softness_beyond_radius_and_misordered_dmfs() {
    let (_, _, message) = error_of(&GOOD.replace("softness: 0.2", "softness: 2.0"));
    assert!(message.contains("twice the radius"), "{message}");
    let chain = GOOD.replace(
        "object: Sphere(radius: 0.8, softness: 0.2),",
        "object: Sphere(radius: 0.8, softness: 0.2),\n    modulation: [Gain(0.7), NoisyRadius(frequency: 2.0, amplitude: 0.5)],",
    );
    let (_, _, message) = error_of(&chain);
    assert!(message.contains("must come before Gain"), "{message}");
    let fur_on_union = GOOD.replace(
        "object: Sphere(radius: 0.8, softness: 0.2),",
        "object: Union([Sphere(radius: 0.8, softness: 0.2), Sphere(radius: 0.3, softness: 0.1)]),\n    modulation: [Fur(frequency: 10.0)],",
    );
    let (_, _, message) = error_of(&fur_on_union);
    assert!(message.contains("Fur"), "{message}");
}

#[test]
fn missing_file_and_non_utf8_are_clear() {
    let err = Scene::load("/definitely/not/here.ron", Overrides::default())
        .err()
        .unwrap();
    assert!(
        err.to_string()
            .starts_with("/definitely/not/here.ron: cannot read"),
        "{err}"
    );
}

#[test]
fn oversized_scene_is_refused() {
    let big = format!("{GOOD}\n//{}", "x".repeat(70_000));
    let err = Scene::from_text(&big, "big.ron", Overrides::default())
        .err()
        .unwrap();
    assert!(matches!(err, SceneError::TooLarge { .. }), "{err}");
}

#[test]
fn every_gilet_scene_loads_and_keeps_within_its_bounds() {
    let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../scenes/gilet");
    let mut count = 0;
    for entry in std::fs::read_dir(&dir).expect("scenes/gilet exists") {
        let path = entry.expect("readable entry").path();
        if path.extension().is_none_or(|e| e != "ron") {
            continue;
        }
        count += 1;
        for quality in [
            hypertexture::Quality::Interactive,
            hypertexture::Quality::High,
        ] {
            let overrides = Overrides {
                quality: Some(quality),
                ..Overrides::default()
            };
            let scene = Scene::load(&path, overrides).unwrap_or_else(|e| panic!("{e}"));
            assert!(scene.max_displacement() > 0.0, "{}", path.display());
        }
        let high = Scene::load(&path, Overrides::default()).unwrap();
        let fast = Scene::load(
            &path,
            Overrides {
                quality: Some(hypertexture::Quality::Interactive),
                ..Overrides::default()
            },
        )
        .unwrap();
        assert!(fast.step() > high.step(), "{}", path.display());
    }
    assert!(
        count >= 24,
        "the Gilet & Dischler gallery, found {count} scenes"
    );
}

/// The whole error of `text` as the user reads it.
fn full_error(text: &str) -> String {
    Scene::from_text(text, "bad.ron", Overrides::default())
        .map(|_| ())
        .unwrap_err()
        .to_string()
}

#[test]
fn a_type_error_names_the_field_and_what_was_found() {
    assert_eq!(
        full_error(&GOOD.replace("radius: 0.8", "radius: \"big\"")),
        "bad.ron:5:28: object.radius: expected a number, found the string \"big\""
    );
    assert_eq!(
        full_error(&GOOD.replace("width: 32", "width: wide")),
        "bad.ron:2:20: image.width: expected a whole number, found `wide`"
    );
    assert_eq!(
        full_error(&GOOD.replace("(0.0, 0.0, 4.0)", "(0.0, up, 4.0)")),
        "bad.ron:3:25: camera.eye[1]: expected a number, found `up`"
    );
}

#[test]
fn unknown_kinds_are_named_in_the_scene_s_words() {
    let with_modulation = GOOD.replace(
        "    object: Sphere(radius: 0.8, softness: 0.2),\n",
        "    object: Sphere(radius: 0.8, softness: 0.2),\n    modulation: [Furr(amount: 1.0)],\n",
    );
    let message = full_error(&with_modulation);
    assert!(
        message.starts_with(
            "bad.ron:6:18: unknown modulation `Furr`, expected one of `NoisyRadius`, "
        ) && message.contains(", `Bias`, `Gain`, "),
        "{message}"
    );
    assert_eq!(
        full_error(&GOOD.replace("Sphere(", "Sphear(")),
        "bad.ron:5:13: unknown object `Sphear`, expected one of `Sphere`, `Box`, `Torus`, `Union`, `Intersection`, `Difference`, `Complement`, `Max`, `Min`, `Hypertexture`"
    );
    // No type name of the program reaches the user, whatever is misspelt.
    for (from, to) in [
        ("Perspective(", "Persp("),
        ("Diagonal(100)", "Diag(100)"),
        ("softness: 0.2", "softnes: 0.2"),
        ("image: (width: 32, height: 32),\n", ""),
        ("step:", "stp:"),
    ] {
        let message = full_error(&GOOD.replace(from, to));
        assert!(
            !message.contains("Desc") && !message.contains("Fields"),
            "{from} → {to}: {message}"
        );
    }
}

#[test]
fn an_unclosed_bracket_is_reported_where_it_was_opened() {
    let text = "Scene(
    image: (width: 32, height: 32),
    camera: (eye: (0.0, 0.0, 4.0), look_at: (0.0, 0.0, 0.0), projection: Perspective(fov_y: 45.0)),
    march: (
        bounds: (min: (-1.0, -1.0, -1.0), max: (1.0, 1.0, 1.0),
        step: Diagonal(100),
        opacity: 10.0,
    ),
    object: Sphere(radius: 0.8, softness: 0.2),
)";
    assert_eq!(
        full_error(text),
        "bad.ron:5:17: unclosed `(`: opened here and never closed"
    );
    // Brackets in strings and comments do not count.
    let commented = GOOD.replace(
        "    object:",
        "    // a ( in a comment /* and ( nested */\n    colour: \"[(\",\n    object:",
    );
    assert!(!full_error(&commented).contains("unclosed"));
    assert_eq!(
        full_error(&GOOD.replace("softness: 0.2),", "softness: 0.2")),
        "bad.ron:5:19: unclosed `(`: opened here and never closed"
    );
}
