//! The helpers of the tests that drive `coordinator serve`: start it, submit
//! and follow jobs through the CLI and the API, compare images with the
//! in-process render, find its local workers.

use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use super::{Running, coordinator, in_process, scene};

/// A service on a free loopback port, writing outputs inside the directory
/// that holds `data`; returns it and its URL.
pub fn serve(data: &Path, extra: &[&str]) -> (Running, String) {
    serve_in(data, data.parent().unwrap(), extra)
}

/// A service on a free loopback port, writing outputs inside `root`;
/// returns it and its URL once it serves.
pub fn serve_in(data: &Path, root: &Path, extra: &[&str]) -> (Running, String) {
    let mut args = vec![
        "serve",
        "--data",
        data.to_str().unwrap(),
        "--listen",
        "127.0.0.1:0",
        "--output-root",
        root.to_str().unwrap(),
    ];
    args.extend_from_slice(extra);
    let mut s = Running::coordinator(&args);
    let port = s.port();
    s.wait_for("serving on", 30);
    (s, format!("http://127.0.0.1:{port}"))
}

/// [`serve_in`] with no local workers unless `extra` says otherwise.
pub fn serve_without_workers(data: &Path, root: &Path, extra: &[&str]) -> (Running, String) {
    let mut args = Vec::new();
    if !extra.contains(&"--local-workers") {
        args.extend(["--local-workers", "0"]);
    }
    args.extend_from_slice(extra);
    serve_in(data, root, &args)
}

/// `coordinator <args>` as a client; returns (success, stdout, stderr).
pub fn client(args: &[&str]) -> (bool, String, String) {
    let out = coordinator(args);
    (
        out.status.success(),
        String::from_utf8_lossy(&out.stdout).into_owned(),
        String::from_utf8_lossy(&out.stderr).into_owned(),
    )
}

/// Submits a job with the CLI; returns its id.
pub fn submit(url: &str, scene_name: &str, out: &Path, extra: &[&str]) -> u64 {
    let scene = scene(scene_name);
    let mut args = vec![
        "submit",
        "--server",
        url,
        scene.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
    ];
    args.extend_from_slice(extra);
    let (ok, stdout, stderr) = client(&args);
    assert!(ok, "submit failed: {stderr}");
    stdout
        .trim()
        .parse()
        .unwrap_or_else(|_| panic!("an id: {stdout:?}"))
}

/// GET a JSON document of the API.
pub fn get_json(url: &str, path: &str) -> serde_json::Value {
    let body = ureq::get(&format!("{url}{path}"))
        .call()
        .unwrap_or_else(|e| panic!("GET {path}: {e}"))
        .into_body()
        .read_to_string()
        .unwrap();
    serde_json::from_str(&body).unwrap()
}

pub fn job(url: &str, id: u64) -> serde_json::Value {
    get_json(url, &format!("/api/v1/jobs/{id}"))
}

/// Polls a job (at most `secs`) until `until` holds; returns it.
pub fn poll_job(
    url: &str,
    id: u64,
    secs: u64,
    until: impl Fn(&serde_json::Value) -> bool,
) -> serde_json::Value {
    let deadline = Instant::now() + Duration::from_secs(secs);
    loop {
        let j = job(url, id);
        if until(&j) {
            return j;
        }
        assert!(Instant::now() < deadline, "job {id} after {secs} s: {j}");
        std::thread::sleep(Duration::from_millis(20));
    }
}

/// `coordinator wait`: exit status and stdout.
pub fn wait(url: &str, id: u64) -> (bool, String) {
    let (ok, stdout, _) = client(&["wait", "--server", url, &id.to_string()]);
    (ok, stdout)
}

/// The in-process render of a scene, as the reference bytes.
pub fn reference(scene_name: &str, dir: &Path, name: &str, extra: &[&str]) -> PathBuf {
    let out = dir.join(name);
    in_process(scene_name, &out, extra);
    out
}

/// A metric's value from the exposition.
pub fn metric(url: &str, name: &str) -> f64 {
    let text = ureq::get(&format!("{url}/metrics"))
        .call()
        .unwrap()
        .into_body()
        .read_to_string()
        .unwrap();
    text.lines()
        .find_map(|l| l.strip_prefix(name)?.strip_prefix(' ')?.parse().ok())
        .unwrap_or_else(|| panic!("no {name} in\n{text}"))
}

/// The processes whose parent is `pid`.
pub fn children(pid: u32) -> Vec<u32> {
    let mut out = Vec::new();
    for task in std::fs::read_dir(format!("/proc/{pid}/task"))
        .into_iter()
        .flatten()
        .flatten()
    {
        if let Ok(list) = std::fs::read_to_string(task.path().join("children")) {
            out.extend(
                list.split_whitespace()
                    .filter_map(|p| p.parse::<u32>().ok()),
            );
        }
    }
    out
}

pub fn alive(pid: u32) -> bool {
    // A zombie has exited; only its entry waits for its parent.
    std::fs::read_to_string(format!("/proc/{pid}/stat"))
        .map(|s| !s.split(") ").nth(1).is_some_and(|r| r.starts_with('Z')))
        .unwrap_or(false)
}
