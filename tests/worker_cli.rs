//! The worker binary as a user meets it.

use std::process::Command;

fn worker(args: &[&str]) -> std::process::Output {
    Command::new(env!("CARGO_BIN_EXE_worker"))
        .args(args)
        .env_remove("HYPERTEXTURE_TOKEN")
        .output()
        .expect("the worker binary runs")
}

#[test]
fn bad_addresses_fail_cleanly() {
    for (args, expected) in [
        (
            vec!["--coordinator", "not a url"],
            "invalid coordinator address",
        ),
        (
            vec!["--coordinator", "ftp://host:1"],
            "expected http://HOST:PORT",
        ),
        (vec!["--coordinator", "https://localhost:1"], "needs --ca"),
        (
            vec![
                "--coordinator",
                "http://localhost:1",
                "--ca",
                "/no/such/ca.pem",
            ],
            "/no/such/ca.pem",
        ),
        (vec!["--threads", "2"], "--coordinator"),
    ] {
        let out = worker(&args);
        assert!(!out.status.success(), "{args:?}");
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(err.contains(expected), "{args:?}: {err}");
        assert!(!err.contains("panicked"), "{args:?}: {err}");
    }
}

/// A Slurm task whose coordinator is not there (the frame it was started
/// for is done): the worker leaves with status 0 once it has been idle for
/// `--idle-exit`, and its log, a pipe as Slurm's `--output` is a file,
/// holds no colour code.
#[test]
fn a_worker_that_never_reaches_its_coordinator_leaves_when_idle_with_plain_logs() {
    let port = std::net::TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port();
    let url = format!("http://127.0.0.1:{port}");
    let started = std::time::Instant::now();
    let out = Command::new(env!("CARGO_BIN_EXE_worker"))
        .args([
            "--coordinator",
            &url,
            "--exit-when-done",
            "--idle-exit",
            "1",
        ])
        .env_remove("HYPERTEXTURE_TOKEN")
        .env_remove("NO_COLOR")
        .env_remove("RUST_LOG")
        .env("SLURM_JOB_ID", "41")
        .env("SLURM_ARRAY_JOB_ID", "40")
        .env("SLURM_ARRAY_TASK_ID", "1")
        .env("SLURM_CPUS_PER_TASK", "1")
        .output()
        .expect("the worker binary runs");
    let secs = started.elapsed().as_secs_f64();
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "{err}");
    assert!(
        err.contains("cannot reach") && err.contains("--idle-exit"),
        "{err}"
    );
    assert!(secs < 20.0, "left after {secs:.1} s:\n{err}");
    assert!(
        !out.stderr.contains(&0x1b),
        "colour codes in a pipe:\n{err}"
    );
}

/// A hostile coordinator: it hands out the jobs of its script in order (one
/// unit each), serves the files they name and counts each fetch, accepts
/// every tile and records every failure a worker reports.
mod hostile {
    use std::collections::HashMap;
    use std::sync::{Arc, Mutex};

    use hypertexture_proto::pb;
    use hypertexture_proto::pb::farm_server::{Farm, FarmServer};
    use tonic::{Request, Response, Status};

    #[derive(Default)]
    pub struct State {
        /// The next job of the script to hand out.
        pub next: usize,
        /// GetAsset calls by hash.
        pub fetches: HashMap<u64, usize>,
        /// Reported failures, by assignment id.
        pub failures: Vec<(u64, String)>,
        /// Tiles received, by assignment id.
        pub tiles: Vec<u64>,
    }

    #[derive(Clone)]
    pub struct Coordinator {
        pub script: Arc<Vec<pb::Job>>,
        pub files: Arc<HashMap<u64, Vec<u8>>>,
        pub state: Arc<Mutex<State>>,
    }

    impl Coordinator {
        pub fn state(&self) -> std::sync::MutexGuard<'_, State> {
            self.state.lock().unwrap()
        }

        /// Assignments ended (a tile or a failure), out of the script's.
        pub fn ended(&self) -> usize {
            let s = self.state();
            s.tiles.len() + s.failures.len()
        }

        /// Serves on a loopback port of its own runtime thread; returns the URL.
        pub fn serve(&self) -> String {
            let listener = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
            let addr = listener.local_addr().unwrap();
            listener.set_nonblocking(true).unwrap();
            let service = FarmServer::new(self.clone());
            std::thread::spawn(move || {
                let runtime = tokio::runtime::Builder::new_current_thread()
                    .enable_all()
                    .build()
                    .unwrap();
                runtime.block_on(async move {
                    let listener = tokio::net::TcpListener::from_std(listener).unwrap();
                    tonic::transport::Server::builder()
                        .add_service(service)
                        .serve_with_incoming(tokio_stream::wrappers::TcpListenerStream::new(
                            listener,
                        ))
                        .await
                        .unwrap();
                });
            });
            format!("http://{addr}")
        }
    }

    type Stream<T> =
        std::pin::Pin<Box<dyn tokio_stream::Stream<Item = Result<T, Status>> + Send + 'static>>;

    #[tonic::async_trait]
    impl Farm for Coordinator {
        async fn register(
            &self,
            _: Request<pb::RegisterParams>,
        ) -> Result<Response<pb::RegisterResult>, Status> {
            Ok(Response::new(pb::RegisterResult {
                worker_id: "w1".into(),
                heartbeat_ms: 1000,
            }))
        }

        async fn get_work(
            &self,
            _: Request<pb::GetWorkParams>,
        ) -> Result<Response<pb::GetWorkResult>, Status> {
            use pb::get_work_result::Outcome;
            let mut s = self.state();
            let outcome = match self.script.get(s.next) {
                Some(job) => {
                    s.next += 1;
                    Outcome::Assignment(pb::Assignment {
                        assignment_id: s.next as u64,
                        job: Some(job.clone()),
                        unit: Some(pb::Unit {
                            interleave: 1,
                            set_index: 0,
                            first_row: 0,
                            row_count: 1,
                            row_stride: 1,
                        }),
                    })
                }
                None => Outcome::RetryAfterMs(100),
            };
            Ok(Response::new(pb::GetWorkResult {
                outcome: Some(outcome),
            }))
        }

        async fn submit_tile(
            &self,
            request: Request<pb::SubmitTileParams>,
        ) -> Result<Response<pb::SubmitTileResult>, Status> {
            self.state().tiles.push(request.get_ref().assignment_id);
            Ok(Response::new(pb::SubmitTileResult {
                accepted: true,
                next: None,
            }))
        }

        type SubmitTilesStream = Stream<pb::SubmitTilesResult>;

        async fn submit_tiles(
            &self,
            request: Request<tonic::Streaming<pb::SubmitTilesParams>>,
        ) -> Result<Response<Self::SubmitTilesStream>, Status> {
            let mut tiles = request.into_inner();
            let (replies, stream) = tokio::sync::mpsc::channel(4);
            let me = self.clone();
            tokio::spawn(async move {
                while let Ok(Some(t)) = tiles.message().await {
                    if let Some(tile) = t.tile {
                        me.state().tiles.push(tile.assignment_id);
                    }
                    let reply = pb::SubmitTilesResult {
                        result: Some(pb::SubmitTileResult {
                            accepted: true,
                            next: None,
                        }),
                    };
                    if replies.send(Ok(reply)).await.is_err() {
                        break;
                    }
                }
            });
            Ok(Response::new(Box::pin(
                tokio_stream::wrappers::ReceiverStream::new(stream),
            )))
        }

        async fn heartbeat(
            &self,
            _: Request<pb::HeartbeatParams>,
        ) -> Result<Response<pb::HeartbeatResult>, Status> {
            Ok(Response::new(pb::HeartbeatResult {}))
        }

        async fn goodbye(
            &self,
            _: Request<pb::GoodbyeParams>,
        ) -> Result<Response<pb::GoodbyeResult>, Status> {
            Ok(Response::new(pb::GoodbyeResult {}))
        }

        async fn report_failure(
            &self,
            request: Request<pb::ReportFailureParams>,
        ) -> Result<Response<pb::ReportFailureResult>, Status> {
            let p = request.into_inner();
            self.state().failures.push((p.assignment_id, p.reason));
            Ok(Response::new(pb::ReportFailureResult { counted: true }))
        }

        type WithdrawalsStream = Stream<pb::Withdrawal>;

        async fn withdrawals(
            &self,
            _: Request<pb::WithdrawalsParams>,
        ) -> Result<Response<Self::WithdrawalsStream>, Status> {
            Err(Status::unimplemented("no withdrawals here"))
        }

        type GetAssetStream = Stream<pb::GetAssetResult>;

        async fn get_asset(
            &self,
            request: Request<pb::GetAssetParams>,
        ) -> Result<Response<Self::GetAssetStream>, Status> {
            let hash = request.get_ref().hash;
            *self.state().fetches.entry(hash).or_default() += 1;
            let bytes = self
                .files
                .get(&hash)
                .ok_or_else(|| Status::not_found("no such file"))?;
            let chunks: Vec<Result<pb::GetAssetResult, Status>> = bytes
                .chunks(1 << 20)
                .map(|c| Ok(pb::GetAssetResult { chunk: c.to_vec() }))
                .collect();
            Ok(Response::new(Box::pin(tokio_stream::iter(chunks))))
        }
    }
}

/// A closed sphere of 8·4⁵ triangles (a subdivided octahedron), scaled by
/// 1 + k/1000 so that each k is another file.
fn sphere_obj(k: u32) -> Vec<u8> {
    type V = [f64; 3];
    let unit = |v: V| {
        let n = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
        [v[0] / n, v[1] / n, v[2] / n]
    };
    let mid = |a: V, b: V| unit([a[0] + b[0], a[1] + b[1], a[2] + b[2]]);
    let (x, y, z) = ([1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]);
    let neg = |v: V| [-v[0], -v[1], -v[2]];
    let mut faces: Vec<[V; 3]> = vec![
        [x, y, z],
        [y, neg(x), z],
        [neg(x), neg(y), z],
        [neg(y), x, z],
        [y, x, neg(z)],
        [neg(x), y, neg(z)],
        [neg(y), neg(x), neg(z)],
        [x, neg(y), neg(z)],
    ];
    for _ in 0..5 {
        faces = faces
            .iter()
            .flat_map(|&[a, b, c]| {
                let (ab, bc, ca) = (mid(a, b), mid(b, c), mid(c, a));
                [[a, ab, ca], [ab, b, bc], [ca, bc, c], [ab, bc, ca]]
            })
            .collect();
    }
    let scale = 0.5 * (1.0 + f64::from(k) / 1000.0);
    let mut obj = String::new();
    for (i, f) in faces.iter().enumerate() {
        for v in f {
            obj.push_str(&format!(
                "v {} {} {}\n",
                v[0] * scale,
                v[1] * scale,
                v[2] * scale
            ));
        }
        obj.push_str(&format!("f {} {} {}\n", 3 * i + 1, 3 * i + 2, 3 * i + 3));
    }
    obj.into_bytes()
}

/// A job for an 8 × 8 render of a scene made of one mesh, `sphere.obj`, as
/// a coordinator sends it; `forged` gives it a scene hash that does not
/// match.
fn mesh_job(name: &str, obj: &[u8], forged: bool) -> hypertexture_proto::pb::Job {
    use hypertexture_proto::{convert, pb};
    let text = "Scene(\n    image: (width: 8, height: 8),\n    camera: (eye: (0.0, 0.0, 3.0), look_at: (0.0, 0.0, 0.0), up: (0.0, 1.0, 0.0), projection: Perspective(fov_y: 40.0)),\n    march: (bounds: (min: (-0.7, -0.7, -0.7), max: (0.7, 0.7, 0.7)), step: Length(0.05), opacity: 40.0, threshold: 0.99),\n    object: Mesh(path: \"sphere.obj\", softness: 0.1),\n)\n";
    let hash = hypertexture::mesh::content_hash(obj);
    let scene_hash = convert::scene_hash_with_assets(
        convert::scene_hash(text, 8, 8, 0, 0, &[]),
        &[("sphere.obj".to_string(), hash)],
    );
    pb::Job {
        scene_hash: if forged { scene_hash ^ 1 } else { scene_hash },
        scene_text: text.into(),
        scene_name: name.into(),
        width: 8,
        height: 8,
        pixel_format: pb::PixelFormat::Srgb8 as i32,
        assets: vec![pb::AssetRef {
            path: "sphere.obj".into(),
            hash,
            size: obj.len() as u64,
        }],
        ..Default::default()
    }
}

/// A worker of the hostile coordinator `c` with `args`, run until every job
/// of the script has ended (at most 120 s); returns its log.
fn work_for(c: &hostile::Coordinator, args: &[&str]) -> (String, u64) {
    use std::io::Read as _;
    let url = c.serve();
    let mut child = Command::new(env!("CARGO_BIN_EXE_worker"))
        .args(["--coordinator", &url, "--threads", "1"])
        .args(args)
        .env_remove("HYPERTEXTURE_TOKEN")
        .env("RUST_LOG", "info")
        .env("NO_COLOR", "1")
        .stderr(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    let mut stderr = child.stderr.take().unwrap();
    let reader = std::thread::spawn(move || {
        let mut log = String::new();
        let _ = stderr.read_to_string(&mut log);
        log
    });
    let deadline = std::time::Instant::now() + std::time::Duration::from_secs(120);
    let mut peak = 0;
    while c.ended() < c.script.len() {
        if let Some(status) = child.try_wait().unwrap() {
            panic!("the worker left with {status}");
        }
        peak = peak.max(rss(child.id()));
        assert!(
            std::time::Instant::now() < deadline,
            "{} of {} jobs ended in 120 s",
            c.ended(),
            c.script.len()
        );
        std::thread::sleep(std::time::Duration::from_millis(20));
    }
    peak = peak.max(rss(child.id()));
    let _ = child.kill();
    let _ = child.wait();
    (reader.join().unwrap(), peak)
}

/// A process's resident set size in bytes, from /proc (0 once it is gone).
fn rss(pid: u32) -> u64 {
    std::fs::read_to_string(format!("/proc/{pid}/status"))
        .unwrap_or_default()
        .lines()
        .find_map(|l| l.strip_prefix("VmRSS:"))
        .and_then(|v| v.trim().trim_end_matches("kB").trim().parse::<u64>().ok())
        .map_or(0, |kb| kb * 1024)
}

fn coordinator_of(
    jobs: Vec<hypertexture_proto::pb::Job>,
    files: Vec<Vec<u8>>,
) -> hostile::Coordinator {
    hostile::Coordinator {
        script: std::sync::Arc::new(jobs),
        files: std::sync::Arc::new(
            files
                .into_iter()
                .map(|f| (hypertexture::mesh::content_hash(&f), f))
                .collect(),
        ),
        state: Default::default(),
    }
}

/// A coordinator that sends a new mesh with every job cannot grow the
/// worker past its cache budget: the oldest meshes go (and are fetched again
/// when named again), the newest stay.
#[test]
fn a_hostile_coordinators_meshes_stay_within_the_cache_budget() {
    const MESHES: u32 = 40;
    let files: Vec<Vec<u8>> = (0..MESHES).map(sphere_obj).collect();
    let mut jobs: Vec<_> = files
        .iter()
        .enumerate()
        .map(|(i, f)| mesh_job(&format!("sphere{i}.ron"), f, false))
        .collect();
    // The newest again (kept), then the first (dropped long ago).
    jobs.push(jobs[MESHES as usize - 1].clone());
    jobs.push(jobs[0].clone());
    let c = coordinator_of(jobs, files.clone());
    let (log, peak) = work_for(&c, &["--asset-cache-mb", "4"]);
    let s = c.state();
    assert!(s.failures.is_empty(), "{:?}\n{log}", s.failures);
    let fetches = |f: &[u8]| s.fetches[&hypertexture::mesh::content_hash(f)];
    assert_eq!(
        fetches(&files[MESHES as usize - 1]),
        1,
        "the newest is kept"
    );
    assert_eq!(
        fetches(&files[0]),
        2,
        "the first was dropped: fetched again"
    );
    // The 40 meshes take 1.3 MB each: kept, they take the worker to ~60 MB.
    assert!(peak < 40 << 20, "peak RSS {} MB", peak >> 20);
}

/// A mesh is kept only for a scene whose hash matches: after a forged job
/// the same mesh is fetched again.
#[test]
fn a_mesh_is_kept_only_once_its_scenes_hash_matches() {
    let obj = sphere_obj(0);
    let c = coordinator_of(
        vec![
            mesh_job("forged.ron", &obj, true),
            mesh_job("true.ron", &obj, false),
        ],
        vec![obj.clone()],
    );
    let (log, _) = work_for(&c, &[]);
    let s = c.state();
    assert_eq!(s.failures.len(), 1, "{log}");
    assert!(
        s.failures[0].1.contains("content hash mismatch"),
        "{:?}",
        s.failures
    );
    assert_eq!(s.tiles, [2], "{log}");
    assert_eq!(
        s.fetches[&hypertexture::mesh::content_hash(&obj)],
        2,
        "the forged job's mesh was kept"
    );
}

/// Names from the coordinator reach the worker's log escaped: a scene name
/// holding newlines and ANSI escapes forges no line and colours nothing.
#[test]
fn names_from_the_coordinator_cannot_forge_log_lines() {
    let obj = sphere_obj(0);
    let name = "evil\nERROR forged line\r\n\u{1b}[31mred\u{1b}[0m\u{202e}.ron";
    let c = coordinator_of(
        vec![mesh_job(name, &obj, true), mesh_job(name, &obj, false)],
        vec![obj.clone()],
    );
    let (log, _) = work_for(&c, &[]);
    assert!(log.contains("fetched in"), "{log}");
    assert!(log.contains("content hash mismatch"), "{log}");
    for line in log.lines() {
        assert!(
            !line.trim_start().starts_with("ERROR forged"),
            "{line:?}\n{log}"
        );
        assert!(
            !line.starts_with('\u{1b}') && !line.contains("\u{1b}[31m"),
            "{line:?}"
        );
        assert!(!line.contains('\u{202e}'), "{line:?}");
    }
    assert!(log.contains("evil\\nERROR forged line\\r\\n"), "{log}");
}
