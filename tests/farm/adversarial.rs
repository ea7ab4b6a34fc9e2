//! The coordinator and the worker facing hostile input and a hostile
//! environment: forged log lines, files that never end, closed pipes,
//! absurd flags, a coordinator that vanishes.

use std::path::Path;
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use crate::support::*;

/// A worker name and a failure reason that carry a forged log line and a
/// right-to-left override reach the coordinator's log escaped: no line starts
/// with the forged text, and the escapes are there.
#[test]
fn network_strings_cannot_forge_log_lines() {
    use hypertexture_proto::pb;
    use hypertexture_proto::pb::farm_client::FarmClient;
    use hypertexture_proto::pb::get_work_result::Outcome;

    let dir = scratch("adversarial-log");
    let out = dir.join("farm.png");
    let scene = scene("noisy_sphere");
    let mut coord = Running::coordinator(&[
        "--scene",
        scene.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
        "--width",
        "32",
        "--height",
        "32",
        "--local-workers",
        "0",
    ]);
    let url = format!("http://127.0.0.1:{}", coord.port());
    block_on(async {
        let mut client = FarmClient::connect(url.clone()).await.unwrap();
        let id = register_raw(
            &mut client,
            "evil\n INFO rendered FAKE → pwned.png\u{202e}gnp.exe",
        )
        .await;
        let work = client
            .get_work(pb::GetWorkParams {
                worker_id: id.clone(),
                known_scene_hash: 0,
            })
            .await
            .unwrap()
            .into_inner();
        let Some(Outcome::Assignment(a)) = work.outcome else {
            panic!("expected an assignment")
        };
        client
            .report_failure(pb::ReportFailureParams {
                worker_id: id.clone(),
                assignment_id: a.assignment_id,
                kind: pb::FailureKind::Render as i32,
                reason: "oops\nERROR forged failure\r\nWARN more\u{2066}".into(),
            })
            .await
            .unwrap();
        // An unknown worker id is echoed escaped too.
        let refused = client
            .heartbeat(pb::HeartbeatParams {
                worker_id: "ghost\nINFO forged heartbeat".into(),
            })
            .await
            .unwrap_err();
        assert!(
            refused.message().contains("ghost\\nINFO forged heartbeat"),
            "{}",
            refused.message()
        );
    });
    coord.wait_for("says it cannot render unit", 30);
    let _worker = Running::worker(&["--coordinator", &url, "--threads", "2"]);
    let (status, log) = coord.finish(60);
    let text = log.join("\n");
    assert!(status.success(), "{text}");
    for line in &log {
        let l = line.trim_start();
        for forged in ["INFO rendered FAKE", "ERROR forged", "WARN more"] {
            assert!(!l.starts_with(forged), "a forged line: {line:?}\n{text}");
        }
        assert!(
            !line.contains('\u{202e}') && !line.contains('\u{2066}'),
            "{line:?}"
        );
    }
    for escaped in [
        "evil\\n INFO rendered FAKE → pwned.png\\u{202e}gnp.exe",
        "oops\\nERROR forged failure\\r\\nWARN more\\u{2066}",
    ] {
        assert!(text.contains(escaped), "{escaped}:\n{text}");
    }
    std::fs::remove_dir_all(&dir).unwrap();
}

/// A closed stderr (its reader gone: EPIPE on every log line) or stdout
/// costs nothing: the render completes, exits 0 and writes the same bytes.
#[test]
fn a_closed_stderr_or_stdout_loses_nothing() {
    let dir = scratch("adversarial-epipe");
    let expected = dir.join("reference.png");
    in_process_at("noisy_sphere", 32, &expected);
    for (i, extra) in [&["--in-process"][..], &["--local-workers", "1"][..]]
        .iter()
        .enumerate()
    {
        let out = dir.join(format!("closed-{i}.png"));
        let mut child = Command::new(env!("CARGO_BIN_EXE_coordinator"))
            .args(["--scene", scene("noisy_sphere").to_str().unwrap()])
            .args([
                "--out",
                out.to_str().unwrap(),
                "--width",
                "32",
                "--height",
                "32",
            ])
            .args(*extra)
            .env("RUST_LOG", "debug")
            .stdin(Stdio::null())
            .stdout(Stdio::piped())
            .stderr(Stdio::piped())
            .spawn()
            .unwrap();
        drop(child.stderr.take());
        drop(child.stdout.take());
        let status = wait_within(&mut child, RUN_SECS);
        assert!(status.success(), "{extra:?}: {status}");
        assert_eq!(
            std::fs::read(&out).unwrap(),
            std::fs::read(&expected).unwrap(),
            "{extra:?}"
        );
    }
    // A result printed to a closed stdout, and an error to a closed stderr.
    for (args, ok) in [
        (&["eval", "1 + 1"][..], true),
        (&["--scene", "/no/such.ron", "--out", "x.png"][..], false),
    ] {
        let mut child = Command::new(env!("CARGO_BIN_EXE_coordinator"))
            .args(args)
            .stdin(Stdio::null())
            .stdout(Stdio::piped())
            .stderr(Stdio::piped())
            .spawn()
            .unwrap();
        drop(child.stderr.take());
        drop(child.stdout.take());
        let status = wait_within(&mut child, RUN_SECS);
        assert_eq!(status.success(), ok, "{args:?}: {status}");
        assert_ne!(status.code(), Some(101), "{args:?} panicked");
    }
    std::fs::remove_dir_all(&dir).unwrap();
}

/// Runs the coordinator with `args`, expecting a quick failure whose stderr
/// contains every one of `needles`.
fn fails_at_once(args: &[&str], needles: &[&str]) {
    let started = Instant::now();
    let o = coordinator(args);
    let took = started.elapsed();
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success(), "{args:?}: {err}");
    assert!(took < Duration::from_secs(3), "{args:?} took {took:?}");
    assert!(!err.contains("panicked"), "{args:?}: {err}");
    for needle in needles {
        assert!(err.contains(needle), "{args:?}: no {needle:?} in {err}");
    }
}

/// Endless files, an output nowhere, absurd thread counts: refused before any
/// work, naming the file, the directory or the limit.
#[test]
fn bad_inputs_fail_at_once_with_the_cause() {
    let dir = scratch("adversarial-inputs");
    let noisy = scene("noisy_sphere");
    let noisy = noisy.to_str().unwrap();
    let out = dir.join("x.png");
    let out = out.to_str().unwrap();
    fails_at_once(
        &["--scene", "/dev/zero", "--out", out],
        &["/dev/zero", "larger than 65536 bytes"],
    );
    fails_at_once(
        &[
            "recolor",
            "in.exr",
            "--colormap",
            "/dev/urandom",
            "--out",
            out,
        ],
        &["/dev/urandom", "larger than 65536 bytes"],
    );
    // An EXR larger than the cap (sparse: no disk used) is refused by its size.
    let huge = dir.join("huge.exr");
    std::fs::File::create(&huge)
        .unwrap()
        .set_len((1 << 30) + 1)
        .unwrap();
    fails_at_once(
        &[
            "recolor",
            huge.to_str().unwrap(),
            "--colormap",
            &scene_file("colormaps/fire"),
            "--out",
            out,
        ],
        &["huge.exr", "larger than 1073741824 bytes"],
    );
    fails_at_once(
        &["grid", "--png", "/dev/zero"],
        &["/dev/zero", "larger than 67108864 bytes"],
    );
    fails_at_once(
        &[
            "--scene",
            noisy,
            "--out",
            out,
            "--tls-cert",
            "/dev/zero",
            "--tls-key",
            "/dev/zero",
        ],
        &["/dev/zero", "larger than 1048576 bytes"],
    );
    fails_at_once(
        &[
            "--scene",
            noisy,
            "--out",
            "/nonexistent-dir/x.png",
            "--width",
            "16384",
            "--height",
            "16384",
        ],
        &["/nonexistent-dir: cannot write the output there"],
    );
    fails_at_once(
        &[
            "--scene",
            noisy,
            "--out",
            "/nonexistent-dir/x.png",
            "--frames",
            "0..3",
        ],
        &["/nonexistent-dir: cannot write the output there"],
    );
    fails_at_once(
        &["--scene", noisy, "--out", out, "--threads", "10000"],
        &["10000 threads is too many: at most"],
    );
    fails_at_once(
        &[
            "serve",
            "--data",
            dir.to_str().unwrap(),
            "--threads",
            "10000",
        ],
        &["10000 threads is too many: at most"],
    );
    let o = output_within(
        Command::new(worker_bin()).args([
            "--coordinator",
            "http://127.0.0.1:1",
            "--threads",
            "10000",
        ]),
        RUN_SECS,
    );
    assert!(!o.status.success());
    assert!(String::from_utf8_lossy(&o.stderr).contains("10000 threads is too many: at most"));
    let o = output_within(
        Command::new(worker_bin()).args([
            "--coordinator",
            "https://localhost:1",
            "--ca",
            "/dev/zero",
        ]),
        RUN_SECS,
    );
    assert!(!o.status.success());
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(
        err.contains("/dev/zero") && err.contains("larger than"),
        "{err}"
    );
    assert!(!dir.join("x.png").exists());
    std::fs::remove_dir_all(&dir).unwrap();
}

/// A file of the repository's scenes/ folder, as a string.
fn scene_file(name: &str) -> String {
    scene(name).to_str().unwrap().to_string()
}

/// A scene saved with a UTF-8 byte order mark renders like the one without.
#[test]
fn a_scene_with_a_byte_order_mark_renders() {
    let dir = scratch("adversarial-bom");
    let bom = dir.join("bom.ron");
    let mut text = b"\xef\xbb\xbf".to_vec();
    text.extend(std::fs::read(scene("noisy_sphere")).unwrap());
    std::fs::write(&bom, text).unwrap();
    let (a, b) = (dir.join("bom.png"), dir.join("plain.png"));
    for (s, out) in [(bom.clone(), &a), (scene("noisy_sphere"), &b)] {
        let o = coordinator(&[
            "--scene",
            s.to_str().unwrap(),
            "--out",
            out.to_str().unwrap(),
            "--width",
            "16",
            "--height",
            "16",
            "--in-process",
            "--quiet",
        ]);
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    }
    // The pixels are the same; the files differ only in the scene name they record.
    assert_eq!(
        crate::support::decode_png(&a).into_raw(),
        crate::support::decode_png(&b).into_raw()
    );
    std::fs::remove_dir_all(&dir).unwrap();
}

/// An `--exit-when-done` worker whose coordinator dies leaves once the lease
/// has run out, with exit status 1 (its render did not end as it should).
#[test]
fn an_exit_when_done_worker_leaves_once_its_coordinator_is_gone() {
    worker_bin();
    let dir = scratch("adversarial-orphan");
    let out = dir.join("x.png");
    let mut coord = Running::coordinator(&[
        "--scene",
        &scene_file("fur"),
        "--out",
        out.to_str().unwrap(),
        "--width",
        "256",
        "--height",
        "256",
        "--local-workers",
        "0",
    ]);
    let url = format!("http://127.0.0.1:{}", coord.port());
    let worker = Running::worker(&[
        "--coordinator",
        &url,
        "--threads",
        "1",
        "--name",
        "orphan",
        "--exit-when-done",
        "--lease-timeout",
        "2",
    ]);
    coord.wait_for("worker orphan joined", 30);
    coord.signal(9);
    let _ = coord.finish(10);
    let killed = Instant::now();
    let (status, log) = worker.finish(15);
    assert!(!status.success(), "{}", log.join("\n"));
    assert!(
        killed.elapsed() < Duration::from_secs(10),
        "left after {:?}",
        killed.elapsed()
    );
    assert!(
        log.iter().any(|l| l.contains("unreachable for")),
        "{}",
        log.join("\n")
    );
    std::fs::remove_dir_all(&dir).unwrap();
}

/// A coordinator that takes the connection and is gone before it answers the
/// registration (killed between the two, as the test above can be) still
/// counts as reached: an exit-when-done worker leaves after its lease.
#[test]
fn an_exit_when_done_worker_leaves_a_coordinator_gone_before_it_answered() {
    use std::io::Read;
    use std::sync::atomic::{AtomicBool, Ordering};
    worker_bin();
    let listener = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
    let url = format!("http://{}", listener.local_addr().unwrap());
    listener.set_nonblocking(true).unwrap();
    let done = std::sync::Arc::new(AtomicBool::new(false));
    let accepting = {
        let done = std::sync::Arc::clone(&done);
        // Reads what each connection sends, then closes it without a byte
        // back: bounded by the flag and by 60 s.
        std::thread::spawn(move || {
            let until = Instant::now() + Duration::from_secs(60);
            while !done.load(Ordering::Relaxed) && Instant::now() < until {
                match listener.accept() {
                    Ok((mut conn, _)) => {
                        conn.set_nonblocking(false).unwrap();
                        conn.set_read_timeout(Some(Duration::from_millis(300)))
                            .unwrap();
                        let _ = conn.read(&mut [0; 4096]);
                    }
                    Err(_) => std::thread::sleep(Duration::from_millis(10)),
                }
            }
        })
    };
    let started = Instant::now();
    let worker = Running::worker(&[
        "--coordinator",
        &url,
        "--threads",
        "1",
        "--exit-when-done",
        "--lease-timeout",
        "2",
    ]);
    let (status, log) = worker.finish(20);
    done.store(true, Ordering::Relaxed);
    accepting.join().unwrap();
    assert!(!status.success(), "{}", log.join("\n"));
    assert!(
        log.iter().any(|l| l.contains("unreachable for")),
        "{}",
        log.join("\n")
    );
    assert!(
        started.elapsed() < Duration::from_secs(15),
        "left after {:?}",
        started.elapsed()
    );
}

/// Local worker processes that fail for another reason than a refusal are
/// replaced by in-process workers with that reason in the message, not a
/// guess about an older build.
#[cfg(unix)]
#[test]
fn failing_local_workers_are_reported_with_their_real_cause() {
    use std::os::unix::fs::PermissionsExt;
    let dir = scratch("adversarial-local");
    let exe = dir.join("coordinator");
    std::fs::copy(env!("CARGO_BIN_EXE_coordinator"), &exe).unwrap();
    let fake = dir.join("worker");
    std::fs::write(
        &fake,
        "#!/bin/sh\necho 'error: cannot start 1 render threads: Resource temporarily unavailable (os error 11)' >&2\nexit 3\n",
    )
    .unwrap();
    std::fs::set_permissions(&fake, std::fs::Permissions::from_mode(0o755)).unwrap();
    let expected = dir.join("reference.png");
    in_process_at("noisy_sphere", 32, &expected);
    let out = dir.join("farm.png");
    let o = output_within(
        Command::new(&exe)
            .args(["--scene", &scene_file("noisy_sphere")])
            .args([
                "--out",
                out.to_str().unwrap(),
                "--width",
                "32",
                "--height",
                "32",
            ])
            .args(["--local-workers", "2"])
            .env_remove("RUST_LOG"),
        RUN_SECS,
    );
    let log = String::from_utf8_lossy(&o.stderr);
    assert!(o.status.success(), "{log}");
    assert!(log.contains("every local worker process"), "{log}");
    assert!(
        log.contains("exit status: 3: error: cannot start 1 render threads: Resource temporarily unavailable (os error 11)"),
        "{log}"
    );
    assert!(!log.contains("older build"), "{log}");
    assert_eq!(
        std::fs::read(&out).unwrap(),
        std::fs::read(&expected).unwrap()
    );
    std::fs::remove_dir_all(&dir).unwrap();
}

/// A TLS farm admits no worker that cannot verify it or that it cannot
/// trust: one speaking plaintext, one trusting another CA, one dialling a
/// name the certificate does not carry. None of them joins, and the farm
/// gives up for want of workers.
#[test]
fn tls_refuses_plaintext_a_wrong_ca_and_a_wrong_name() {
    let dir = scratch("adversarial-tls");
    let self_signed = |names: Vec<String>| {
        let key = rcgen::KeyPair::generate().unwrap();
        let cert = rcgen::CertificateParams::new(names)
            .unwrap()
            .self_signed(&key)
            .unwrap();
        (cert.pem(), key.serialize_pem())
    };
    let (cert, key) = self_signed(vec!["localhost".into()]);
    let (other_ca, _) = self_signed(vec!["localhost".into()]);
    let (cert_path, key_path, other_path) = (
        dir.join("cert.pem"),
        dir.join("key.pem"),
        dir.join("other.pem"),
    );
    std::fs::write(&cert_path, cert).unwrap();
    std::fs::write(&key_path, key).unwrap();
    std::fs::write(&other_path, other_ca).unwrap();
    let out = dir.join("x.png");
    let mut coord = Running::coordinator(&[
        "--scene",
        &scene_file("noisy_sphere"),
        "--out",
        out.to_str().unwrap(),
        "--width",
        "16",
        "--height",
        "16",
        "--local-workers",
        "0",
        "--worker-timeout",
        "6",
        "--tls-cert",
        cert_path.to_str().unwrap(),
        "--tls-key",
        key_path.to_str().unwrap(),
    ]);
    let port = coord.port();
    let (cert_path, other_path) = (cert_path.to_str().unwrap(), other_path.to_str().unwrap());
    let plaintext = format!("http://localhost:{port}");
    let localhost = format!("https://localhost:{port}");
    let by_address = format!("https://127.0.0.1:{port}");
    let mut workers = [
        ("plaintext", vec!["--coordinator", &plaintext]),
        (
            "wrong-ca",
            vec!["--coordinator", &localhost, "--ca", other_path],
        ),
        (
            "wrong-name",
            vec!["--coordinator", &by_address, "--ca", cert_path],
        ),
    ]
    .map(|(name, args)| {
        let w = Running::worker(&[&args[..], &["--name", name, "--threads", "1"]].concat());
        (name, w)
    });
    for (name, w) in &mut workers {
        let line = w.wait_for("retrying in", 30);
        assert!(!line.contains("registered"), "{name}: {line}");
    }
    let (status, log) = coord.finish(30);
    let text = log.join("\n");
    assert!(!status.success(), "{text}");
    assert!(!text.contains("joined"), "{text}");
    assert!(text.contains("no worker has been connected"), "{text}");
    for (name, w) in &mut workers {
        while let Ok(line) = w.lines.try_recv() {
            assert!(!line.contains("registered with"), "{name}: {line}");
        }
    }
    std::fs::remove_dir_all(&dir).unwrap();
}

/// How many of the flood's calls, and how large (`HYPERTEXTURE_FLOOD=128x15`
/// gives the 128 calls of 15 MiB of BENCHMARKS.md; the default fits CI).
fn flood_size() -> (usize, usize) {
    std::env::var("HYPERTEXTURE_FLOOD")
        .ok()
        .and_then(|v| {
            let (n, mib) = v.split_once('x')?;
            Some((n.parse().ok()?, mib.parse().ok()?))
        })
        .unwrap_or((128, 2))
}

/// Unauthenticated traffic from another process on loopback: concurrent calls
/// with large bodies are refused from their headers (the coordinator's RSS
/// grows by far less than the bodies), idle sockets beyond the file
/// descriptor limit do not keep a real worker out, the refusals are logged
/// once with a count, and the render is exact.
#[test]
fn unauthenticated_floods_are_refused_before_their_bodies() {
    use hypertexture_proto::pb;
    use hypertexture_proto::pb::farm_client::FarmClient;
    use std::os::unix::process::CommandExt;

    let dir = scratch("adversarial-flood");
    let (out, expected) = (dir.join("farm.png"), dir.join("in-process.png"));
    in_process_at("noisy_sphere", 32, &expected);
    let scene = scene("noisy_sphere");
    let mut cmd = Command::new(env!("CARGO_BIN_EXE_coordinator"));
    cmd.args([
        "--scene",
        scene.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
        "--width",
        "32",
        "--height",
        "32",
        "--local-workers",
        "0",
        "--worker-timeout",
        "120",
        "--token",
        "s3cret",
    ]);
    // The limit: 256 file descriptors for the coordinator.
    unsafe {
        cmd.pre_exec(|| {
            let limit = libc::rlimit {
                rlim_cur: 256,
                rlim_max: 256,
            };
            if libc::setrlimit(libc::RLIMIT_NOFILE, &limit) != 0 {
                return Err(std::io::Error::last_os_error());
            }
            Ok(())
        });
    }
    worker_bin();
    let mut coord = Running::spawn(&mut cmd);
    let port = coord.port();
    let pid = coord.child.id();
    let url = format!("http://127.0.0.1:{port}");
    std::thread::sleep(Duration::from_millis(300));
    let idle = rss_kib(pid).map_or(0, |kb| kb * 1024);

    // Concurrent calls with large bodies and no token, each on its own
    // connection, sampled for the coordinator's RSS meanwhile.
    let (calls, mib) = flood_size();
    let sampling = std::sync::Arc::new(std::sync::atomic::AtomicBool::new(true));
    let sampler = {
        let sampling = sampling.clone();
        std::thread::spawn(move || {
            let mut peak = 0;
            while sampling.load(std::sync::atomic::Ordering::Relaxed) {
                peak = peak.max(rss_kib(pid).map_or(0, |kb| kb * 1024));
                std::thread::sleep(Duration::from_millis(5));
            }
            peak
        })
    };
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()
        .unwrap();
    let pixels = tonic::codegen::Bytes::from(vec![0x5a_u8; mib << 20]);
    let started = Instant::now();
    let outcomes: Vec<Result<(), tonic::Status>> = runtime.block_on(async {
        let calls = (0..calls).map(|i| {
            let (url, pixels) = (url.clone(), pixels.clone());
            tokio::spawn(async move {
                let mut client = FarmClient::connect(url)
                    .await
                    .map_err(|e| tonic::Status::unavailable(e.to_string()))?
                    .max_encoding_message_size(usize::MAX);
                client
                    .submit_tile(pb::SubmitTileParams {
                        worker_id: format!("w{i}"),
                        pixels,
                        ..Default::default()
                    })
                    .await
                    .map(|_| ())
            })
        });
        let all = futures_util::future::join_all(calls);
        tokio::time::timeout(Duration::from_secs(120), all)
            .await
            .expect("the flood's calls end within 120 s")
            .into_iter()
            .map(|r| r.expect("the call's task"))
            .collect()
    });
    let flood_secs = started.elapsed().as_secs_f64();
    sampling.store(false, std::sync::atomic::Ordering::Relaxed);
    let peak = sampler.join().unwrap();
    let refused = outcomes
        .iter()
        .filter(|o| matches!(o, Err(s) if s.code() == tonic::Code::Unauthenticated))
        .count();
    assert!(
        outcomes.iter().all(Result::is_err),
        "an unauthenticated call got through"
    );
    assert!(refused > 0, "no call was refused as unauthenticated");
    let growth = peak.saturating_sub(idle);
    eprintln!(
        "flood: {calls} calls of {mib} MiB in {flood_secs:.2} s, {refused} refused \
         UNAUTHENTICATED, the rest closed; coordinator RSS idle {:.1} MB, peak {:.1} MB \
         (+{:.1} MB)",
        idle as f64 / 1e6,
        peak as f64 / 1e6,
        growth as f64 / 1e6
    );
    assert!(
        growth < 64 << 20,
        "RSS grew by {growth} bytes for {calls} calls of {mib} MiB"
    );

    // 300 idle sockets (more than the coordinator's 256 descriptors), then a
    // real worker: it registers while they are open.
    let idle_sockets: Vec<std::net::TcpStream> = (0..300)
        .filter_map(|_| std::net::TcpStream::connect(("127.0.0.1", port)).ok())
        .collect();
    assert!(idle_sockets.len() >= 250, "{} sockets", idle_sockets.len());
    std::thread::sleep(Duration::from_millis(200));
    let started = Instant::now();
    let mut worker = Running::worker(&[
        "--coordinator",
        &url,
        "--token",
        "s3cret",
        "--threads",
        "1",
        "--exit-when-done",
    ]);
    worker.wait_for("registered with", 30);
    eprintln!(
        "a worker registered {:.3} s after it started, {} idle sockets open",
        started.elapsed().as_secs_f64(),
        idle_sockets.len()
    );
    let (status, log) = coord.finish(120);
    drop(idle_sockets);
    let text = log.join("\n");
    assert!(status.success(), "{text}");
    let refusal_lines = log
        .iter()
        .filter(|l| l.contains("missing or wrong token"))
        .count();
    assert!(
        (1..=2).contains(&refusal_lines),
        "refusals are logged once a minute a peer, not per call:\n{text}"
    );
    assert_eq!(
        std::fs::read(&out).unwrap(),
        std::fs::read(&expected).unwrap(),
        "the farm's image differs from the in-process one"
    );
    let _ = worker.finish(30);
    std::fs::remove_dir_all(&dir).unwrap();
}

/// One raw HTTP/1.1 request to `port`; returns the status and the body, or
/// why there was none within 10 s.
fn raw_http(port: u16, request: &[u8]) -> Result<(u16, String), String> {
    use std::io::{Read, Write};
    let mut s = std::net::TcpStream::connect(("127.0.0.1", port)).map_err(|e| e.to_string())?;
    s.set_read_timeout(Some(Duration::from_secs(10)))
        .map_err(|e| e.to_string())?;
    s.write_all(request).map_err(|e| e.to_string())?;
    let mut answer = Vec::new();
    s.read_to_end(&mut answer)
        .map_err(|e| format!("no complete answer within 10 s: {e}"))?;
    let text = String::from_utf8_lossy(&answer).into_owned();
    let status = text
        .split(' ')
        .nth(1)
        .and_then(|c| c.parse().ok())
        .ok_or_else(|| format!("no status line: {text:?}"))?;
    let body = text
        .split_once("\r\n\r\n")
        .map_or(String::new(), |(_, b)| b.to_string());
    Ok((status, body))
}

/// Random requests against the running HTTP API of `coordinator serve`
/// (random paths under its routes, methods, headers, JSON bodies, with and
/// without the token): each is answered within 10 s, never with a 5xx, and
/// every 4xx carries a JSON `{"error": …}`.
#[test]
fn random_requests_to_the_api_get_json_4xx_never_5xx() {
    use proptest::prelude::*;
    use proptest::test_runner::{Config, TestCaseError, TestRunner};

    let data = scratch("adversarial-api-proptest");
    let mut serve = Running::coordinator(&[
        "serve",
        "--data",
        data.to_str().unwrap(),
        "--listen",
        "127.0.0.1:0",
        "--local-workers",
        "0",
        "--token",
        "s3cret",
    ]);
    let port = serve.port();
    serve.wait_for("serving on", 30);

    let json = prop_oneof![
        Just(String::new()),
        "[ -~]{0,60}",
        any::<i64>().prop_map(|n| n.to_string()),
        ("[a-z_]{1,10}", "[ -~]{0,20}").prop_map(|(k, v)| serde_json::json!({ k: v }).to_string()),
        ("[ -~]{0,40}", any::<u32>(), any::<i32>()).prop_map(|(scene, w, p)| {
            serde_json::json!({"scene": scene, "width": w, "priority": p, "out": "/x.png"})
                .to_string()
        }),
    ];
    let path = (
        prop_oneof![
            Just("/api/v1/jobs"),
            Just("/api/v1/jobs/"),
            Just("/api/v1/workers"),
            Just("/api/v1/openapi.json"),
            Just("/metrics"),
            Just("/api/v2/"),
            Just("/"),
        ],
        "[a-zA-Z0-9._~/-]{0,24}",
    )
        .prop_map(|(a, b)| format!("{a}{b}"));
    let request = (
        prop_oneof![
            Just("GET"),
            Just("POST"),
            Just("PUT"),
            Just("DELETE"),
            Just("PATCH")
        ],
        path,
        any::<bool>(),
        prop_oneof![
            Just("application/json".to_string()),
            Just("text/plain".to_string()),
            Just("application/x-www-form-urlencoded".to_string()),
            "[a-z]{1,8}/[a-z]{1,8}",
        ],
        proptest::collection::vec(("x-[a-z]{1,10}", "[!-~]{0,30}"), 0..4),
        json,
    );
    let mut runner = TestRunner::new(Config {
        cases: 96,
        failure_persistence: None,
        ..Config::default()
    });
    let started = Instant::now();
    let result = runner.run(
        &request,
        |(method, path, authorized, content_type, headers, body)| {
            let mut r = format!(
                "{method} {path} HTTP/1.1\r\nHost: 127.0.0.1\r\nConnection: close\r\n\
                 Content-Type: {content_type}\r\nContent-Length: {}\r\n",
                body.len()
            );
            if authorized {
                r.push_str("Authorization: Bearer s3cret\r\n");
            }
            for (name, value) in &headers {
                r.push_str(&format!("{name}: {value}\r\n"));
            }
            r.push_str("\r\n");
            r.push_str(&body);
            let (status, answer) = raw_http(port, r.as_bytes()).map_err(TestCaseError::fail)?;
            prop_assert!(status < 500, "{method} {path}: {status} {answer}");
            if status >= 400 {
                let v: serde_json::Value = serde_json::from_str(&answer).map_err(|e| {
                    TestCaseError::fail(format!(
                        "{method} {path}: {status} not JSON ({e}): {answer:?}"
                    ))
                })?;
                prop_assert!(v["error"].is_string(), "{method} {path}: {status} {answer}");
            }
            Ok(())
        },
    );
    eprintln!(
        "96 random requests in {:.2} s",
        started.elapsed().as_secs_f64()
    );
    serve.signal(15);
    let (_, log) = serve.finish(30);
    if let Err(e) = result {
        panic!("{e}\nlog:\n{}", log.join("\n"));
    }
    std::fs::remove_dir_all(&data).unwrap();
}

/// A coordinator rendering `noisy_sphere` at 32² to `out` with no local
/// workers and `extra` flags, a lying worker (`fault`, in this process,
/// named with a forged log line) joined first, then a good worker; returns
/// its exit status and log once it has exited.
fn render_with_a_liar(
    out: &Path,
    fault: worker::Fault,
    extra: &[&str],
) -> (std::process::ExitStatus, String) {
    let lease = ["--lease-timeout", "60"];
    let (mut coord, url) = remote_only("noisy_sphere", 32, out, &[&lease[..], extra].concat());
    let (runtime, stop, task) = in_process_worker(&url, LIAR, Some(fault));
    // The liar is caught before the good worker joins: its lie is in.
    coord.wait_for("lied about job 1", 60);
    let _good = Running::worker(&["--coordinator", &url, "--threads", "1", "--name", "good"]);
    let (status, log) = coord.finish(120);
    stop.send(true).unwrap();
    runtime.block_on(async {
        let _ = tokio::time::timeout(Duration::from_secs(30), task).await;
    });
    (status, log.join("\n"))
}

/// The lying worker's name: it carries a forged log line.
const LIAR: &str = "liar\nERROR forged by the liar";

/// The liar is named in the log, escaped, as blocklisted; no line is forged.
fn liar_named(log: &str) {
    assert!(
        log.contains("worker liar\\nERROR forged by the liar lied about job 1")
            && log.contains("it is blocklisted for the job"),
        "{log}"
    );
    assert!(
        !log.lines()
            .any(|l| l.trim_start().starts_with("ERROR forged")),
        "{log}"
    );
}

/// A worker that sends garbage tiles of the right size (1e38 floats in an
/// EXR's samples, magenta in a PNG's bytes) is caught by the coordinator's
/// second rendering: blocklisted and named, every unit it delivered
/// rendered again by the good worker, the image byte-identical to the
/// in-process one, exit status 0.
#[test]
fn a_worker_sending_garbage_tiles_is_caught_and_the_image_stays_exact() {
    let dir = scratch("adversarial-garbage");
    for ext in ["png", "exr"] {
        let reference = dir.join(format!("reference.{ext}"));
        in_process_at("noisy_sphere", 32, &reference);
        let out = dir.join(format!("farm.{ext}"));
        // Every unit rendered twice: the liar's first tile is checked.
        let (status, log) = render_with_a_liar(&out, worker::Fault::Garbage, &["--verify", "1"]);
        assert!(status.success(), "{log}");
        liar_named(&log);
        assert!(
            log.contains("differs from the coordinator's own rendering"),
            "{log}"
        );
        assert!(
            std::fs::read(&reference).unwrap() == std::fs::read(&out).unwrap(),
            "{ext}: the farm's image differs from the in-process one\n{log}"
        );
    }
    std::fs::remove_dir_all(&dir).unwrap();
}

/// A worker that turns liar in the middle of a sequence (true tiles in
/// frame 0, garbage from frame 1 on) is caught in frame 1; frame 0, already
/// written, holds its tiles, so it is rendered again, whole, by the good
/// worker and written again; every file ends byte-identical to the
/// in-process render, exit status 0.
#[test]
fn frames_written_before_a_liar_is_caught_are_rendered_again() {
    let dir = scratch("adversarial-earlier-frames");
    let reference = dir.join("reference.png");
    let flags = ["--frames", "0..3", "--width", "32", "--height", "32"];
    in_process("noisy_sphere", &reference, &flags);
    let out = dir.join("farm.png");
    // Alone, the liar renders frame 0 truly (the coordinator checks it) and
    // is caught in frame 1; then the good worker joins.
    let (status, log) = render_with_a_liar(
        &out,
        worker::Fault::GarbageFrom(1),
        &["--frames", "0..3", "--verify", "1"],
    );
    assert!(status.success(), "{log}");
    liar_named(&log);
    assert!(
        log.contains("the frames already complete that hold its tiles are rendered again, whole, and written again: [0]"),
        "{log}"
    );
    assert!(
        log.contains("3 frames on"),
        "each frame counted once: {log}"
    );
    for frame in 0..3 {
        let name = |stem: &str| dir.join(format!("{stem}_{frame:04}.png"));
        same_bytes(&name("reference"), &name("farm"));
    }
    std::fs::remove_dir_all(&dir).unwrap();
}

/// A worker that says it cannot build the scene, which the coordinator
/// builds, fails nothing: it is blocklisted and named, the good worker
/// renders the frame, exact, exit status 0 (with verification off: claims
/// are checked whatever the sampled fraction).
#[test]
fn a_false_cannot_build_the_scene_fails_nothing() {
    let dir = scratch("adversarial-false-scene");
    let expected = dir.join("reference.png");
    in_process_at("noisy_sphere", 32, &expected);
    let out = dir.join("farm.png");
    let (status, log) = render_with_a_liar(&out, worker::Fault::Scene, &["--verify", "0"]);
    assert!(status.success(), "{log}");
    liar_named(&log);
    assert!(
        log.contains("it said it cannot build the scene of unit"),
        "{log}"
    );
    same_bytes(&expected, &out);
    std::fs::remove_dir_all(&dir).unwrap();
}

/// A worker that says it cannot render its units, which the coordinator
/// renders, fails nothing: blocklisted and named, the image exact, exit 0.
#[test]
fn a_false_cannot_render_this_unit_fails_nothing() {
    let dir = scratch("adversarial-false-render");
    let expected = dir.join("reference.png");
    in_process_at("noisy_sphere", 32, &expected);
    let out = dir.join("farm.png");
    let (status, log) = render_with_a_liar(&out, worker::Fault::RenderClaim, &[]);
    assert!(status.success(), "{log}");
    liar_named(&log);
    assert!(log.contains("it said it cannot render unit"), "{log}");
    same_bytes(&expected, &out);
    std::fs::remove_dir_all(&dir).unwrap();
}

/// Failure reports under made-up worker ids (altered secrets, bare
/// numbers, ids never handed out) are refused as from unknown workers and
/// count for nothing; three registered workers that all say the same unit
/// cannot be rendered are checked, found lying and blocklisted; the good
/// worker renders the frame, exact, exit status 0.
#[test]
fn made_up_ids_and_three_false_failures_of_one_unit_fail_nothing() {
    use hypertexture_proto::pb;
    use hypertexture_proto::pb::farm_client::FarmClient;
    use hypertexture_proto::pb::get_work_result::Outcome;

    let dir = scratch("adversarial-made-up-ids");
    let expected = dir.join("reference.png");
    in_process_at("noisy_sphere", 32, &expected);
    let out = dir.join("farm.png");
    let scene = scene("noisy_sphere");
    let mut coord = Running::coordinator(&[
        "--scene",
        scene.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
        "--width",
        "32",
        "--height",
        "32",
        "--local-workers",
        "0",
        "--lease-timeout",
        "60",
    ]);
    let url = format!("http://127.0.0.1:{}", coord.port());
    let liars = block_on(async {
        let mut client = FarmClient::connect(url.clone()).await.unwrap();
        let mut ids = Vec::new();
        let mut claimed = Vec::new();
        for name in ["alpha", "beta", "gamma"] {
            ids.push(register_raw(&mut client, name).await);
        }
        // A report must name a kind.
        let refused = client
            .report_failure(pb::ReportFailureParams {
                worker_id: ids[0].clone(),
                assignment_id: 1,
                kind: 0,
                reason: "?".into(),
            })
            .await
            .unwrap_err();
        assert_eq!(refused.code(), tonic::Code::InvalidArgument);
        let mut unit = None;
        for (i, id) in ids.iter().enumerate() {
            let work = client
                .get_work(pb::GetWorkParams {
                    worker_id: id.clone(),
                    known_scene_hash: 0,
                })
                .await
                .unwrap()
                .into_inner();
            let Some(Outcome::Assignment(a)) = work.outcome else {
                panic!("expected an assignment")
            };
            unit.get_or_insert(a.unit);
            let number = id.split_once('-').unwrap().0;
            for forged in [
                format!("{number}-0000000000000000"),
                format!("{number}-{}", "f".repeat(16)),
                number.to_string(),
                format!("w{}-0000000000000001", 100 + i),
                "ghost".into(),
            ] {
                let refused = client
                    .report_failure(pb::ReportFailureParams {
                        worker_id: forged.clone(),
                        assignment_id: a.assignment_id,
                        kind: pb::FailureKind::Scene as i32,
                        reason: "forged".into(),
                    })
                    .await
                    .unwrap_err();
                assert_eq!(refused.code(), tonic::Code::NotFound, "{forged}");
            }
            let counted = client
                .report_failure(pb::ReportFailureParams {
                    worker_id: id.clone(),
                    assignment_id: a.assignment_id,
                    kind: pb::FailureKind::Render as i32,
                    reason: format!("out of memory on node {i}"),
                })
                .await
                .unwrap()
                .into_inner()
                .counted;
            // Not counted when the coordinator has rendered the unit already
            // (it checked an earlier claim): the assignment was taken back.
            if counted {
                claimed.push(["alpha", "beta", "gamma"][i]);
            }
        }
        claimed
    });
    assert_eq!(
        liars.first(),
        Some(&"alpha"),
        "the first claim is taken back"
    );
    for name in liars {
        coord.wait_for(&format!("worker {name} lied about job 1"), 60);
    }
    let _good = Running::worker(&["--coordinator", &url, "--threads", "1", "--name", "good"]);
    let (status, log) = coord.finish(120);
    let log = log.join("\n");
    assert!(status.success(), "{log}");
    assert!(!log.contains("giving up"), "{log}");
    same_bytes(&expected, &out);
    std::fs::remove_dir_all(&dir).unwrap();
}
