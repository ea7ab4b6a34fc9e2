//! The farm with real processes on loopback: exact images from any number of
//! workers, workers killed or joining mid-frame, tokens, time-outs, bad tiles.

use std::path::Path;

use crate::support::*;

#[test]
fn any_number_of_workers_gives_the_in_process_bytes() {
    let dir = scratch("farm-counts");
    for ext in ["png", "exr"] {
        let reference = dir.join(format!("reference.{ext}"));
        in_process_at("tribble", 40, &reference);
        for workers in ["1", "2", "4"] {
            let out = dir.join(format!("farm-{workers}.{ext}"));
            let o = coordinator(&[
                "--scene",
                scene("tribble").to_str().unwrap(),
                "--out",
                out.to_str().unwrap(),
                "--width",
                "40",
                "--height",
                "40",
                "--local-workers",
                workers,
                "--quiet",
            ]);
            assert!(
                o.status.success(),
                "{workers} workers: {}",
                String::from_utf8_lossy(&o.stderr)
            );
            same_bytes(&reference, &out);
        }
    }
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn a_killed_worker_loses_nothing_and_a_late_one_gets_work() {
    let dir = scratch("farm-kill");
    let reference = dir.join("reference.png");
    // Big enough that one render thread is still busy when it is killed
    // (about 0.4 s of rendering on one thread of a fast machine).
    in_process_at("fur", 512, &reference);
    let out = dir.join("farm.png");
    let (mut coord, url) = remote_only(
        "fur",
        512,
        &out,
        &["--lease-timeout", "1", "--worker-timeout", "30"],
    );
    let mut doomed =
        Running::worker(&["--coordinator", &url, "--threads", "1", "--name", "doomed"]);
    doomed.wait_for("registered", 30);
    coord.wait_for("worker doomed joined", 30);
    std::thread::sleep(std::time::Duration::from_millis(150));
    doomed.signal(9);
    let _ = doomed.finish(10);
    // A worker that joins mid-frame receives the rest, including the lost units.
    let mut late = Running::worker(&["--coordinator", &url, "--threads", "2", "--name", "late"]);
    let (status, log) = coord.finish(120);
    assert!(status.success(), "coordinator failed:\n{}", log.join("\n"));
    same_bytes(&reference, &out);
    let late_line = log
        .iter()
        .find(|l| l.contains("worker late:"))
        .expect("the late worker is reported");
    assert!(!late_line.contains(": 0 units"), "{late_line}");
    // SIGTERM: the worker (a daemon waiting for the next frame) says goodbye and exits 0.
    late.wait_for("registered", 10);
    late.signal(15);
    let (status, log) = late.finish(30);
    assert!(
        status.success(),
        "worker after SIGTERM:\n{}",
        log.join("\n")
    );
    std::fs::remove_dir_all(&dir).unwrap();
}

/// SIGTERM mid-frame (Kubernetes scaling down, `scancel`): the worker
/// finishes the unit it renders, delivers it, hands back the one it holds
/// ahead with its goodbye and exits 0. Nothing waits for a lease: with
/// leases of a minute, the frame is done by another worker well before one
/// could run out.
#[test]
fn a_worker_stopped_mid_frame_delivers_or_hands_back_its_units_at_once() {
    let dir = scratch("farm-sigterm");
    let reference = dir.join("reference.png");
    // Large enough that one thread is still rendering 300 ms in.
    in_process_at("fur", 768, &reference);
    let out = dir.join("farm.png");
    let (mut coord, url) = remote_only(
        "fur",
        768,
        &out,
        &["--lease-timeout", "60", "--worker-timeout", "60"],
    );
    let mut leaving =
        Running::worker(&["--coordinator", &url, "--threads", "1", "--name", "leaving"]);
    leaving.wait_for("registered", 30);
    coord.wait_for("worker leaving joined", 30);
    std::thread::sleep(std::time::Duration::from_millis(300));
    assert!(!out.exists(), "the frame was done before SIGTERM");
    let stopped = std::time::Instant::now();
    leaving.signal(15);
    let (status, log) = leaving.finish(30);
    assert!(
        status.success(),
        "worker after SIGTERM:\n{}",
        log.join("\n")
    );
    assert!(
        log.iter().any(|l| l.contains("leaving after")),
        "no goodbye:\n{}",
        log.join("\n")
    );
    let _rest = Running::worker(&["--coordinator", &url, "--threads", "2", "--name", "rest"]);
    let (status, log) = coord.finish(120);
    assert!(status.success(), "coordinator failed:\n{}", log.join("\n"));
    let secs = stopped.elapsed().as_secs_f64();
    eprintln!("sigterm: the frame was done {secs:.1} s after SIGTERM (leases of 60 s)");
    assert!(
        secs < 50.0,
        "the frame took {secs:.1} s after SIGTERM: a lease ran out?\n{}",
        log.join("\n")
    );
    same_bytes(&reference, &out);
    assert!(
        !log.iter()
            .any(|l| l.contains("worker leaving stopped answering")),
        "{}",
        log.join("\n")
    );
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn a_wrong_token_is_refused_and_no_worker_means_a_clean_failure() {
    let mut coord = Running::coordinator(&[
        "--scene",
        scene("fur").to_str().unwrap(),
        "--out",
        "/tmp/never-written.png",
        "--local-workers",
        "0",
        "--token",
        "right-secret",
        // Long enough for both refused workers to start on a loaded machine.
        "--worker-timeout",
        "15",
    ]);
    let url = format!("http://127.0.0.1:{}", coord.port());
    let intruder = Running::worker(&["--coordinator", &url, "--token", "wrong-secret"]);
    let (status, log) = intruder.finish(30);
    assert!(!status.success());
    assert!(
        log.iter()
            .any(|l| l.contains("refused") && l.contains("token")),
        "{}",
        log.join("\n")
    );
    let anonymous = Running::worker(&["--coordinator", &url]);
    let (status, _) = anonymous.finish(30);
    assert!(!status.success(), "a worker with no token is refused too");
    // Every call needs the token, the tile stream included.
    block_on(async {
        use hypertexture_proto::pb;
        let mut client = pb::farm_client::FarmClient::connect(url.clone())
            .await
            .unwrap();
        let status = client
            .submit_tiles(tokio_stream::iter([pb::SubmitTilesParams { tile: None }]))
            .await
            .unwrap_err();
        assert_eq!(status.code(), tonic::Code::Unauthenticated, "{status:?}");
    });
    let (status, log) = coord.finish(60);
    assert!(!status.success(), "the coordinator gives up");
    let log = log.join("\n");
    assert!(log.contains("missing or wrong token"), "{log}");
    assert!(log.contains("error: no worker has been connected"), "{log}");
    assert!(!log.contains("panicked"), "{log}");
}

#[test]
fn listening_beyond_loopback_needs_a_token() {
    let o = coordinator(&[
        "--scene",
        scene("fur").to_str().unwrap(),
        "--out",
        "/tmp/never.png",
        "--listen",
        "0.0.0.0:0",
        "--local-workers",
        "0",
    ]);
    assert!(!o.status.success());
    assert!(String::from_utf8_lossy(&o.stderr).contains("needs a shared token"));
}

/// A hand-written client sends malformed tiles; none is used, and the image that
/// real workers then finish is still exactly the in-process one.
#[test]
fn malformed_tiles_are_rejected_without_touching_the_image() {
    use hypertexture_proto::pb;
    use hypertexture_proto::pb::farm_client::FarmClient;
    use hypertexture_proto::pb::get_work_result::Outcome;
    use tonic::Code;

    let dir = scratch("farm-malformed");
    // An EXR: the tiles carry float samples, which can be NaN or infinite.
    let reference = dir.join("reference.exr");
    in_process_at("noisy_sphere", 32, &reference);
    let out = dir.join("farm.exr");
    let (coord, url) = remote_only("noisy_sphere", 32, &out, &["--lease-timeout", "1"]);
    block_on(async {
        let mut client = FarmClient::connect(url.clone())
            .await
            .unwrap()
            .max_encoding_message_size(64 * 1024 * 1024);
        let refused = client
            .register(pb::RegisterParams {
                protocol_version: 999,
                name: "old".into(),
                threads: 1,
                arithmetic_digest: 0,
                tags: Vec::new(),
            })
            .await
            .unwrap_err();
        assert_eq!(refused.code(), Code::FailedPrecondition);
        assert!(
            refused.message().contains("999")
                && refused
                    .message()
                    .contains(&hypertexture_proto::PROTOCOL_VERSION.to_string())
        );
        // The right protocol but other arithmetic (another build): its pixels
        // would not be byte-identical, so it is refused, naming both digests.
        let digest = hypertexture::render::probe::arithmetic_digest().unwrap();
        let refused = client
            .register(pb::RegisterParams {
                protocol_version: hypertexture_proto::PROTOCOL_VERSION,
                name: "skewed".into(),
                threads: 1,
                arithmetic_digest: digest ^ 1,
                tags: Vec::new(),
            })
            .await
            .unwrap_err();
        assert_eq!(refused.code(), Code::FailedPrecondition);
        assert!(
            refused.message().contains("arithmetic mismatch")
                && refused.message().contains(&format!("{:016x}", digest ^ 1))
                && refused.message().contains(&format!("{digest:016x}")),
            "{}",
            refused.message()
        );
        let id = register_raw(&mut client, "evil").await;
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
        assert_eq!(
            a.job.as_ref().unwrap().pixel_format,
            pb::PixelFormat::Samples as i32
        );
        let unit = a.unit.unwrap();
        let pixels = {
            let u = hypertexture_proto::convert::unit_from_wire(&unit, 32, 32).unwrap();
            u.pixel_count(32)
        };
        let tile = |samples: Vec<u8>, assignment_id: u64| pb::SubmitTileParams {
            worker_id: id.clone(),
            assignment_id,
            unit: Some(unit),
            pixels: samples.into(),
            render_cpu_micros: 0,
            want_next: true,
            known_scene_hash: 0,
            calls_cpu_micros: 0,
        };
        let floats =
            |values: &[f32]| -> Vec<u8> { values.iter().flat_map(|v| v.to_le_bytes()).collect() };
        let n = pixels * hypertexture::Sample::CHANNELS;
        let mut nan = vec![7.0; n];
        nan[1] = f32::NAN;
        let mut inf = vec![7.0; n];
        inf[n - 1] = f32::INFINITY;
        for (what, params, code) in [
            (
                "short",
                tile(floats(&vec![7.0; n - 1]), a.assignment_id),
                Code::InvalidArgument,
            ),
            (
                "ragged",
                tile(vec![0; n * 4 + 3], a.assignment_id),
                Code::InvalidArgument,
            ),
            (
                "NaN",
                tile(floats(&nan), a.assignment_id),
                Code::InvalidArgument,
            ),
            (
                "infinite",
                tile(floats(&inf), a.assignment_id),
                Code::InvalidArgument,
            ),
            (
                "never assigned",
                tile(floats(&vec![7.0; n]), 424_242),
                Code::InvalidArgument,
            ),
            (
                "oversized",
                tile(vec![0; 20_000_000], a.assignment_id),
                Code::OutOfRange,
            ),
        ] {
            let ok = |status: &tonic::Status| {
                status.code() == code
                    || (what == "oversized" && status.code() == Code::ResourceExhausted)
            };
            // On the stream workers use, the refusal ends the stream with the
            // same status.
            let mut replies = client
                .submit_tiles(tokio_stream::iter([pb::SubmitTilesParams {
                    tile: Some(params.clone()),
                }]))
                .await
                .unwrap()
                .into_inner();
            let status = replies.message().await.unwrap_err();
            assert!(ok(&status), "{what}, streamed: {status:?}");
            let status = client.submit_tile(params).await.unwrap_err();
            assert!(ok(&status), "{what}: {status:?}");
        }
        // A stream message without a tile is refused too.
        let mut replies = client
            .submit_tiles(tokio_stream::iter([pb::SubmitTilesParams { tile: None }]))
            .await
            .unwrap()
            .into_inner();
        let status = replies.message().await.unwrap_err();
        assert_eq!(status.code(), Code::InvalidArgument, "{status:?}");
        // The evil client vanishes; its lease runs out and real workers take over.
    });
    let _worker = Running::worker(&["--coordinator", &url, "--threads", "2"]);
    let (status, log) = coord.finish(60);
    assert!(status.success(), "{}", log.join("\n"));
    assert!(
        log.iter().any(|l| l.contains("refused a tile")),
        "{}",
        log.join("\n")
    );
    same_bytes(&reference, &out);
    std::fs::remove_dir_all(&dir).unwrap();
}

/// A raw client's first request for work (it has built no scene yet).
async fn first_work(
    client: &mut hypertexture_proto::pb::farm_client::FarmClient<tonic::transport::Channel>,
    worker_id: &str,
) -> Option<hypertexture_proto::pb::get_work_result::Outcome> {
    client
        .get_work(hypertexture_proto::pb::GetWorkParams {
            worker_id: worker_id.to_string(),
            known_scene_hash: 0,
        })
        .await
        .unwrap()
        .into_inner()
        .outcome
}

/// The tile of `assignment` rendered as a worker renders it (building the
/// scene into `scene` on first use), asking for the next unit with it.
fn worker_tile(
    worker_id: &str,
    assignment: &hypertexture_proto::pb::Assignment,
    scene: &mut Option<hypertexture::Scene>,
) -> hypertexture_proto::pb::SubmitTileParams {
    use hypertexture_proto::convert;
    let job = assignment.job.as_ref().unwrap();
    let scene = scene.get_or_insert_with(|| {
        hypertexture::Scene::from_text(
            &job.scene_text,
            &job.scene_name,
            hypertexture::Overrides {
                width: Some(job.width),
                height: Some(job.height),
                ..Default::default()
            },
        )
        .unwrap()
    });
    let wire_unit = assignment.unit.unwrap();
    let unit = convert::unit_from_wire(&wire_unit, job.width, job.height).unwrap();
    let pixels: Vec<(u32, u32)> = unit.pixels(job.width).collect();
    let samples = hypertexture::render::render_pixels(scene, job.frame, &pixels);
    hypertexture_proto::pb::SubmitTileParams {
        worker_id: worker_id.to_string(),
        assignment_id: assignment.assignment_id,
        unit: Some(wire_unit),
        pixels: convert::tile_to_wire(
            &samples,
            convert::pixel_format_from_wire(job.pixel_format).unwrap(),
        ),
        render_cpu_micros: 1,
        want_next: true,
        known_scene_hash: job.scene_hash,
        calls_cpu_micros: 1,
    }
}

/// Protocol 2 by hand: a tile's reply hands out the next unit, without the scene
/// text the worker already has. The client then dies holding that unit (never
/// started); the lease runs out, a real worker renders it, and the image is
/// exactly the in-process one.
#[test]
fn the_unit_handed_out_with_a_tile_is_not_lost_when_its_worker_dies() {
    use hypertexture_proto::pb;
    use hypertexture_proto::pb::farm_client::FarmClient;
    use hypertexture_proto::pb::get_work_result::Outcome;

    let dir = scratch("farm-ahead");
    let reference = dir.join("reference.png");
    in_process_at("noisy_sphere", 32, &reference);
    let out = dir.join("farm.png");
    let (mut coord, url) = remote_only("noisy_sphere", 32, &out, &["--lease-timeout", "1"]);
    block_on(async {
        let mut client = FarmClient::connect(url.clone()).await.unwrap();
        let id = register_raw(&mut client, "short-lived").await;
        let Some(Outcome::Assignment(first)) = first_work(&mut client, &id).await else {
            panic!("expected an assignment")
        };
        let job = first.job.clone().unwrap();
        assert!(
            !job.scene_text.is_empty(),
            "a new worker gets the scene text"
        );
        // Render the unit as a worker would, and ask for the next one with the tile.
        let reply = client
            .submit_tile(worker_tile(&id, &first, &mut None))
            .await
            .unwrap()
            .into_inner();
        assert!(reply.accepted);
        let Some(pb::GetWorkResult {
            outcome: Some(Outcome::Assignment(ahead)),
        }) = reply.next
        else {
            panic!("expected the next unit in the reply: {:?}", reply.next)
        };
        let ahead_job = ahead.job.unwrap();
        assert_eq!(ahead_job.scene_hash, job.scene_hash);
        assert!(
            ahead_job.scene_text.is_empty(),
            "the worker has this scene: its text is left out"
        );
        assert_ne!(ahead.unit, first.unit);
        // The client dies here, holding `ahead`.
    });
    coord.wait_for("stopped answering", 30);
    let _worker = Running::worker(&["--coordinator", &url, "--threads", "2"]);
    let (status, log) = coord.finish(60);
    assert!(status.success(), "{}", log.join("\n"));
    same_bytes(&reference, &out);
    std::fs::remove_dir_all(&dir).unwrap();
}

/// A worker told to exit when the frame is done learns it from the reply to its
/// last tile, and exits 0 (it does not chase a coordinator that has gone).
#[test]
fn a_worker_exits_when_the_frame_is_done() {
    let dir = scratch("farm-done");
    let out = dir.join("farm.png");
    let (coord, url) = remote_only("noisy_sphere", 32, &out, &[]);
    let worker = Running::worker(&["--coordinator", &url, "--threads", "1", "--exit-when-done"]);
    let (status, log) = worker.finish(30);
    assert!(status.success(), "{}", log.join("\n"));
    let (status, log) = coord.finish(30);
    assert!(status.success(), "{}", log.join("\n"));
    std::fs::remove_dir_all(&dir).unwrap();
}

/// A worker that asks again only after the coordinator has written the image
/// still hears that the render is finished: the coordinator keeps serving
/// until every worker has been told. (With every unit checked, the reply to
/// the last tile comes before the coordinator's own rendering of it settles
/// the frame, so it says "wait"; the next call says "finished".)
#[test]
fn a_worker_that_asks_after_the_image_is_written_is_told_the_render_is_finished() {
    use hypertexture_proto::pb;
    use hypertexture_proto::pb::farm_client::FarmClient;
    use hypertexture_proto::pb::get_work_result::Outcome;

    let dir = scratch("farm-told");
    let reference = dir.join("reference.png");
    in_process_at("noisy_sphere", 16, &reference);
    let out = dir.join("farm.png");
    let (mut coord, url) = remote_only("noisy_sphere", 16, &out, &["--verify", "1"]);
    block_on(async {
        let mut client = FarmClient::connect(url.clone()).await.unwrap();
        let id = register_raw(&mut client, "slow-to-ask").await;
        let mut next = first_work(&mut client, &id).await;
        let mut scene = None;
        let mut units = 0;
        // Render every unit as a worker would, asking for the next with each tile.
        while let Some(Outcome::Assignment(a)) = next {
            let reply = client
                .submit_tile(worker_tile(&id, &a, &mut scene))
                .await
                .unwrap()
                .into_inner();
            assert!(reply.accepted);
            units += 1;
            next = reply.next.and_then(|n| n.outcome);
        }
        assert!(units > 1, "{units} units");
        assert!(
            matches!(next, Some(Outcome::RetryAfterMs(_))),
            "the last tile's reply comes before its check settles the frame: {next:?}"
        );
        // The image is written meanwhile (the supervisor looks every 100 ms).
        coord.wait_for("rendered", 30);
        tokio::time::sleep(std::time::Duration::from_millis(300)).await;
        let work = client
            .get_work(pb::GetWorkParams {
                worker_id: id.clone(),
                known_scene_hash: 0,
            })
            .await
            .expect("the coordinator still answers")
            .into_inner();
        assert_eq!(work.outcome, Some(Outcome::Finished(true)));
    });
    let (status, log) = coord.finish(30);
    assert!(status.success(), "{}", log.join("\n"));
    same_bytes(&reference, &out);
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn workers_wait_for_a_late_coordinator_and_outlive_a_dead_one() {
    let dir = scratch("farm-rejoin");
    let reference = dir.join("reference.png");
    in_process_at("fur", 96, &reference);
    let port = free_port();
    let url = format!("http://127.0.0.1:{port}");
    let listen = format!("127.0.0.1:{port}");
    // The worker starts first: nobody answers, it retries with backoff.
    let mut worker =
        Running::worker(&["--coordinator", &url, "--threads", "2", "--name", "patient"]);
    worker.wait_for("cannot reach", 30);
    let args = |out: &Path| {
        vec![
            "--scene".to_string(),
            scene("fur").to_str().unwrap().to_string(),
            "--out".into(),
            out.to_str().unwrap().to_string(),
            "--width".into(),
            "96".into(),
            "--height".into(),
            "96".into(),
            "--local-workers".into(),
            "0".into(),
            "--listen".into(),
            listen.clone(),
        ]
    };
    // A coordinator comes, then dies mid-render (SIGKILL).
    let first_out = dir.join("first.png");
    let first_args = args(&first_out);
    let mut first =
        Running::coordinator(&first_args.iter().map(String::as_str).collect::<Vec<_>>());
    first.wait_for("worker patient joined", 30);
    first.signal(9);
    let _ = first.finish(10);
    // The worker survives and joins the next coordinator on the same address.
    let out = dir.join("second.png");
    let second_args = args(&out);
    let second = Running::coordinator(&second_args.iter().map(String::as_str).collect::<Vec<_>>());
    let (status, log) = second.finish(120);
    assert!(status.success(), "{}", log.join("\n"));
    assert!(
        log.iter().any(|l| l.contains("worker patient joined")),
        "{}",
        log.join("\n")
    );
    same_bytes(&reference, &out);
    worker.signal(15);
    let (status, log) = worker.finish(30);
    assert!(
        status.success(),
        "the worker never crashed:\n{}",
        log.join("\n")
    );
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn tls_farm_gives_the_same_bytes() {
    let dir = scratch("farm-tls");
    let key = rcgen::KeyPair::generate().unwrap();
    let cert = rcgen::CertificateParams::new(vec!["localhost".to_string()])
        .unwrap()
        .self_signed(&key)
        .unwrap();
    let (cert_path, key_path) = (dir.join("cert.pem"), dir.join("key.pem"));
    std::fs::write(&cert_path, cert.pem()).unwrap();
    std::fs::write(&key_path, key.serialize_pem()).unwrap();
    let reference = dir.join("reference.exr");
    in_process_at("fire_ball", 32, &reference);
    let out = dir.join("tls.exr");
    let o = coordinator(&[
        "--scene",
        scene("fire_ball").to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
        "--width",
        "32",
        "--height",
        "32",
        "--local-workers",
        "2",
        "--tls-cert",
        cert_path.to_str().unwrap(),
        "--tls-key",
        key_path.to_str().unwrap(),
    ]);
    let log = String::from_utf8_lossy(&o.stderr);
    assert!(o.status.success(), "{log}");
    assert!(log.contains("https://"), "{log}");
    same_bytes(&reference, &out);
    // A plaintext worker cannot talk to a TLS farm; a worker without --ca cannot verify it.
    let o = output_within(
        std::process::Command::new(worker_bin()).args(["--coordinator", "https://localhost:1"]),
        RUN_SECS,
    );
    assert!(!o.status.success());
    std::fs::remove_dir_all(&dir).unwrap();
}

/// A Gilet & Dischler scene with jittered supersampling, motion blur and the
/// interactive preset: the jitter is a function of (pixel, sample, seed), and
/// `--spp`/`--quality` travel in the job, so the farm's bytes are the in-process ones.
#[test]
fn supersampled_farm_renders_equal_in_process_ones() {
    let dir = scratch("farm-spp");
    // Noise drifting with `flow` and a shutter open all frame: motion blur too.
    let scene_path = scene("gilet/motion_blur");
    let render = |out: &Path, extra: &[&str]| {
        let mut args = vec![
            "--scene",
            scene_path.to_str().unwrap(),
            "--out",
            out.to_str().unwrap(),
            "--width",
            "32",
            "--height",
            "32",
            "--spp",
            "4",
            "--quality",
            "interactive",
            "--frame",
            "2",
            "--quiet",
        ];
        args.extend_from_slice(extra);
        let o = coordinator(&args);
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    };
    let reference = dir.join("in-process.exr");
    render(&reference, &["--in-process"]);
    let farm = dir.join("farm.exr");
    render(&farm, &["--local-workers", "2"]);
    same_bytes(&reference, &farm);
    // And the samples did something: one sample per pixel is another picture.
    let single = dir.join("single.exr");
    let o = coordinator(&[
        "--scene",
        scene_path.to_str().unwrap(),
        "--out",
        single.to_str().unwrap(),
        "--width",
        "32",
        "--height",
        "32",
        "--spp",
        "1",
        "--quality",
        "interactive",
        "--frame",
        "2",
        "--in-process",
        "--quiet",
    ]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    assert_ne!(
        std::fs::read(&single).unwrap(),
        std::fs::read(&reference).unwrap()
    );
}

/// A worker that says the scene does not build, which the coordinator
/// builds, is blocklisted as a liar at once; alone, it leaves the farm with
/// no worker, and the coordinator gives up after the worker time-out naming
/// it, instead of hanging (the worker heartbeats, so its lease never runs out).
#[test]
fn a_lone_worker_claiming_the_scene_does_not_build_is_blocklisted_and_nothing_hangs() {
    let dir = scratch("farm-scene-fails");
    let out = dir.join("never.png");
    let (coord, url) = remote_only(
        "noisy_sphere",
        32,
        &out,
        &["--worker-timeout", "3", "--lease-timeout", "60"],
    );
    let started = std::time::Instant::now();
    let (runtime, stop, task) = in_process_worker(&url, "broken", Some(worker::Fault::Scene));
    let (status, log) = coord.finish(30);
    let log = log.join("\n");
    assert!(!status.success(), "{log}");
    assert!(
        started.elapsed() < std::time::Duration::from_secs(20),
        "not after a hang: {log}"
    );
    assert!(
        log.contains("worker broken says it cannot build the scene of unit")
            && log.contains("fails to build on purpose"),
        "{log}"
    );
    assert!(
        log.contains("worker broken lied about job 1: it said it cannot build the scene"),
        "{log}"
    );
    assert!(
        log.contains("no worker has been connected for 3 s (1 connected worker cannot build the scene or is blocklisted: broken)"),
        "{log}"
    );
    assert!(!out.exists(), "no image");
    // The worker itself never crashed: it outlives the coordinator and stops when told.
    stop.send(true).unwrap();
    let report = runtime.block_on(async {
        tokio::time::timeout(std::time::Duration::from_secs(30), task)
            .await
            .expect("the worker stops")
            .unwrap()
    });
    assert!(report.is_ok(), "{report:?}");
    std::fs::remove_dir_all(&dir).unwrap();
}

/// A worker of another build (its known-answer probe differs) is refused at
/// registration with both digests and exits; a worker of this build then
/// renders the frame, byte for byte the in-process image.
#[test]
fn a_worker_with_other_arithmetic_is_refused_and_the_image_stays_exact() {
    let dir = scratch("farm-arithmetic");
    let reference = dir.join("reference.png");
    in_process_at("noisy_sphere", 32, &reference);
    let out = dir.join("farm.png");
    let (mut coord, url) = remote_only("noisy_sphere", 32, &out, &["--worker-timeout", "60"]);
    let (runtime, _stop, task) = in_process_worker(&url, "skewed", Some(worker::Fault::Arithmetic));
    let refused = runtime.block_on(async {
        tokio::time::timeout(std::time::Duration::from_secs(30), task)
            .await
            .expect("the refused worker returns")
            .unwrap()
    });
    match refused {
        Err(worker::WorkerError::Refused(message)) => {
            assert!(message.contains("arithmetic mismatch"), "{message}")
        }
        other => panic!("expected a refusal, got {other:?}"),
    }
    coord.wait_for("refused worker skewed", 30);
    let _good = Running::worker(&["--coordinator", &url, "--threads", "1", "--name", "good"]);
    let (status, log) = coord.finish(60);
    assert!(status.success(), "{}", log.join("\n"));
    same_bytes(&reference, &out);
    std::fs::remove_dir_all(&dir).unwrap();
}

/// A worker whose renders panic gives each unit back with the panic's message;
/// the coordinator renders the unit itself, so the worker is blocklisted as
/// a liar; another worker renders the rest, and the image is exactly the
/// in-process one.
#[test]
fn units_a_worker_fails_to_render_go_to_another_and_nothing_is_lost() {
    let dir = scratch("farm-panics");
    // Long enough (32 samples a pixel) for the second worker to join mid-frame.
    let args = |out: &Path, extra: &[&'static str]| {
        let mut args = vec![
            "--scene".to_string(),
            scene("fur").to_str().unwrap().to_string(),
            "--out".into(),
            out.to_str().unwrap().to_string(),
        ];
        for a in ["--width", "128", "--height", "128", "--spp", "32"]
            .iter()
            .chain(extra)
        {
            args.push(a.to_string());
        }
        args
    };
    let reference = dir.join("reference.png");
    let reference_args = args(&reference, &["--in-process", "--quiet"]);
    let o = coordinator(
        &reference_args
            .iter()
            .map(String::as_str)
            .collect::<Vec<_>>(),
    );
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let out = dir.join("farm.png");
    let farm_args = args(&out, &["--local-workers", "0", "--lease-timeout", "60"]);
    let mut coord = Running::coordinator(&farm_args.iter().map(String::as_str).collect::<Vec<_>>());
    let url = format!("http://127.0.0.1:{}", coord.port());
    // The good worker first: a failed unit always has somewhere else to go.
    let _good = Running::worker(&["--coordinator", &url, "--threads", "1", "--name", "good"]);
    coord.wait_for("worker good joined", 30);
    let (runtime, stop, task) = in_process_worker(&url, "flaky", Some(worker::Fault::Panic));
    let (status, log) = coord.finish(120);
    let log = log.join("\n");
    assert!(status.success(), "{log}");
    assert!(
        log.contains("worker flaky says it cannot render unit")
            && log.contains("render: the render panicked: the render panics on purpose")
            && log.contains("worker flaky lied about job 1"),
        "{log}"
    );
    same_bytes(&reference, &out);
    stop.send(true).unwrap();
    runtime.block_on(async {
        let _ = tokio::time::timeout(std::time::Duration::from_secs(30), task).await;
    });
    std::fs::remove_dir_all(&dir).unwrap();
}

/// `--frames` on the farm is one session: one server, the local workers started
/// once and kept for every frame (each assignment says its frame; the scene is
/// built once per worker), and every numbered file byte-identical to the
/// in-process sequence.
#[test]
fn a_sequence_is_one_farm_session_with_the_in_process_bytes() {
    let dir = scratch("farm-sequence");
    let scene_path = scene("pse/spinning_marble");
    let render = |out: &Path, extra: &[&str]| {
        let mut args = vec![
            "--scene",
            scene_path.to_str().unwrap(),
            "--out",
            out.to_str().unwrap(),
            "--width",
            "32",
            "--height",
            "32",
            "--frames",
            "0..3",
        ];
        args.extend_from_slice(extra);
        args.iter().map(|a| a.to_string()).collect::<Vec<_>>()
    };
    let reference = dir.join("reference.png");
    let o = coordinator(
        &render(&reference, &["--in-process", "--quiet"])
            .iter()
            .map(String::as_str)
            .collect::<Vec<_>>(),
    );
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let out = dir.join("farm.png");
    let coord = Running::coordinator(
        &render(&out, &["--local-workers", "2"])
            .iter()
            .map(String::as_str)
            .collect::<Vec<_>>(),
    );
    let (status, log) = coord.finish(120);
    assert!(status.success(), "{}", log.join("\n"));
    for frame in 0..3 {
        let name = |stem: &str| dir.join(format!("{stem}_{frame:04}.png"));
        same_bytes(&name("reference"), &name("farm"));
    }
    assert_ne!(
        std::fs::read(dir.join("reference_0000.png")).unwrap(),
        std::fs::read(dir.join("reference_0001.png")).unwrap(),
        "the scene moves"
    );
    let count = |needle: &str| log.iter().filter(|l| l.contains(needle)).count();
    let log_text = log.join("\n");
    assert_eq!(count("farm listening on"), 1, "{log_text}");
    assert_eq!(count("started 2 local worker processes"), 1, "{log_text}");
    assert_eq!(count("worker local-0 joined"), 1, "{log_text}");
    assert_eq!(count("worker local-1 joined"), 1, "{log_text}");
    assert_eq!(count("rendered "), 3, "{log_text}");
    std::fs::remove_dir_all(&dir).unwrap();
}

/// A `worker` binary left from an older build (here a script that fails as a
/// protocol mismatch does) must not stall the render: the coordinator notices
/// that every local worker process failed and renders with in-process workers.
#[cfg(unix)]
#[test]
fn failing_local_worker_binaries_give_way_to_in_process_workers() {
    use std::os::unix::fs::PermissionsExt;
    let dir = scratch("farm-stale-worker");
    let exe = dir.join("coordinator");
    std::fs::copy(env!("CARGO_BIN_EXE_coordinator"), &exe).unwrap();
    let fake = dir.join("worker");
    std::fs::write(
        &fake,
        "#!/bin/sh\necho 'error: the coordinator refused this worker: protocol version mismatch' >&2\nexit 1\n",
    )
    .unwrap();
    std::fs::set_permissions(&fake, std::fs::Permissions::from_mode(0o755)).unwrap();
    let reference = dir.join("reference.png");
    in_process_at("noisy_sphere", 48, &reference);
    let out = dir.join("farm.png");
    let started = std::time::Instant::now();
    let o = output_within(
        std::process::Command::new(&exe)
            .args(["--scene", scene("noisy_sphere").to_str().unwrap()])
            .args([
                "--out",
                out.to_str().unwrap(),
                "--width",
                "48",
                "--height",
                "48",
            ])
            .args(["--local-workers", "2", "--worker-timeout", "30"])
            .env_remove("RUST_LOG"),
        RUN_SECS,
    );
    let log = String::from_utf8_lossy(&o.stderr);
    assert!(o.status.success(), "{log}");
    assert!(log.contains("every local worker process"), "{log}");
    assert!(
        started.elapsed().as_secs() < 20,
        "no wait for a time-out: {log}"
    );
    same_bytes(&reference, &out);
    std::fs::remove_dir_all(&dir).unwrap();
}

/// `--preview-every` rewrites the partial image while the farm renders, in the
/// output's format (8-bit tiles for a PNG, every sample for an EXR), and the
/// final image replaces it: the same bytes as in-process.
#[test]
fn previews_are_written_while_rendering_and_the_final_image_replaces_them() {
    let dir = scratch("farm-preview");
    let fur = scene("fur");
    for ext in ["png", "exr"] {
        let reference = dir.join(format!("reference.{ext}"));
        // About a second of one debug-build thread: many preview intervals.
        in_process_at("fur", 384, &reference);
        let out = dir.join(format!("farm.{ext}"));
        let o = output_within(
            std::process::Command::new(env!("CARGO_BIN_EXE_coordinator"))
                .args([
                    "--scene",
                    fur.to_str().unwrap(),
                    "--out",
                    out.to_str().unwrap(),
                ])
                .args(["--width", "384", "--height", "384"])
                .args([
                    "--local-workers",
                    "1",
                    "--threads",
                    "1",
                    "--preview-every",
                    "0.05",
                ])
                .env("RUST_LOG", "info,coordinator=debug")
                .env("NO_COLOR", "1"),
            RUN_SECS,
        );
        let log = String::from_utf8_lossy(&o.stderr);
        assert!(o.status.success(), "{log}");
        assert!(
            log.contains("preview of frame 0"),
            "no preview written: {log}"
        );
        same_bytes(&reference, &out);
    }
    std::fs::remove_dir_all(&dir).unwrap();
}
