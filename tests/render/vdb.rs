//! `coordinator bake` read back by OpenVDB itself (Debian's `python3-openvdb`,
//! which `scripts/test` installs): the grids' names, classes and transform,
//! the active voxels, and every value equal to the library's density (and
//! colour) at the voxel's world point. Under CI (`CI=true`) a missing module
//! fails the test; elsewhere the test says why it skips.

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

use crate::support::*;
use coordinator::pipeline::bake::Lattice;
use hypertexture::{Overrides, Scene};

/// Prints each VDB file named on the command line as one JSON object per
/// line: the file's metadata and, per grid, its name, value type, class,
/// voxel size, the world position of voxel (0, 0, 0), the active voxel count
/// and every active voxel as [i, j, k, value…]. Numbers are given by their
/// bits (f32 values as u32, the transform's f64s as u64), which JSON carries
/// exactly.
const DUMP: &str = r#"
import json, struct, sys
import pyopenvdb as vdb

def f32(x):
    return struct.unpack("<I", struct.pack("<f", x))[0]

def f64(x):
    return struct.unpack("<Q", struct.pack("<d", x))[0]

for path in sys.argv[1:]:
    grids, meta = vdb.readAll(path)
    out = {"meta": {k: meta[k] for k in meta}, "grids": {}}
    for g in grids:
        voxels = []
        for it in g.citerOnValues():
            assert it.count == 1, "a tile where voxels were written"
            v = it.value
            v = [f32(c) for c in v] if isinstance(v, tuple) else [f32(v)]
            voxels.append(list(it.min) + v)
        out["grids"][g.name] = {
            "type": g.valueTypeName,
            "class": g.gridClass,
            "voxel_size": [f64(c) for c in g.transform.voxelSize()],
            "origin": [f64(c) for c in g.transform.indexToWorld((0, 0, 0))],
            "active": g.activeVoxelCount(),
            "leaves": g.leafCount(),
            "voxels": voxels,
        }
    print(json.dumps(out))
"#;

/// Debian's Python, which has `pyopenvdb` (a pyenv `python3` first on the
/// PATH does not).
fn python() -> &'static str {
    if Path::new("/usr/bin/python3").exists() {
        "/usr/bin/python3"
    } else {
        "python3"
    }
}

fn python_has_openvdb() -> bool {
    Command::new(python())
        .args(["-c", "import pyopenvdb"])
        .output()
        .is_ok_and(|o| o.status.success())
}

/// False (after saying why) when the test must skip: outside CI without
/// `pyopenvdb`. Under CI a missing module fails.
fn reader_present() -> bool {
    if python_has_openvdb() {
        return true;
    }
    let ci = std::env::var("CI").is_ok_and(|v| v == "true");
    assert!(
        !ci,
        "{} cannot import pyopenvdb: scripts/test installs it (apt-get install python3-openvdb)",
        python()
    );
    eprintln!("skipped: python3 cannot import pyopenvdb (scripts/test installs it)");
    false
}

fn bake(args: &[&str]) -> Output {
    output_within(
        Command::new(env!("CARGO_BIN_EXE_coordinator"))
            .arg("bake")
            .args(args)
            .env_remove("RUST_LOG"),
        120,
    )
}

/// Bakes the gallery scene `name` to `out` with `args`, which must succeed.
fn bake_ok(name: &str, out: &Path, args: &[&str]) {
    let scene = scene(name);
    let mut all = vec![
        scene.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
        "--quiet",
    ];
    all.extend_from_slice(args);
    let baked = bake(&all);
    assert!(
        baked.status.success(),
        "{}",
        String::from_utf8_lossy(&baked.stderr)
    );
}

fn dump(files: &[PathBuf]) -> Vec<serde_json::Value> {
    let dir = files[0].parent().expect("a directory");
    let script = dir.join("dump.py");
    std::fs::write(&script, DUMP).expect("the script is written");
    let out = output_within(Command::new(python()).arg(&script).args(files), 120);
    assert!(
        out.status.success(),
        "pyopenvdb could not read the files: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    String::from_utf8_lossy(&out.stdout)
        .lines()
        .map(|l| serde_json::from_str(l).expect("one JSON object a file"))
        .collect()
}

/// An f64 given by its bits.
fn f(v: &serde_json::Value) -> f64 {
    f64::from_bits(v.as_u64().expect("the bits of an f64"))
}

/// An f32 given by its bits.
fn f32_bits(v: &serde_json::Value) -> f32 {
    f32::from_bits(v.as_u64().expect("the bits of an f32") as u32)
}

/// An integer voxel coordinate.
fn coord(v: &serde_json::Value) -> f64 {
    v.as_i64().expect("a voxel coordinate") as f64
}

/// Checks one frame's file against the library: the transform, the grids'
/// names and classes, that the active voxels are exactly the lattice's voxels
/// of non-zero density, and that each value is the density (and colour) at
/// the voxel's world point, bit for bit.
fn check_frame(file: &serde_json::Value, scene: &Scene, frame: u32, resolution: u32) {
    assert_eq!(file["meta"]["frame"], frame);
    assert!(
        file["meta"]["creator"]
            .as_str()
            .is_some_and(|c| c.starts_with("hypertexture"))
    );
    let density = &file["grids"]["density"];
    let colour = &file["grids"]["color"];
    assert_eq!(density["type"], "float");
    assert_eq!(density["class"], "fog volume");
    assert_eq!(colour["type"], "vec3s");
    // The transform puts voxel centres on the box where the density can be
    // non-zero, `resolution` voxels along its longest edge.
    let (lo, hi) = scene.density_box(frame);
    let h = f(&density["voxel_size"][0]);
    assert!(
        density["voxel_size"]
            .as_array()
            .expect("three sizes")
            .iter()
            .all(|s| f(s) == h),
        "a uniform scale"
    );
    assert_eq!(h as f32, (hi - lo).max_element() / resolution as f32);
    let t: Vec<f64> = (0..3).map(|a| f(&density["origin"][a])).collect();
    for a in 0..3 {
        assert_eq!(t[a] as f32, lo[a] + 0.5 * h as f32, "translation, axis {a}");
    }
    // Active voxels: exactly the lattice's voxels where the density is not 0.
    let lattice = Lattice::of(scene, frame, resolution);
    let mut non_zero = 0u64;
    for i in 0..lattice.dims[0] {
        for j in 0..lattice.dims[1] {
            for k in 0..lattice.dims[2] {
                non_zero += u64::from(scene.density_at(lattice.point([i, j, k]), frame) != 0.0);
            }
        }
    }
    assert!(non_zero > 100, "the bake is not empty: {non_zero}");
    assert_eq!(density["active"], non_zero);
    assert_eq!(colour["active"], non_zero);
    // Each value, at the world point OpenVDB's transform gives the voxel.
    let voxels = density["voxels"].as_array().expect("voxels");
    let colours = colour["voxels"].as_array().expect("voxels");
    assert_eq!(voxels.len() as u64, non_zero);
    for (v, c) in voxels.iter().zip(colours) {
        let ijk: Vec<f64> = (0..3).map(|a| coord(&v[a])).collect();
        assert_eq!(
            &c.as_array().expect("a voxel")[..3],
            &v.as_array().expect("a voxel")[..3]
        );
        let p = glam::Vec3::new(
            (t[0] + ijk[0] * h) as f32,
            (t[1] + ijk[1] * h) as f32,
            (t[2] + ijk[2] * h) as f32,
        );
        let d = scene.density_at(p, frame);
        assert_eq!(f32_bits(&v[3]), d, "density at voxel {ijk:?} = {p}");
        let rgb = scene.colour_at(p, d, frame);
        for a in 0..3 {
            assert_eq!(f32_bits(&c[3 + a]), rgb[a], "colour at voxel {ijk:?}");
        }
    }
}

#[test]
fn openvdb_reads_the_fur_back_with_the_librarys_densities() {
    if !reader_present() {
        return;
    }
    let dir = scratch("vdb-fur");
    let out = dir.join("fur.vdb");
    bake_ok("fur", &out, &["--resolution", "24"]);
    let fur = Scene::load(scene("fur"), Overrides::default()).expect("the fur scene loads");
    let files = dump(std::slice::from_ref(&out));
    check_frame(&files[0], &fur, 0, 24);
    // One thread or several: the same file.
    let serial = dir.join("fur-serial.vdb");
    bake_ok("fur", &serial, &["--resolution", "24", "--threads", "1"]);
    assert_eq!(
        std::fs::read(&out).unwrap(),
        std::fs::read(&serial).unwrap()
    );
}

#[test]
fn an_animated_scene_bakes_one_file_per_frame_named_by_the_pattern() {
    if !reader_present() {
        return;
    }
    let dir = scratch("vdb-frames");
    let pattern = dir.join("fire_###.vdb");
    bake_ok(
        "fire_ball",
        &pattern,
        &["--resolution", "16", "--frames", "9..=10"],
    );
    let files = [dir.join("fire_009.vdb"), dir.join("fire_010.vdb")];
    let fire = Scene::load(scene("fire_ball"), Overrides::default()).expect("the scene loads");
    let read = dump(&files);
    check_frame(&read[0], &fire, 9, 16);
    check_frame(&read[1], &fire, 10, 16);
    // The flame drifts: the frames differ.
    assert_ne!(
        read[0]["grids"]["density"]["voxels"],
        read[1]["grids"]["density"]["voxels"]
    );
}

#[test]
fn bad_bakes_say_what_is_wrong() {
    let fur = scene("fur");
    let cases: [(&[&str], &str); 3] = [
        (
            &[
                fur.to_str().unwrap(),
                "--out",
                "x.vdb",
                "--frames",
                "0..3",
                "--quiet",
            ],
            "3 frames need a # in the name",
        ),
        (
            &[
                fur.to_str().unwrap(),
                "--out",
                "x.vdb",
                "--resolution",
                "4096",
            ],
            "--resolution",
        ),
        (
            &["no/such/scene.ron", "--out", "x.vdb"],
            "no/such/scene.ron",
        ),
    ];
    for (args, says) in cases {
        let out = bake(args);
        let stderr = String::from_utf8_lossy(&out.stderr);
        assert!(!out.status.success(), "{args:?} succeeded");
        assert!(stderr.contains(says), "{args:?}: {stderr}");
        assert!(!stderr.contains("panicked"), "{args:?}: {stderr}");
    }
}
