//! `coordinator serve`: the farm as a service, driven through its CLI clients
//! and HTTP API. Restart and resume after SIGKILL, priorities, cancel, jobs
//! interleaved on shared workers, blocklists and failed jobs, the graceful
//! drain, the API's refusals, and local workers that never outlive their
//! coordinator. Every image is compared with the in-process render, byte for
//! byte. Loopback only; every wait is bounded.

use std::path::Path;
use std::time::{Duration, Instant};

use crate::support::service::{
    alive, children, client, get_json, job, metric, poll_job, reference, serve, submit, wait,
};
use crate::support::{Running, in_process_worker, same_bytes, scene, scratch};

/// SIGKILL mid-frame, restart: every stored unit counts, none is rendered
/// again, and the frames come out byte-identical to the in-process render.
/// Local workers die with their coordinator. Verification is off: a unit
/// sampled for a second rendering is stored only once confirmed, so with it
/// on, a unit counted before the kill may rightly be rendered again.
#[test]
fn a_killed_service_resumes_from_its_stored_units_without_rendering_them_again() {
    let dir = scratch("service-resume");
    let data = dir.join("data");
    let expected = reference(
        "fur",
        &dir,
        "ref.png",
        &["--width", "96", "--height", "96", "--spp", "2"],
    );
    // Frame 1 records its frame number in the file.
    let expected_1 = reference(
        "fur",
        &dir,
        "ref1.png",
        &[
            "--width", "96", "--height", "96", "--spp", "2", "--frame", "1",
        ],
    );
    let (s, url) = serve(&data, &["--local-workers", "1", "--verify", "0"]);
    let pid = s.child.id();
    let out = dir.join("fur.#.png");
    let id = submit(
        &url,
        "fur",
        &out,
        &[
            "--width", "96", "--height", "96", "--spp", "2", "--frames", "0..=1",
        ],
    );
    // Kill it in the middle of the second frame, once the first is written.
    let before = poll_job(&url, id, 120, |j| {
        let (done, total) = (
            j["units_done"].as_u64().unwrap(),
            j["units_total"].as_u64().unwrap(),
        );
        j["frames_done"] == 1 && done > total / 2 + total / 8
    });
    let workers = children(pid);
    assert_eq!(workers.len(), 1, "one local worker process");
    s.signal(9);
    let _ = s.finish(10);
    let units_before = before["units_done"].as_u64().unwrap();
    let total = before["units_total"].as_u64().unwrap();
    assert!(units_before < total, "killed before the end: {before}");
    let deadline = Instant::now() + Duration::from_secs(5);
    while workers.iter().any(|&w| alive(w)) {
        assert!(
            Instant::now() < deadline,
            "a local worker outlived its coordinator"
        );
        std::thread::sleep(Duration::from_millis(50));
    }
    assert!(
        dir.join("fur.0.png").exists(),
        "the first frame was written before the kill"
    );

    // Restart with no worker first: what was stored is all there.
    let (s2, url) = serve(&data, &["--local-workers", "0", "--verify", "0"]);
    let after = job(&url, id);
    let units_after = after["units_done"].as_u64().unwrap();
    assert!(
        units_after >= units_before,
        "{units_after} < {units_before}"
    );
    assert_eq!(after["frames_done"], 1, "{after}");
    let _w = Running::worker(&["--coordinator", &url, "--threads", "1"]);
    let (ok, stdout) = wait(&url, id);
    assert!(ok, "{stdout}");
    // Units accepted by this process: exactly those not stored before.
    let accepted = metric(&url, "hypertexture_unit_latency_seconds_count") as u64;
    assert_eq!(accepted, total - units_after, "units rendered again");
    drop(s2);
    same_bytes(&dir.join("fur.0.png"), &expected);
    same_bytes(&dir.join("fur.1.png"), &expected_1);
    let done = job_after_restart(&data, id);
    assert_eq!(done["state"], "done");
    assert_eq!(done["outputs"].as_array().unwrap().len(), 2);
}

/// Restarts the service on `data` (no workers) and returns a job.
fn job_after_restart(data: &Path, id: u64) -> serde_json::Value {
    let (_s, url) = serve(data, &["--local-workers", "0"]);
    job(&url, id)
}

/// Highest priority first; two jobs share the workers and both come out
/// exact; a cancelled job ends, and `wait` says it did not finish.
#[test]
fn priorities_cancel_and_two_jobs_interleaved_on_shared_workers() {
    let dir = scratch("service-queue");
    let data = dir.join("data");
    let expected_a = reference(
        "noisy_sphere",
        &dir,
        "a_ref.png",
        &["--width", "48", "--height", "48"],
    );
    let expected_b = reference(
        "eroded_cube",
        &dir,
        "b_ref.exr",
        &["--width", "40", "--height", "40"],
    );
    let (mut s, url) = serve(&data, &["--local-workers", "0"]);
    let a = submit(
        &url,
        "noisy_sphere",
        &dir.join("a.png"),
        &["--width", "48", "--height", "48"],
    );
    let b = submit(
        &url,
        "eroded_cube",
        &dir.join("b.exr"),
        &["--width", "40", "--height", "40", "--priority", "5"],
    );
    let big = submit(&url, "fur", &dir.join("big.png"), &["--priority", "-1"]);
    assert_eq!(job(&url, a)["state"], "queued");
    let (ok, table, _) = client(&["status", "--server", &url]);
    assert!(ok && table.contains("queued"), "{table}");
    // Cancel the big one before any worker comes.
    let (ok, stdout, _) = client(&["cancel", "--server", &url, &big.to_string()]);
    assert!(ok, "{stdout}");
    assert_eq!(job(&url, big)["state"], "cancelled");
    let (ok, _) = wait(&url, big);
    assert!(!ok, "wait exits non-zero for a cancelled job");
    let (ok, _, stderr) = client(&["cancel", "--server", &url, &big.to_string()]);
    assert!(!ok && stderr.contains("409"), "{stderr}");

    let _w1 = Running::worker(&["--coordinator", &url, "--threads", "1", "--name", "one"]);
    let _w2 = Running::worker(&["--coordinator", &url, "--threads", "1", "--name", "two"]);
    assert!(wait(&url, a).0);
    assert!(wait(&url, b).0);
    same_bytes(&dir.join("a.png"), &expected_a);
    same_bytes(&dir.join("b.exr"), &expected_b);
    // The higher priority's frame was written first.
    let log = s.wait_for(&format!("job {a}: frame 0"), 10);
    assert!(
        s.log
            .iter()
            .any(|l| l.contains(&format!("job {b}: frame 0"))),
        "job {b} (priority 5) before job {a}: {log}\n{}",
        s.log.join("\n")
    );
    let workers = get_json(&url, "/api/v1/workers");
    assert_eq!(workers.as_array().unwrap().len(), 2, "{workers}");
}

/// A cancelled job's units in flight are dropped by the worker rendering
/// them (the coordinator's Withdrawals stream), not rendered to the end.
#[test]
fn a_cancelled_jobs_units_in_flight_are_dropped_by_their_worker() {
    let dir = scratch("service-withdraw");
    let (_s, url) = serve(&dir.join("data"), &["--local-workers", "0"]);
    // Slow units: 64 samples per pixel, one render thread.
    let id = submit(
        &url,
        "noisy_sphere",
        &dir.join("slow.png"),
        &["--width", "128", "--height", "128", "--spp", "64"],
    );
    let (runtime, stop, task) = in_process_worker(&url, "slow", None);
    poll_job(&url, id, 120, |j| j["units_done"].as_u64() >= Some(1));
    // Between a unit's result and its next lease the worker holds none: the
    // cancel waits for a unit in flight (at most 120 s).
    let in_flight = format!("hypertexture_units_in_flight{{job=\"{id}\"}}");
    let deadline = Instant::now() + Duration::from_secs(120);
    while metric(&url, &in_flight) < 1.0 {
        assert!(Instant::now() < deadline, "no unit of job {id} in flight");
        std::thread::sleep(Duration::from_millis(20));
    }
    let (ok, stdout, _) = client(&["cancel", "--server", &url, &id.to_string()]);
    assert!(ok, "{stdout}");
    let _ = stop.send(true);
    let report = runtime
        .block_on(async { tokio::time::timeout(Duration::from_secs(120), task).await })
        .expect("the worker stops")
        .expect("its task ends")
        .expect("without error");
    assert!(
        report.withdrawn >= 1,
        "the unit rendering when the job was cancelled was dropped: {report:?}"
    );
    assert!(
        report.units < job(&url, id)["units_total"].as_u64().unwrap(),
        "{report:?}"
    );
}

/// A worker whose renders panic, where the coordinator's own rendering of
/// the unit does not, is blocklisted for the job (and `status` shows it)
/// while a good worker finishes the job; three such workers on one job fail
/// nothing: each is blocklisted, and a good worker finishes the job exactly.
#[test]
fn a_failing_worker_is_blocklisted_and_failures_the_coordinator_refutes_fail_no_job() {
    let dir = scratch("service-failures");
    let data = dir.join("data");
    let expected = reference(
        "noisy_sphere",
        &dir,
        "ref.png",
        &["--width", "32", "--height", "32"],
    );
    let (_s, url) = serve(&data, &["--local-workers", "0"]);
    let id = submit(
        &url,
        "noisy_sphere",
        &dir.join("ok.png"),
        &["--width", "32", "--height", "32"],
    );
    let bad = in_process_worker(&url, "flaky", Some(worker::Fault::Panic));
    poll_job(&url, id, 60, |j| {
        !j["blocklisted"].as_array().unwrap().is_empty()
    });
    let (ok, table, _) = client(&["status", "--server", &url]);
    assert!(ok && table.contains("flaky"), "{table}");
    let good = in_process_worker(&url, "good", None);
    assert!(wait(&url, id).0);
    same_bytes(&dir.join("ok.png"), &expected);
    let j = job(&url, id);
    assert_eq!(j["blocklisted"][0], "flaky", "{j}");
    assert!(metric(&url, "hypertexture_workers_blocklisted_total") >= 1.0);
    for (_, stop, _) in [&good, &bad] {
        let _ = stop.send(true);
    }
    drop((good, bad));

    // Failing workers, one after another: the coordinator renders what each
    // says it cannot, so each is blocklisted as a liar and no failure counts
    // towards failing the job, however many workers say it.
    let doubted = submit(
        &url,
        "noisy_sphere",
        &dir.join("doubted.png"),
        &["--width", "32", "--height", "32"],
    );
    let mut flaky = Vec::new();
    for k in 2..=4 {
        flaky.push(in_process_worker(
            &url,
            &format!("flaky{k}"),
            Some(worker::Fault::Panic),
        ));
        poll_job(&url, doubted, 60, |j| {
            j["state"] == "failed" || j["blocklisted"].as_array().unwrap().len() >= k - 1
        });
    }
    let j = job(&url, doubted);
    assert_ne!(j["state"], "failed", "{j}");
    assert_eq!(j["blocklisted"].as_array().unwrap().len(), 3, "{j}");
    for (_, stop, _) in &flaky {
        let _ = stop.send(true);
    }
    let _good = in_process_worker(&url, "good2", None);
    assert!(wait(&url, doubted).0);
    same_bytes(&dir.join("doubted.png"), &expected);
}

/// SIGTERM drains: units in flight arrive, everything is stored, the process
/// exits 0, its local workers are gone, and the next start finishes the job
/// exactly.
#[test]
fn sigterm_drains_and_the_next_start_finishes_the_job() {
    let dir = scratch("service-drain");
    let data = dir.join("data");
    let expected = reference(
        "tribble",
        &dir,
        "ref.png",
        &["--width", "64", "--height", "64"],
    );
    let (mut s, url) = serve(&data, &["--local-workers", "1", "--drain-timeout", "20"]);
    let pid = s.child.id();
    let id = submit(
        &url,
        "tribble",
        &dir.join("t.png"),
        &["--width", "64", "--height", "64"],
    );
    poll_job(&url, id, 60, |j| j["units_done"].as_u64().unwrap() > 0);
    let workers = children(pid);
    s.signal(15);
    s.wait_for("draining", 10);
    let (status, log) = s.finish(30);
    assert!(status.success(), "{}", log.join("\n"));
    assert!(
        log.iter()
            .any(|l| l.contains("drained") || l.contains("drain time-out"))
    );
    std::thread::sleep(Duration::from_millis(300));
    assert!(
        workers.iter().all(|&w| !alive(w)),
        "local workers left behind"
    );
    let (_s2, url) = serve(&data, &["--local-workers", "1"]);
    assert!(wait(&url, id).0);
    same_bytes(&dir.join("t.png"), &expected);
}

/// The API's refusals: 400 with file:line:column, 401 without the token,
/// 404, 413, all JSON; and the OpenAPI document lists the routes.
#[test]
fn the_api_refuses_bad_requests_with_json_errors() {
    let dir = scratch("service-api");
    let data = dir.join("data");
    let (_s, url) = serve(&data, &["--local-workers", "0", "--token", "sesame"]);
    let post = |body: &str, token: Option<&str>| {
        let mut req = ureq::post(&format!("{url}/api/v1/jobs"))
            .header("content-type", "application/json")
            .config()
            .http_status_as_error(false)
            .build();
        if let Some(t) = token {
            req = req.header("authorization", &format!("Bearer {t}"));
        }
        let mut resp = req.send(body).unwrap();
        let status = resp.status().as_u16();
        let body: serde_json::Value =
            serde_json::from_str(&resp.body_mut().read_to_string().unwrap()).unwrap();
        (status, body)
    };
    let out = dir.join("x.png");
    let good = serde_json::json!({"scene": std::fs::read_to_string(scene("noisy_sphere")).unwrap(), "out": out});
    let (status, body) = post(&good.to_string(), None);
    assert_eq!(status, 401, "{body}");
    assert!(body["error"].is_string());
    let (status, body) = post(&good.to_string(), Some("wrong"));
    assert_eq!(status, 401, "{body}");
    let broken = serde_json::json!({"scene": "(\n  objects: [\n    Sphre(radius: 1.0),\n  ],\n)", "scene_name": "broken.ron", "out": out});
    let (status, body) = post(&broken.to_string(), Some("sesame"));
    assert_eq!(status, 400, "{body}");
    let message = body["error"].as_str().unwrap();
    assert!(
        message.contains("broken.ron:"),
        "file:line:column: {message}"
    );
    let huge = serde_json::json!({"scene": "x".repeat(70 * 1024), "out": out});
    let (status, body) = post(&huge.to_string(), Some("sesame"));
    assert_eq!(status, 413, "{body}");
    let (status, body) = post("{not json", Some("sesame"));
    assert_eq!(status, 400, "{body}");
    let mut resp = ureq::get(&format!("{url}/api/v1/jobs/999"))
        .header("authorization", "Bearer sesame")
        .config()
        .http_status_as_error(false)
        .build()
        .call()
        .unwrap();
    assert_eq!(resp.status().as_u16(), 404);
    let body: serde_json::Value =
        serde_json::from_str(&resp.body_mut().read_to_string().unwrap()).unwrap();
    assert!(body["error"].as_str().unwrap().contains("999"));
    let (status, body) = post(&good.to_string(), Some("sesame"));
    assert_eq!(status, 201, "{body}");
    assert_eq!(body["state"], "queued");
    let doc: serde_json::Value = serde_json::from_str(
        &ureq::get(&format!("{url}/api/v1/openapi.json"))
            .header("authorization", "Bearer sesame")
            .call()
            .unwrap()
            .into_body()
            .read_to_string()
            .unwrap(),
    )
    .unwrap();
    for path in [
        "/api/v1/jobs",
        "/api/v1/jobs/{id}",
        "/api/v1/jobs/{id}/cancel",
        "/api/v1/workers",
    ] {
        assert!(
            doc["paths"].get(path).is_some(),
            "{path} in the OpenAPI document"
        );
    }
}

/// A store locked by a running coordinator, or corrupt, is refused with a
/// message naming the directory; nothing is emptied.
#[test]
fn a_locked_or_corrupt_store_is_refused_with_its_directory() {
    let dir = scratch("service-store");
    let data = dir.join("data");
    let (_s, _url) = serve(&data, &["--local-workers", "0"]);
    let (ok, _, stderr) = client(&[
        "serve",
        "--data",
        data.to_str().unwrap(),
        "--listen",
        "127.0.0.1:0",
        "--local-workers",
        "0",
    ]);
    assert!(
        !ok && stderr.contains(data.to_str().unwrap()) && stderr.contains("in use"),
        "{stderr}"
    );
    let bad = dir.join("bad");
    std::fs::create_dir_all(&bad).unwrap();
    std::fs::write(bad.join("farm.sqlite"), vec![0x5a; 8192]).unwrap();
    let (ok, _, stderr) = client(&[
        "serve",
        "--data",
        bad.to_str().unwrap(),
        "--listen",
        "127.0.0.1:0",
        "--local-workers",
        "0",
    ]);
    assert!(!ok && stderr.contains("farm.sqlite"), "{stderr}");
    assert_eq!(
        std::fs::read(bad.join("farm.sqlite")).unwrap(),
        vec![0x5a; 8192]
    );
}

/// A job that requires a tag waits for a worker carrying it.
#[test]
fn tagged_jobs_wait_for_a_worker_with_their_tags() {
    let dir = scratch("service-tags");
    let data = dir.join("data");
    let expected = reference(
        "noisy_sphere",
        &dir,
        "ref.png",
        &["--width", "24", "--height", "24"],
    );
    let (_s, url) = serve(&data, &["--local-workers", "0"]);
    let _plain = Running::worker(&["--coordinator", &url, "--threads", "1", "--name", "plain"]);
    let id = submit(
        &url,
        "noisy_sphere",
        &dir.join("t.png"),
        &["--width", "24", "--height", "24", "--require-tag", "big"],
    );
    std::thread::sleep(Duration::from_millis(1500));
    assert_eq!(
        job(&url, id)["units_done"],
        0,
        "the untagged worker rendered none"
    );
    let _big = Running::worker(&["--coordinator", &url, "--threads", "1", "--tag", "big"]);
    assert!(wait(&url, id).0);
    same_bytes(&dir.join("t.png"), &expected);
    let workers = get_json(&url, "/api/v1/workers");
    assert!(
        workers
            .as_array()
            .unwrap()
            .iter()
            .any(|w| w["tags"][0] == "big"),
        "{workers}"
    );
}

/// TLS covers the workers' gRPC and the API alike, on one port: with a
/// token, a client needs both the CA and the token; the image is exact.
#[test]
fn tls_and_the_token_cover_the_api_and_the_workers() {
    let dir = scratch("service-tls");
    let key = rcgen::KeyPair::generate().unwrap();
    let cert = rcgen::CertificateParams::new(vec!["localhost".to_string()])
        .unwrap()
        .self_signed(&key)
        .unwrap();
    let (cert_path, key_path) = (dir.join("cert.pem"), dir.join("key.pem"));
    std::fs::write(&cert_path, cert.pem()).unwrap();
    std::fs::write(&key_path, key.serialize_pem()).unwrap();
    let expected = reference(
        "fire_ball",
        &dir,
        "ref.exr",
        &["--width", "24", "--height", "24"],
    );
    let data = dir.join("data");
    let mut s = Running::coordinator(&[
        "serve",
        "--data",
        data.to_str().unwrap(),
        "--listen",
        "127.0.0.1:0",
        "--local-workers",
        "1",
        "--token",
        "sesame",
        "--tls-cert",
        cert_path.to_str().unwrap(),
        "--tls-key",
        key_path.to_str().unwrap(),
        "--output-root",
        dir.to_str().unwrap(),
    ]);
    let port = s.port();
    s.wait_for("serving on https://", 30);
    let url = format!("https://localhost:{port}");
    let scene = scene("fire_ball");
    let out = dir.join("tls.exr");
    let submit = |extra: &[&str]| {
        let mut args = vec![
            "submit",
            "--server",
            &url,
            scene.to_str().unwrap(),
            "--out",
            out.to_str().unwrap(),
            "--width",
            "24",
            "--height",
            "24",
        ];
        args.extend_from_slice(extra);
        client(&args)
    };
    let (ok, _, stderr) = submit(&["--token", "sesame"]);
    assert!(!ok, "no CA: the certificate cannot be verified: {stderr}");
    let (ok, _, stderr) = submit(&["--ca", cert_path.to_str().unwrap()]);
    assert!(!ok && stderr.contains("401"), "no token: {stderr}");
    let (ok, stdout, stderr) = submit(&["--ca", cert_path.to_str().unwrap(), "--token", "sesame"]);
    assert!(ok, "{stderr}");
    let id = stdout.trim().to_string();
    let (ok, stdout, stderr) = client(&[
        "wait",
        "--server",
        &url,
        "--ca",
        cert_path.to_str().unwrap(),
        "--token",
        "sesame",
        &id,
    ]);
    assert!(ok, "{stdout}{stderr}");
    same_bytes(&out, &expected);
}

/// `--log-format json` writes one JSON object per event; plain logs to a
/// pipe carry no colour codes.
#[test]
fn logs_are_json_on_request_and_plain_without_colour_codes() {
    let dir = scratch("service-logs");
    let data = dir.join("data");
    let mut s = Running::coordinator(&[
        "serve",
        "--data",
        data.to_str().unwrap(),
        "--listen",
        "127.0.0.1:0",
        "--local-workers",
        "0",
        "--log-format",
        "json",
    ]);
    let line = s.wait_for("serving on", 30);
    let event: serde_json::Value = serde_json::from_str(&line).expect("a JSON object per line");
    assert_eq!(event["level"], "INFO", "{line}");
    assert!(
        event["fields"]["message"]
            .as_str()
            .unwrap()
            .starts_with("serving on"),
        "{line}"
    );
    drop(s);
    let data = dir.join("data2");
    let mut s = Running::coordinator(&[
        "serve",
        "--data",
        data.to_str().unwrap(),
        "--listen",
        "127.0.0.1:0",
        "--local-workers",
        "0",
    ]);
    s.wait_for("serving on", 30);
    assert!(s.log.iter().all(|l| !l.contains('\u{1b}')), "{:?}", s.log);
}
