//! The Pixel Stream Editor from the command line: `eval`, `--set`, `--frames`,
//! `recolor`, and knob overrides on the farm.

use crate::support::*;

fn ok(out: &std::process::Output) -> String {
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    String::from_utf8_lossy(&out.stdout).into_owned()
}

#[test]
fn eval_prints_perlins_reference_value_and_probes_scenes() {
    let out = coordinator(&["eval", "improved(3.14, 42, 7)"]);
    assert_eq!(ok(&out).trim(), "0.13691995878400012");
    let fur = scene("pse/fur");
    let out = coordinator(&[
        "eval",
        "[D(x), fineness, length]",
        "--scene",
        fur.to_str().unwrap(),
        "--at",
        "1,0,0",
        "--set",
        "fineness=12.5",
    ]);
    assert_eq!(ok(&out).trim(), "(1, 12.5, 1)");
    let out = coordinator(&["eval", "noise(x)", "--at", "0.5,0.25,0.125"]);
    let v: f32 = ok(&out).trim().parse().unwrap();
    assert_eq!(
        v,
        hypertexture::field::noise::perlin(glam::Vec3::new(0.5, 0.25, 0.125))
    );
    let out = coordinator(&["eval", "1 + nosie(x)"]);
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        err.contains("1:5: unknown function `nosie`")
            && err.contains("    1 + nosie(x)\n        ^"),
        "{err}"
    );
}

#[test]
fn set_overrides_knobs_and_rejects_bad_ones() {
    let dir = scratch("pse-set");
    let render = |name: &str, set: &[&str]| {
        let out_path = dir.join(name);
        let scene_path = scene("pse/fur");
        let mut args = vec![
            "--scene",
            scene_path.to_str().unwrap(),
            "--out",
            out_path.to_str().unwrap(),
            "--width",
            "24",
            "--height",
            "24",
            "--in-process",
            "--quiet",
        ];
        for s in set {
            args.push("--set");
            args.push(s);
        }
        let out = coordinator(&args);
        (out, out_path)
    };
    let (out, plain) = render("plain.png", &[]);
    ok(&out);
    let (out, curly) = render("curly.png", &["curliness=0.9", "fineness=25"]);
    ok(&out);
    assert_ne!(decode_png(&plain), decode_png(&curly));
    let (out, _) = render("bad.png", &["curliness=7"]);
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        err.contains("curliness=7") && err.contains("[0, 2]"),
        "{err}"
    );
    let (out, _) = render("bad.png", &["wiggle=1"]);
    assert!(String::from_utf8_lossy(&out.stderr).contains("unknown knob"));
    let (out, _) = render("bad.png", &["curliness"]);
    assert!(String::from_utf8_lossy(&out.stderr).contains("KNOB=VALUE"));
}

#[test]
fn knob_overrides_reach_farm_workers() {
    let dir = scratch("pse-farm");
    let fur = scene("pse/fur");
    let local = dir.join("local.png");
    let farm = dir.join("farm.png");
    for (path, mode) in [(&local, "--in-process"), (&farm, "--local-workers=2")] {
        ok(&coordinator(&[
            "--scene",
            fur.to_str().unwrap(),
            "--out",
            path.to_str().unwrap(),
            "--width",
            "24",
            "--height",
            "20",
            "--set",
            "curliness=0.7",
            mode,
            "--quiet",
        ]));
    }
    assert_eq!(
        std::fs::read(&local).unwrap(),
        std::fs::read(&farm).unwrap()
    );
}

#[test]
fn frames_write_a_numbered_sequence() {
    let dir = scratch("pse-frames");
    let out = dir.join("fire.png");
    ok(&coordinator(&[
        "--scene",
        scene("pse/corona").to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
        "--width",
        "16",
        "--height",
        "16",
        "--frames",
        "1..=3",
        "--in-process",
        "--quiet",
    ]));
    let frames: Vec<_> = (1..=3)
        .map(|f| decode_png(&dir.join(format!("fire_{f:04}.png"))))
        .collect();
    assert!(!dir.join("fire.png").exists() && !dir.join("fire_0004.png").exists());
    assert_ne!(frames[0], frames[1], "the corona moves");
    // On the farm, each frame is split into pixel sets: the same bytes.
    let farm = scratch("pse-frames-farm");
    ok(&coordinator(&[
        "--scene",
        scene("pse/corona").to_str().unwrap(),
        "--out",
        farm.join("fire.png").to_str().unwrap(),
        "--width",
        "16",
        "--height",
        "16",
        "--frames",
        "1..4",
        "--local-workers=2",
        "--quiet",
    ]));
    for f in 1..=3 {
        let name = format!("fire_{f:04}.png");
        assert_eq!(
            std::fs::read(dir.join(&name)).unwrap(),
            std::fs::read(farm.join(&name)).unwrap(),
            "{name}"
        );
    }
}

#[test]
fn recolor_maps_the_density_channel_again() {
    let dir = scratch("pse-recolor");
    let exr = dir.join("fur.exr");
    ok(&coordinator(&[
        "--scene",
        scene("fur").to_str().unwrap(),
        "--out",
        exr.to_str().unwrap(),
        "--width",
        "24",
        "--height",
        "24",
        "--in-process",
        "--quiet",
    ]));
    let fire = dir.join("fire.png");
    let ice = dir.join("ice.png");
    for (map, out) in [("fire", &fire), ("ice", &ice)] {
        let colormap = root().join(format!("scenes/colormaps/{map}.ron"));
        ok(&coordinator(&[
            "recolor",
            exr.to_str().unwrap(),
            "--colormap",
            colormap.to_str().unwrap(),
            "--out",
            out.to_str().unwrap(),
        ]));
    }
    let (fire, ice) = (decode_png(&fire), decode_png(&ice));
    assert_eq!(fire.dimensions(), (24, 24));
    // Fire is red-dominant where there is fur, ice blue-dominant.
    let (mut red, mut blue) = (0u32, 0u32);
    for (f, i) in fire.pixels().zip(ice.pixels()) {
        if f.0[3] > 128 {
            red += u32::from(f.0[0] > f.0[2]);
            blue += u32::from(i.0[2] > i.0[0]);
        }
    }
    assert!(red > 50 && blue > 50, "red {red}, blue {blue}");
    let out = coordinator(&[
        "recolor",
        root().join("scenes/fur.ron").to_str().unwrap(),
        "--colormap",
        root().join("scenes/colormaps/fire.ron").to_str().unwrap(),
        "--out",
        dir.join("x.png").to_str().unwrap(),
    ]);
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("density"));
}
