//! `coordinator bake` on the farm, with real processes on loopback: the
//! OpenVDB file is byte-identical to the in-process bake for 1, 2 and 4
//! workers, and when a worker is killed mid-bake.

use std::path::{Path, PathBuf};

use crate::support::*;

/// Bakes the gallery scene `name` at `resolution` to `out` with `extra`
/// flags (the coordinator has its own deadline); returns its log.
fn bake(name: &str, resolution: u32, out: &Path, extra: &[&str]) -> Vec<String> {
    let scene = scene(name);
    let resolution = resolution.to_string();
    let args = [
        "bake",
        scene.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
        "--resolution",
        &resolution,
    ];
    let coord = Running::coordinator(&[&args[..], extra].concat());
    let (status, log) = coord.finish(120);
    assert!(status.success(), "the bake failed:\n{}", log.join("\n"));
    log
}

/// The bytes of a file that must exist and not be empty.
fn bytes(path: &Path) -> Vec<u8> {
    let b = std::fs::read(path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    assert!(b.len() > 1000, "{}: {} bytes", path.display(), b.len());
    b
}

/// The units a worker's summary line reports (`worker NAME: N units, …`).
fn units_of(log: &[String], worker: &str) -> u64 {
    let needle = format!("worker {worker}: ");
    let line = log
        .iter()
        .find(|l| l.contains(&needle))
        .unwrap_or_else(|| panic!("no line for worker {worker}:\n{}", log.join("\n")));
    line.split(&needle)
        .nth(1)
        .and_then(|r| r.split(' ').next())
        .and_then(|n| n.parse().ok())
        .unwrap_or_else(|| panic!("no unit count in {line:?}"))
}

#[test]
fn a_farm_bake_is_byte_identical_to_the_in_process_one_on_1_2_and_4_workers() {
    let dir = scratch("bake-farm");
    let reference = dir.join("in-process.vdb");
    bake("eroded_cube", 32, &reference, &["--in-process", "--quiet"]);
    let expected = bytes(&reference);
    for workers in [1, 2, 4] {
        let out: PathBuf = dir.join(format!("farm-{workers}.vdb"));
        let n = workers.to_string();
        let log = bake("eroded_cube", 32, &out, &["--local-workers", &n]);
        assert!(
            log.iter().any(|l| l.contains("with the farm")),
            "baked on the farm:\n{}",
            log.join("\n")
        );
        let joined = log.iter().filter(|l| l.contains(" joined from ")).count();
        assert_eq!(joined, workers, "{}", log.join("\n"));
        assert!(
            bytes(&out) == expected,
            "{workers} workers: the file differs from the in-process bake"
        );
    }
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn a_worker_killed_mid_bake_loses_nothing() {
    let dir = scratch("bake-kill");
    let reference = dir.join("in-process.vdb");
    // Large enough (about 2 million voxels, over a second on one thread)
    // that the first worker is still baking when it is killed.
    bake("eroded_cube", 128, &reference, &["--in-process", "--quiet"]);
    let out = dir.join("farm.vdb");
    let scene = scene("eroded_cube");
    let mut coord = Running::coordinator(&[
        "bake",
        scene.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
        "--resolution",
        "128",
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
    doomed.wait_for("registered", 30);
    coord.wait_for("worker doomed joined", 30);
    std::thread::sleep(std::time::Duration::from_millis(400));
    doomed.signal(9);
    let _ = doomed.finish(10);
    // A worker that joins after the kill gets the rest, the lost units too.
    let late = Running::worker(&["--coordinator", &url, "--threads", "2", "--name", "late"]);
    let (status, log) = coord.finish(120);
    assert!(status.success(), "the bake failed:\n{}", log.join("\n"));
    // Killed mid-bake: it had delivered units, and units were left for the late worker.
    assert!(units_of(&log, "doomed") > 0, "{}", log.join("\n"));
    assert!(units_of(&log, "late") > 0, "{}", log.join("\n"));
    assert!(
        bytes(&out) == bytes(&reference),
        "the file differs from the in-process bake"
    );
    late.signal(15);
    let (status, _) = late.finish(30);
    assert!(status.success(), "the late worker exits cleanly on SIGTERM");
    std::fs::remove_dir_all(&dir).unwrap();
}
