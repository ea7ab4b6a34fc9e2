//! The coordinator binary as a user meets it: renders, errors, exit codes.

use crate::support::*;

#[test]
fn renders_a_scene_to_png_and_exr() {
    let dir = scratch("cli-render");
    let png = dir.join("fur.png");
    let out = coordinator(&[
        "--scene",
        scene("fur").to_str().unwrap(),
        "--out",
        png.to_str().unwrap(),
        "--width",
        "32",
        "--height",
        "24",
        "--quiet",
    ]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(
        out.stderr.is_empty(),
        "--quiet prints nothing: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    let img = decode_png(&png);
    assert_eq!(img.dimensions(), (32, 24));
    assert!(img.pixels().any(|p| p.0[0] > 60), "the fur is visible");

    let exr = dir.join("fur.exr");
    let out = coordinator(&[
        "--scene",
        scene("fur").to_str().unwrap(),
        "--out",
        exr.to_str().unwrap(),
        "--width",
        "16",
        "--height",
        "16",
        "--threads",
        "1",
        "--in-process",
    ]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let log = String::from_utf8_lossy(&out.stderr);
    assert!(
        log.contains("rendered") && log.contains("1 thread"),
        "{log}"
    );
    let bytes = std::fs::read(&exr).unwrap();
    assert_eq!(
        &bytes[..4],
        &[0x76, 0x2f, 0x31, 0x01],
        "OpenEXR magic number"
    );
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn a_broken_scene_names_file_line_and_column() {
    let dir = scratch("cli-broken");
    let bad = dir.join("bad.ron");
    let text = std::fs::read_to_string(scene("noisy_sphere"))
        .unwrap()
        .replace("radius: 1.0", "radius: -1.0");
    std::fs::write(&bad, text).unwrap();
    let out = coordinator(&[
        "--scene",
        bad.to_str().unwrap(),
        "--out",
        dir.join("x.png").to_str().unwrap(),
    ]);
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    let expected = format!("error: {}:", bad.display());
    assert!(err.starts_with(&expected), "{err}");
    assert!(
        err.contains("expected a positive number, found -1"),
        "{err}"
    );
    assert_eq!(err.lines().count(), 1, "one clear line: {err}");
    assert!(!err.contains("panicked"));
    assert!(!dir.join("x.png").exists());
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn bad_flags_and_outputs_fail_cleanly() {
    let fur = scene("fur");
    let fur = fur.to_str().unwrap();
    for args in [
        vec!["--scene", fur, "--threads", "0"],
        vec!["--scene", fur, "--width", "-3"],
        vec!["--scene", fur, "--width", "100000"],
        vec!["--scene", fur, "--frobnicate"],
        vec!["--scene", fur, "--spp", "0"],
        vec!["--scene", fur, "--spp", "5000"],
        vec!["--scene", fur, "--quality", "ultra"],
        vec!["--out", "x.png"],
    ] {
        let out = coordinator(&args);
        assert!(!out.status.success(), "{args:?} should fail");
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(err.contains("error"), "{args:?}: {err}");
        assert!(!err.contains("panicked"), "{args:?}: {err}");
    }
    let out = coordinator(&["--scene", fur, "--out", "/tmp/x.jpg"]);
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("unsupported output format"));
    let out = coordinator(&["--scene", "no/such/scene.ron", "--out", "/tmp/x.png"]);
    assert!(!out.status.success());
    assert!(
        String::from_utf8_lossy(&out.stderr).contains("no/such/scene.ron: cannot read the scene")
    );
}

#[test]
fn an_image_renders_again_from_the_scene_it_stores() {
    let dir = scratch("cli-rerender");
    let fur = scene("pse/fur");
    for (name, farm) in [("first.png", false), ("first.exr", true)] {
        let first = dir.join(name);
        let mut args = vec![
            "--scene",
            fur.to_str().unwrap(),
            "--out",
            first.to_str().unwrap(),
            "--width",
            "20",
            "--height",
            "14",
            "--frame",
            "3",
            "--spp",
            "2",
            "--quality",
            "interactive",
            "--set",
            "curliness=0.6",
            "--quiet",
        ];
        if !farm {
            args.push("--in-process");
        }
        let out = coordinator(&args);
        assert!(
            out.status.success(),
            "{}",
            String::from_utf8_lossy(&out.stderr)
        );
        // From the image alone, in-process and on the farm: the same bytes.
        for (again, farm) in [("again.png", farm), ("again_farm.png", !farm)] {
            let again = dir.join(again).with_extension(first.extension().unwrap());
            let mut args = vec![
                "--scene",
                first.to_str().unwrap(),
                "--out",
                again.to_str().unwrap(),
                "--quiet",
            ];
            if !farm {
                args.push("--in-process");
            }
            let out = coordinator(&args);
            assert!(
                out.status.success(),
                "{}",
                String::from_utf8_lossy(&out.stderr)
            );
            assert!(
                std::fs::read(&first).unwrap() == std::fs::read(&again).unwrap(),
                "{} differs from {}",
                again.display(),
                first.display()
            );
        }
    }
    // An image written from no scene (a recoloured one) says what is missing.
    let recoloured = dir.join("recoloured.png");
    let out = coordinator(&[
        "recolor",
        dir.join("first.exr").to_str().unwrap(),
        "--colormap",
        root().join("scenes/colormaps/fire.ron").to_str().unwrap(),
        "--out",
        recoloured.to_str().unwrap(),
    ]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let out = coordinator(&[
        "--scene",
        recoloured.to_str().unwrap(),
        "--out",
        dir.join("x.png").to_str().unwrap(),
        "--in-process",
    ]);
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert_eq!(
        err.trim_end(),
        format!(
            "error: {}: the image holds no scene (no `hypertexture:scene` text chunk): it was not written by hypertexture {} or its metadata was stripped",
            recoloured.display(),
            env!("CARGO_PKG_VERSION")
        )
    );
    std::fs::remove_dir_all(&dir).unwrap();
}
