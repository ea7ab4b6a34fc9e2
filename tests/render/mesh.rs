//! Meshes on the farm, with real processes on loopback: the mesh scenes come
//! out byte-identical to in-process from 1, 2 and 4 workers and with a worker
//! killed mid-frame; a worker joining mid-frame fetches the mesh by its hash;
//! a changed mesh is a new scene; bad meshes are clear errors naming the file,
//! and an open one renders with a warning naming it. The scenes read the
//! mesh through its distance field (`sdf: Field`, the default), which every
//! worker builds from the fetched mesh.

use std::path::Path;

use crate::support::*;

fn render(scene: &Path, out: &Path, size: u32, extra: &[&str]) -> std::process::Output {
    let size = size.to_string();
    let args = [
        "--scene",
        scene.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
        "--width",
        &size,
        "--height",
        &size,
        "--quiet",
    ];
    coordinator(&[&args[..], extra].concat())
}

#[test]
fn mesh_scenes_from_any_number_of_workers_give_the_in_process_bytes() {
    let dir = scratch("mesh-counts");
    for name in ["furry_spot", "wool_spot"] {
        let scene = scene(&format!("mesh/{name}"));
        let reference = dir.join(format!("{name}.png"));
        let o = render(&scene, &reference, 24, &["--in-process"]);
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
        // The cow is there: not every pixel is the background.
        let img = decode_png(&reference);
        assert!(
            img.pixels().any(|p| p.0[0] > 60),
            "{name}: no cow in the image"
        );
        for workers in ["1", "2", "4"] {
            let out = dir.join(format!("{name}-{workers}.png"));
            let o = render(&scene, &out, 24, &["--local-workers", workers]);
            assert!(
                o.status.success(),
                "{name}, {workers} workers: {}",
                String::from_utf8_lossy(&o.stderr)
            );
            same_bytes(&reference, &out);
        }
    }
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn a_killed_worker_loses_nothing_and_a_late_one_fetches_the_mesh() {
    let dir = scratch("mesh-kill");
    let scene = scene("mesh/furry_spot");
    let reference = dir.join("reference.png");
    // Big enough that the doomed worker is still rendering when it is killed.
    let o = render(&scene, &reference, 48, &["--in-process"]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let out = dir.join("farm.png");
    let size = "48";
    let mut coord = Running::coordinator(&[
        "--scene",
        scene.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
        "--width",
        size,
        "--height",
        size,
        "--local-workers",
        "0",
        "--lease-timeout",
        "1",
        "--worker-timeout",
        "30",
    ]);
    let url = format!("http://127.0.0.1:{}", coord.port());
    let mut doomed =
        Running::worker(&["--coordinator", &url, "--threads", "1", "--name", "doomed"]);
    // The mesh arrives and is built before the first unit renders.
    doomed.wait_for("meshes/spot.obj (330623 bytes, 5856 triangles) fetched", 60);
    std::thread::sleep(std::time::Duration::from_millis(150));
    doomed.signal(9);
    let _ = doomed.finish(10);
    // A worker that joins mid-frame fetches the mesh too, and gets the rest.
    let mut late = Running::worker(&["--coordinator", &url, "--threads", "2", "--name", "late"]);
    let fetched = late.wait_for("meshes/spot.obj (330623 bytes, 5856 triangles) fetched", 60);
    eprintln!("late worker: {fetched}");
    let (status, log) = coord.finish(180);
    assert!(status.success(), "coordinator failed:\n{}", log.join("\n"));
    same_bytes(&reference, &out);
    let late_line = log
        .iter()
        .find(|l| l.contains("worker late:"))
        .expect("the late worker is reported");
    assert!(!late_line.contains(": 0 units"), "{late_line}");
    late.signal(15);
    let _ = late.finish(30);
    std::fs::remove_dir_all(&dir).unwrap();
}

/// The scene hash a PNG records (its `hypertexture:sceneHash` text).
fn scene_hash(png: &Path) -> String {
    let bytes = std::fs::read(png).unwrap();
    let key = b"hypertexture:sceneHash";
    let at = bytes
        .windows(key.len())
        .position(|w| w == key)
        .expect("the image records its scene hash");
    let rest = &bytes[at + key.len()..];
    let start = rest
        .iter()
        .position(u8::is_ascii_hexdigit)
        .expect("a hexadecimal hash");
    String::from_utf8(rest[start..start + 16].to_vec()).unwrap()
}

#[test]
fn a_changed_mesh_is_a_new_scene_and_bad_meshes_are_named() {
    let dir = scratch("mesh-changed");
    std::fs::create_dir_all(dir.join("meshes")).unwrap();
    let cube = root().join("scenes/mesh/meshes/cube.obj");
    std::fs::copy(&cube, dir.join("meshes/cube.obj")).unwrap();
    let text = std::fs::read_to_string(scene("mesh/furry_spot"))
        .unwrap()
        .replace("meshes/spot.obj", "meshes/cube.obj");
    let scene = dir.join("cube.ron");
    std::fs::write(&scene, &text).unwrap();
    let first = dir.join("first.png");
    let o = render(&scene, &first, 8, &["--in-process"]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    // The same text with another mesh under the same name: another scene.
    let mut obj = std::fs::read_to_string(&cube).unwrap();
    obj.push_str("# changed\n");
    std::fs::write(dir.join("meshes/cube.obj"), &obj).unwrap();
    let second = dir.join("second.png");
    let o = render(&scene, &second, 8, &["--in-process"]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    assert_ne!(scene_hash(&first), scene_hash(&second));

    // An open mesh: rendered, with a warning naming the scene, the file and
    // how many edges are open.
    let open: String = obj
        .lines()
        .filter(|l| *l != "f 2 4 8")
        .map(|l| format!("{l}\n"))
        .collect();
    std::fs::write(dir.join("meshes/cube.obj"), open).unwrap();
    let o = render(&scene, &dir.join("open.png"), 8, &[]);
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(o.status.success(), "{err}");
    assert!(err.contains("cube.ron: mesh "), "{err}");
    assert!(
        err.contains("meshes/cube.obj: the mesh is open: 3 edges belong to one triangle only"),
        "{err}"
    );
    // A missing file and a malformed one.
    std::fs::remove_file(dir.join("meshes/cube.obj")).unwrap();
    let o = render(&scene, &dir.join("missing.png"), 8, &[]);
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(
        err.contains("meshes/cube.obj: cannot read the mesh"),
        "{err}"
    );
    std::fs::write(dir.join("meshes/cube.obj"), "v 0 0 0\nf 1 2 3\n").unwrap();
    let o = render(&scene, &dir.join("malformed.png"), 8, &[]);
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success());
    assert!(err.contains("meshes/cube.obj: "), "{err}");
    std::fs::remove_dir_all(&dir).unwrap();
}
