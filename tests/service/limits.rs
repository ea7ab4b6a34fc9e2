//! What bounds `coordinator serve`: output patterns checked at submission
//! (`#` runs, PATH_MAX, NAME_MAX) and expanded only as frames are written,
//! the output roots, the queue limit, the pruning of ended jobs, the paged
//! job list, the metrics (`promtool check metrics`, a real Prometheus
//! scraping it, no series for ended jobs) and the studio's status events,
//! which carry changes only. Loopback only; every wait is bounded.

use std::io::{Read as _, Write as _};
use std::process::Command;
use std::time::{Duration, Instant};

use crate::support::http::{answer, get, poll, post_job};
use crate::support::service::serve_without_workers;
use crate::support::{
    RUN_SECS, collect_within, coordinator, free_port, output_within, rss_kib, scene, scratch,
};

/// A job of a tiny image of the noisy sphere, writing `out`.
fn spec(out: &str) -> serde_json::Value {
    serde_json::json!({
        "scene": std::fs::read_to_string(scene("noisy_sphere")).unwrap(),
        "out": out,
        "width": 16,
        "height": 16,
    })
}

/// Patterns that cannot be written are refused at submission with a 400
/// naming the limit, and the service goes on answering.
#[test]
fn output_patterns_over_the_limits_are_400_naming_them() {
    let dir = scratch("limits-patterns");
    let (_s, url) = serve_without_workers(&dir.join("data"), &dir, &[]);
    let root = dir.display().to_string();
    let cases = [
        (
            format!("{root}/{}.png", "#".repeat(65_536)),
            "longer than 9",
        ),
        (format!("{root}/f.{}.png", "#".repeat(10)), "longer than 9"),
        (
            format!("{root}/{}.png", "n".repeat(300)),
            "NAME_MAX allows 255",
        ),
        (
            format!("{root}/{}/x.png", vec!["d".repeat(250); 17].join("/")),
            "PATH_MAX allows 4095",
        ),
    ];
    for (out, limit) in &cases {
        let a = post_job(&url, &spec(out));
        assert_eq!(a.status, 400, "{}", a.body);
        assert!(a.error().contains(limit), "{limit}: {}", a.error());
    }
    // The longest expansion counts: 251 + 4 bytes fit frames below 10, and
    // frame 10 makes the name one byte too long.
    let mut job = spec(&format!("{root}/{}#.png", "n".repeat(250)));
    job["frames"] = serde_json::json!([0, 10]);
    let a = post_job(&url, &job);
    assert_eq!(a.status, 400, "{}", a.body);
    assert!(a.error().contains("frame 10"), "{}", a.error());
    job["frames"] = serde_json::json!([0, 9]);
    assert_eq!(post_job(&url, &job).status, 201);
    assert_eq!(get(&url, "/api/v1/jobs").status, 200);
}

/// A job of 100,000 frames is accepted and restored in milliseconds, and
/// the service's memory does not grow with its frames: they are expanded as
/// they are written.
#[test]
fn a_job_of_100000_frames_is_accepted_and_restored_without_growing() {
    let dir = scratch("limits-frames");
    let data = dir.join("data");
    let (s, url) = serve_without_workers(&data, &dir, &[]);
    // Long names make each expanded path ~300 bytes.
    let out = format!("{}/{}.#########.png", dir.display(), "f".repeat(200));
    let mut job = spec(&out);
    job["frames"] = serde_json::json!([0, 99_999]);
    assert_eq!(post_job(&url, &job).status, 201);
    let before = rss_kib(s.child.id()).expect("VmRSS");
    let start = Instant::now();
    for _ in 0..4 {
        let a = post_job(&url, &job);
        assert_eq!(a.status, 201, "{}", a.body);
        assert_eq!(a.json()["frames_total"], 100_000);
    }
    let took = start.elapsed();
    let grown = rss_kib(s.child.id()).expect("VmRSS").saturating_sub(before);
    assert!(
        took < Duration::from_millis(400),
        "4 jobs of 100,000 frames took {took:?} to accept"
    );
    assert!(
        grown < 4 * 1024,
        "4 jobs of 100,000 frames grew the service by {grown} KiB"
    );
    s.signal(15);
    let (status, _) = s.finish(30);
    assert!(status.success());
    let (s, url) = serve_without_workers(&data, &dir, &[]);
    let line = s
        .log
        .iter()
        .find(|l| l.contains("jobs resumed in"))
        .cloned()
        .unwrap_or_default();
    let secs: f64 = line
        .split("jobs resumed in ")
        .nth(1)
        .and_then(|r| r.split(' ').next())
        .and_then(|v| v.parse().ok())
        .unwrap_or_else(|| panic!("a restore time in {line:?}"));
    assert!(line.contains("5 jobs resumed"), "{line}");
    assert!(secs < 0.5, "5 jobs of 100,000 frames restored in {secs} s");
    assert_eq!(get(&url, "/api/v1/jobs/5").json()["frames_total"], 100_000);
    let rss = rss_kib(s.child.id()).expect("VmRSS");
    assert!(rss < 200 * 1024, "{rss} KiB after restoring");
}

/// Outputs outside the output roots are 403 naming the roots, the same
/// whether or not their directory exists; `..` and symlinks are resolved; a
/// missing directory inside a root is created; a target that is not a
/// regular file is refused; serve started in `/` asks for --output-root.
#[test]
fn outputs_resolve_inside_the_roots_or_are_403() {
    let dir = scratch("limits-roots");
    let root = dir.join("root");
    let elsewhere = dir.join("elsewhere");
    std::fs::create_dir_all(&root).unwrap();
    std::fs::create_dir_all(&elsewhere).unwrap();
    std::os::unix::fs::symlink(&elsewhere, root.join("link")).unwrap();
    let (_s, url) = serve_without_workers(&dir.join("data"), &root, &["--local-workers", "1"]);
    let r = root.display().to_string();
    let mut messages = Vec::new();
    for out in [
        format!("{}/x.png", elsewhere.display()),
        format!("{r}/../elsewhere/x.png"),
        format!("{r}/link/x.png"),
        format!("{r}/link/new/x.png"),
        "/etc/x.png".to_string(),
        "/no/such/directory/x.png".to_string(),
        "x.png".to_string(),
    ] {
        let a = post_job(&url, &spec(&out));
        assert_eq!(a.status, 403, "{out}: {}", a.body);
        let message = a.error();
        assert!(message.contains(&r), "{out}: {message}");
        messages.push(message.replace(&format!("{out:?}"), "OUT"));
    }
    messages.dedup();
    assert_eq!(messages.len(), 1, "one message for all: {messages:?}");
    let inside = root.join("new/deeper/x.png");
    let a = post_job(&url, &spec(inside.to_str().unwrap()));
    assert_eq!(a.status, 201, "{}", a.body);
    let id = a.json()["id"].as_u64().unwrap();
    poll(&url, &format!("/api/v1/jobs/{id}"), 60, |a| {
        a.json()["state"] == "done"
    });
    assert!(inside.is_file());
    // A target that is a symlink is refused when the frame is written.
    std::os::unix::fs::symlink(elsewhere.join("victim.png"), root.join("trap.png")).unwrap();
    let a = post_job(&url, &spec(root.join("trap.png").to_str().unwrap()));
    assert_eq!(a.status, 201, "{}", a.body);
    let id = a.json()["id"].as_u64().unwrap();
    let failed = poll(&url, &format!("/api/v1/jobs/{id}"), 60, |a| {
        a.json()["state"] == "failed"
    });
    assert!(
        failed.json()["error"]
            .as_str()
            .unwrap()
            .contains("not a regular file"),
        "{}",
        failed.body
    );
    assert!(!elsewhere.join("victim.png").exists());

    let o = output_within(
        Command::new(env!("CARGO_BIN_EXE_coordinator"))
            .args(["serve", "--data"])
            .arg(dir.join("data-slash"))
            .args(["--listen", "127.0.0.1:0", "--local-workers", "0"])
            .current_dir("/"),
        RUN_SECS,
    );
    let stderr = String::from_utf8_lossy(&o.stderr);
    assert!(
        !o.status.success() && stderr.contains("--output-root"),
        "{stderr}"
    );
}

/// Past `--max-queued` jobs not ended, a submission is 429 with Retry-After.
#[test]
fn a_full_queue_answers_429_with_retry_after() {
    let dir = scratch("limits-queue");
    let (_s, url) = serve_without_workers(&dir.join("data"), &dir, &["--max-queued", "2"]);
    let out = dir.join("q.png");
    for _ in 0..2 {
        assert_eq!(post_job(&url, &spec(out.to_str().unwrap())).status, 201);
    }
    let a = post_job(&url, &spec(out.to_str().unwrap()));
    assert_eq!(a.status, 429, "{}", a.body);
    assert!(a.error().contains("--max-queued 2"), "{}", a.error());
    let retry: u64 = a.headers["retry-after"].to_str().unwrap().parse().unwrap();
    assert!(retry > 0);
    // A cancelled job frees its place.
    let cancel = ureq::post(&format!("{url}/api/v1/jobs/1/cancel")).send_empty();
    assert_eq!(answer(cancel).status, 200);
    assert_eq!(post_job(&url, &spec(out.to_str().unwrap())).status, 201);
}

/// Ended jobs beyond `--keep-ended` leave the list and the store; their
/// files stay.
#[test]
fn ended_jobs_are_pruned_from_the_list_and_the_store_and_their_files_kept() {
    let dir = scratch("limits-prune");
    let data = dir.join("data");
    let (s, url) =
        serve_without_workers(&data, &dir, &["--local-workers", "1", "--keep-ended", "1"]);
    let mut files = Vec::new();
    for i in 0..3 {
        let out = dir.join(format!("p{i}.png"));
        let a = post_job(&url, &spec(out.to_str().unwrap()));
        let id = a.json()["id"].as_u64().unwrap();
        poll(&url, &format!("/api/v1/jobs/{id}"), 60, |a| {
            a.json()["state"] == "done"
        });
        files.push(out);
    }
    poll(&url, "/api/v1/jobs", 10, |a| {
        a.json().as_array().is_some_and(|j| j.len() == 1)
    });
    assert_eq!(get(&url, "/api/v1/jobs/1").status, 404);
    assert_eq!(get(&url, "/api/v1/jobs/3").status, 200);
    assert!(files.iter().all(|f| f.is_file()), "files are kept");
    s.signal(15);
    assert!(s.finish(30).0.success());
    let (_s, url) = serve_without_workers(&data, &dir, &["--keep-ended", "1"]);
    let jobs = get(&url, "/api/v1/jobs").json();
    assert_eq!(jobs.as_array().unwrap().len(), 1, "{jobs}");
    assert_eq!(jobs[0]["id"], 3);
}

/// `GET /api/v1/jobs` answers pages (`limit`, a cursor in the `Link`
/// header), the OpenAPI document says so, and `coordinator status` reads
/// every page.
#[test]
fn the_job_list_is_paged_and_status_reads_every_page() {
    let dir = scratch("limits-pages");
    let (_s, url) = serve_without_workers(&dir.join("data"), &dir, &[]);
    let out = dir.join("l.png");
    let body = spec(out.to_str().unwrap());
    let total = 1003;
    for _ in 0..total {
        assert_eq!(post_job(&url, &body).status, 201);
    }
    let first = get(&url, "/api/v1/jobs");
    assert_eq!(
        first.json().as_array().unwrap().len(),
        100,
        "a default page"
    );
    let mut seen = Vec::new();
    let mut path = "/api/v1/jobs?limit=400".to_string();
    for _ in 0..10 {
        let page = get(&url, &path);
        assert_eq!(page.status, 200, "{}", page.body);
        seen.extend(
            page.json()
                .as_array()
                .unwrap()
                .iter()
                .map(|j| j["id"].as_u64().unwrap()),
        );
        let Some(link) = page.headers.get("link") else {
            break;
        };
        let link = link.to_str().unwrap();
        assert!(link.ends_with("rel=\"next\""), "{link}");
        path = link[1..link.find('>').unwrap()].to_string();
    }
    let expected: Vec<u64> = (1..=total).rev().collect();
    assert_eq!(seen, expected, "every job once, newest first");
    assert_eq!(get(&url, "/api/v1/jobs?limit=0").status, 400);
    assert_eq!(get(&url, "/api/v1/jobs?limit=1001").status, 400);
    assert_eq!(get(&url, "/api/v1/jobs?cursor=x").status, 400);
    let doc = get(&url, "/api/v1/openapi.json").json();
    let params = doc["paths"]["/api/v1/jobs"]["get"]["parameters"].to_string();
    assert!(
        params.contains("\"limit\"") && params.contains("\"cursor\""),
        "{params}"
    );
    let o = coordinator(&["status", "--server", &url]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let table = String::from_utf8_lossy(&o.stdout);
    assert!(table.starts_with(&format!("jobs: {total}\n")), "{table}");
    let rows = table.lines().filter(|l| l.contains(" queued ")).count();
    assert_eq!(rows, total as usize, "{table}");
}

/// `/metrics` passes `promtool check metrics`, and holds no series for a
/// job that is not running: the count does not grow with the queue or its
/// history.
#[test]
fn metrics_pass_promtool_and_hold_no_series_for_jobs_not_running() {
    let dir = scratch("limits-metrics");
    let (_s, url) = serve_without_workers(&dir.join("data"), &dir, &[]);
    let out = dir.join("m.png");
    let series = |url: &str| {
        let text = get(url, "/metrics").body;
        let n = text.lines().filter(|l| !l.starts_with('#')).count();
        (text, n)
    };
    let (_, empty) = series(&url);
    for _ in 0..50 {
        assert_eq!(post_job(&url, &spec(out.to_str().unwrap())).status, 201);
    }
    for id in 1..=25 {
        let cancel = ureq::post(&format!("{url}/api/v1/jobs/{id}/cancel")).send_empty();
        assert_eq!(answer(cancel).status, 200);
    }
    let (text, n) = series(&url);
    assert_eq!(n, empty, "series with 50 jobs, 25 ended:\n{text}");
    assert!(!text.contains("job=\""), "{text}");
    assert!(text.contains("hypertexture_farm_units_queued "), "{text}");
    assert!(text.contains("hypertexture_jobs{state=\"cancelled\"} 25"));
    let mut promtool = Command::new("promtool")
        .args(["check", "metrics"])
        .stdin(std::process::Stdio::piped())
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .expect("promtool (scripts/test-deps/prometheus.sh installs it)");
    promtool
        .stdin
        .take()
        .unwrap()
        .write_all(text.as_bytes())
        .unwrap();
    let o = collect_within(promtool, 60);
    assert!(
        o.status.success() && o.stdout.is_empty() && o.stderr.is_empty(),
        "promtool: {}{}",
        String::from_utf8_lossy(&o.stdout),
        String::from_utf8_lossy(&o.stderr)
    );
}

/// A Prometheus 2 server scrapes the service on loopback: `up` is 1.
#[test]
fn a_prometheus_server_scrapes_the_service() {
    let dir = scratch("limits-prometheus");
    let (_s, url) = serve_without_workers(&dir.join("data"), &dir, &[]);
    let target = url.trim_start_matches("http://");
    let config = dir.join("prometheus.yml");
    std::fs::write(
        &config,
        format!(
            "global:\n  scrape_interval: 1s\n  evaluation_interval: 1s\n\
             scrape_configs:\n  - job_name: hypertexture\n    static_configs:\n      - targets: ['{target}']\n"
        ),
    )
    .unwrap();
    let port = free_port();
    let mut prometheus = Command::new("prometheus")
        .arg(format!("--config.file={}", config.display()))
        .arg(format!(
            "--storage.tsdb.path={}",
            dir.join("tsdb").display()
        ))
        .arg(format!("--web.listen-address=127.0.0.1:{port}"))
        .stdout(std::process::Stdio::null())
        .stderr(std::process::Stdio::null())
        .spawn()
        .expect("prometheus (scripts/test-deps/prometheus.sh installs it)");
    let query = format!("http://127.0.0.1:{port}");
    let deadline = Instant::now() + Duration::from_secs(60);
    let up = loop {
        let value = ureq::get(&format!("{query}/api/v1/query?query=up"))
            .call()
            .ok()
            .and_then(|mut r| r.body_mut().read_to_string().ok())
            .and_then(|b| serde_json::from_str::<serde_json::Value>(&b).ok())
            .and_then(|v| {
                v["data"]["result"][0]["value"][1]
                    .as_str()
                    .map(String::from)
            });
        if let Some(v) = value {
            break v;
        }
        if Instant::now() > deadline {
            break "no answer in 60 s".into();
        }
        std::thread::sleep(Duration::from_millis(200));
    };
    let _ = Command::new("kill")
        .arg(prometheus.id().to_string())
        .status();
    let _ = prometheus.wait();
    assert_eq!(up, "1");
}

/// Server-Sent Events of `/studio/events` read for `duration`: the `status`
/// events' data.
fn status_events(url: &str, duration: Duration) -> Vec<serde_json::Value> {
    let addr = url.trim_start_matches("http://");
    let mut conn = std::net::TcpStream::connect(addr).unwrap();
    write!(
        conn,
        "GET /studio/events HTTP/1.1\r\nHost: {addr}\r\nAccept: text/event-stream\r\n\r\n"
    )
    .unwrap();
    let deadline = Instant::now() + duration;
    let mut bytes = Vec::new();
    let mut buf = [0; 65536];
    while let Some(left) = deadline.checked_duration_since(Instant::now()) {
        conn.set_read_timeout(Some(left.max(Duration::from_millis(1))))
            .unwrap();
        match conn.read(&mut buf) {
            Ok(0) | Err(_) => break,
            Ok(n) => bytes.extend_from_slice(&buf[..n]),
        }
    }
    let text = String::from_utf8_lossy(&bytes);
    let mut events = Vec::new();
    for block in text.split("\n\n") {
        let lines: Vec<&str> = block.lines().collect();
        if !lines.iter().any(|l| l.trim_end() == "event: status") {
            continue;
        }
        let data: String = lines
            .iter()
            .filter_map(|l| l.strip_prefix("data:"))
            .map(str::trim)
            .collect();
        if let Ok(v) = serde_json::from_str(&data) {
            events.push(v);
        }
    }
    events
}

/// The studio's status events carry changes: every job once, then only the
/// jobs that changed and the ids of jobs gone.
#[test]
fn studio_status_events_carry_changes_not_the_queue() {
    let dir = scratch("limits-events");
    let (_s, url) = serve_without_workers(&dir.join("data"), &dir, &[]);
    let out = dir.join("e.png");
    for _ in 0..20 {
        assert_eq!(post_job(&url, &spec(out.to_str().unwrap())).status, 201);
    }
    let events = status_events(&url, Duration::from_millis(1800));
    assert!(!events.is_empty(), "no status event");
    assert_eq!(events[0]["full"], true, "{}", events[0]);
    assert_eq!(events[0]["jobs"].as_array().unwrap().len(), 20);
    let later: usize = events[1..]
        .iter()
        .map(|e| e["jobs"].as_array().map_or(0, Vec::len))
        .sum();
    assert_eq!(later, 0, "nothing changed: {events:?}");
}
