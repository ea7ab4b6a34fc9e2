//! Interoperability: an EXR we write, read back by OpenEXR itself (Python's
//! `OpenEXR` module, which `scripts/test` installs). Under CI (`CI=true`) a
//! missing module fails the test; elsewhere the test says why it skips.

use crate::support::*;

/// Prints every header attribute of the EXR named by argv[1] as one JSON object:
/// strings as text, matrices as 16 numbers row by row, others as text.
const PRINT_HEADER: &str = r#"
import json, sys
import OpenEXR

def plain(value):
    if isinstance(value, bytes):
        return value.decode("utf-8")
    if isinstance(value, (str, int, float)):
        return value
    if hasattr(value, "tolist"):
        flat = value.tolist()
        while flat and isinstance(flat[0], list):
            flat = [x for row in flat for x in row]
        return flat
    try:
        return [float(value[i][j]) for i in range(4) for j in range(4)]
    except Exception:
        return str(value)

if hasattr(OpenEXR, "File"):
    header = OpenEXR.File(sys.argv[1]).header()
else:
    header = OpenEXR.InputFile(sys.argv[1]).header()
print(json.dumps({k: plain(v) for k, v in header.items()}))
"#;

fn python_has_openexr() -> bool {
    std::process::Command::new("python3")
        .args(["-c", "import OpenEXR"])
        .output()
        .is_ok_and(|o| o.status.success())
}

#[test]
fn openexr_reads_the_camera_and_the_scene_from_the_header() {
    if !python_has_openexr() {
        let ci = std::env::var("CI").is_ok_and(|v| v == "true");
        assert!(
            !ci,
            "python3 cannot import OpenEXR: scripts/test installs it (pip install OpenEXR)"
        );
        eprintln!("skipped: python3 cannot import OpenEXR (scripts/test installs it)");
        return;
    }
    let dir = scratch("interop");
    let exr = dir.join("fur.exr");
    let fur = scene("fur");
    let out = coordinator(&[
        "--scene",
        fur.to_str().unwrap(),
        "--out",
        exr.to_str().unwrap(),
        "--width",
        "16",
        "--height",
        "12",
        "--frame",
        "2",
        "--in-process",
        "--quiet",
    ]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let script = dir.join("header.py");
    std::fs::write(&script, PRINT_HEADER).unwrap();
    let out = std::process::Command::new("python3")
        .arg(&script)
        .arg(&exr)
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let header: serde_json::Value = serde_json::from_slice(&out.stdout)
        .unwrap_or_else(|e| panic!("{e}: {}", String::from_utf8_lossy(&out.stdout)));
    assert_eq!(
        header["software"],
        format!("hypertexture {}", env!("CARGO_PKG_VERSION")),
        "{header}"
    );
    assert_eq!(
        header["hypertexture/scene"],
        std::fs::read_to_string(&fur).unwrap(),
        "{header}"
    );
    assert_eq!(header["hypertexture/frame"], 2, "{header}");
    assert_eq!(header["hypertexture/sceneName"], fur.display().to_string());
    // The camera of scenes/fur.ron: the eye at (0, 2.3, 2.9) looking at (0, -0.15, 0).
    let matrix = |name: &str| -> Vec<f64> {
        let m: Vec<f64> = header[name]
            .as_array()
            .unwrap_or_else(|| panic!("{name}: {header}"))
            .iter()
            .map(|v| v.as_f64().unwrap())
            .collect();
        assert_eq!(m.len(), 16, "{name}: {m:?}");
        m
    };
    let times = |p: [f64; 3], m: &[f64]| -> [f64; 4] {
        std::array::from_fn(|c| p[0] * m[c] + p[1] * m[4 + c] + p[2] * m[8 + c] + m[12 + c])
    };
    let to_camera = matrix("worldToCamera");
    let eye = times([0.0, 2.3, 2.9], &to_camera);
    assert!(eye[..3].iter().all(|c| c.abs() < 1e-5), "the eye: {eye:?}");
    let target = times([0.0, -0.15, 0.0], &to_camera);
    let distance = (2.45f64 * 2.45 + 2.9 * 2.9).sqrt();
    assert!(
        target[0].abs() < 1e-5 && target[1].abs() < 1e-5 && (target[2] + distance).abs() < 1e-4,
        "the target lies ahead, down −z: {target:?}"
    );
    let ndc = times([0.0, -0.15, 0.0], &matrix("worldToNDC"));
    assert!(
        (ndc[0] / ndc[3]).abs() < 1e-5 && (ndc[1] / ndc[3]).abs() < 1e-5,
        "the target is at the centre of the image: {ndc:?}"
    );
    std::fs::remove_dir_all(&dir).unwrap();
}
