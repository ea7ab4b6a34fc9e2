//! Unit tests of the farm's edge without a network: its configuration
//! checks, a render's plan, jobs' wire forms, tiles accepted through the
//! farm's state, and jobs cancelled.

use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use hypertexture::render::interleave::{WorkUnit, work_units};
use hypertexture::{Overrides, PixelFormat, RenderRequest, Sample};
use hypertexture_proto::{convert, pb};
use tokio::sync::watch;

use super::scheduler::{Accepted, JobId, JobPlan, Next, Refusal, Resume, Scheduler};
use super::{
    FarmConfig, FarmError, FrameJob, FrameOut, Service, Shared, TileSink, WireJob, bind, refusal,
    tags_from_wire,
};

fn config(listen: &str, token: Option<&str>) -> FarmConfig {
    FarmConfig {
        listen: listen.parse().expect("a socket address"),
        token: token.map(str::to_string),
        lease: Duration::from_secs(5),
        worker_timeout: Duration::from_secs(5),
        local_workers: 0,
        local_threads: 1,
        preview_every: None,
        tls: None,
        interleave: 4,
        progress: false,
        gate: Default::default(),
        verify: 0.0,
        allow_hosts: Vec::new(),
    }
}

fn frame_job(frames: &[u32]) -> FrameJob {
    let mut request = RenderRequest::new("(scene text)", "test.ron");
    request.overrides = Overrides {
        width: Some(16),
        height: Some(16),
        spp: Some(3),
        quality: None,
        knobs: vec![("radius".into(), 0.5)],
    };
    request.pixel_format = PixelFormat::Samples;
    FrameJob {
        request,
        frames: frames
            .iter()
            .map(|&frame| FrameOut {
                frame,
                out: format!("frame{frame}.png").into(),
            })
            .collect(),
        metadata: Arc::new(crate::image::output::ImageMetadata::without_scene(
            16, 16, None, None,
        )),
        assets: Vec::new(),
    }
}

fn block_on<F: std::future::Future>(future: F) -> F::Output {
    tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .expect("a runtime")
        .block_on(future)
}

/// Keeps what the farm hands it; refuses every tile while `full`.
#[derive(Default)]
struct Sink {
    tiles: Mutex<Vec<(Accepted, usize)>>,
    full: std::sync::atomic::AtomicBool,
}

impl TileSink for Sink {
    fn tile(&self, accepted: &Accepted, pixels: &[u8]) -> Result<(), String> {
        if self.full.load(std::sync::atomic::Ordering::Relaxed) {
            return Err("the disk is full".into());
        }
        self.tiles
            .lock()
            .unwrap()
            .push((accepted.clone(), pixels.len()));
        Ok(())
    }
}

/// A farm's state with one job of 16×16 pixels (id 7), not served.
fn shared_with_job(sink: Option<Arc<dyn TileSink>>) -> (Arc<Shared>, Vec<WorkUnit>) {
    let (finished, _) = watch::channel(false);
    let config = config("127.0.0.1:0", None);
    let scheduler = Scheduler::service(config.lease);
    let shared = Arc::new(Shared::new(&config, scheduler, 0, finished, sink));
    let units = work_units(16, 16, 4, 64);
    let plan = JobPlan {
        id: 7,
        priority: 0,
        units: units.clone(),
        width: 16,
        height: 16,
        format: PixelFormat::Samples,
        frames: hypertexture::FrameRange::one(0),
        require_tags: Vec::new(),
    };
    shared
        .add_job(plan, Resume::default(), WireJob::of(&frame_job(&[0])))
        .expect("a new job");
    (shared, units)
}

fn assign(shared: &Shared, worker: &str) -> (u64, JobId, WorkUnit) {
    match shared.lock().scheduler.next(worker, Instant::now()) {
        Ok(Next::Assign {
            assignment_id,
            job,
            unit,
            ..
        }) => (assignment_id, job, unit),
        other => panic!("expected an assignment, got {other:?}"),
    }
}

fn tile_params(worker: &str, assignment_id: u64, unit: &WorkUnit) -> pb::SubmitTileParams {
    let samples = vec![Sample::from_array([0.25; Sample::CHANNELS]); unit.pixel_count(16)];
    pb::SubmitTileParams {
        worker_id: worker.to_string(),
        assignment_id,
        unit: Some(convert::unit_to_wire(unit)),
        pixels: convert::tile_to_wire(&samples, PixelFormat::Samples),
        render_cpu_micros: 1000,
        ..Default::default()
    }
}

#[test]
fn a_farm_beyond_loopback_needs_a_token_before_it_binds() {
    let refused = block_on(bind(&config("0.0.0.0:0", None)));
    assert!(
        matches!(refused, Err(FarmError::TokenRequired(addr)) if addr.port() == 0),
        "{:?}",
        refused.map(|(_, addr)| addr)
    );
    let (_, addr) = block_on(bind(&config("127.0.0.1:0", None))).expect("loopback binds");
    assert!(addr.ip().is_loopback() && addr.port() != 0);
}

#[test]
fn a_render_without_frames_or_with_gaps_between_them_is_refused_before_it_serves() {
    let render = |frames: &[u32]| {
        block_on(super::render_frames(
            frame_job(frames),
            // Were it to start, it would bind a port that cannot be bound.
            config("0.0.0.0:0", None),
            &mut |_| Ok(()),
            std::future::pending(),
        ))
    };
    match render(&[]) {
        Err(FarmError::Stopped(why)) => assert_eq!(why, "no frame to render"),
        other => panic!("expected a refusal, got {:?}", other.map(|r| r.tile_bytes)),
    }
    match render(&[1, 3]) {
        Err(FarmError::Stopped(why)) => assert!(why.contains("consecutive"), "{why}"),
        other => panic!("expected a refusal, got {:?}", other.map(|r| r.tile_bytes)),
    }
}

#[test]
fn tags_are_checked_and_each_kept_once() {
    let tags = |t: &[&str]| tags_from_wire(&t.iter().map(|s| s.to_string()).collect::<Vec<_>>());
    assert_eq!(
        tags(&["gpu", "eu-west.1", "gpu"]).unwrap(),
        ["gpu", "eu-west.1"]
    );
    let bad = tags(&["ok", "no spaces"]).unwrap_err();
    assert!(bad.contains("no spaces"), "{bad}");
    assert!(tags(&[""]).is_err());
    assert!(tags(&[&"x".repeat(65)]).is_err());
    let many: Vec<String> = (0..17).map(|i| format!("t{i}")).collect();
    assert!(tags_from_wire(&many).unwrap_err().contains("17 tags"));
}

#[test]
fn a_jobs_wire_form_leaves_the_text_out_only_for_workers_that_built_its_scene() {
    let job = frame_job(&[4, 5]);
    let wire = WireJob::of(&job);
    assert_eq!(wire.with_text.scene_text, job.request.scene_text);
    assert!(wire.without_text.scene_text.is_empty());
    assert_eq!(wire.with_text.scene_hash, wire.without_text.scene_hash);
    assert_eq!(wire.with_text.frame, 4);
    assert_eq!(wire.with_text.spp, 3);
    let mut other = job.clone();
    other.request.overrides.knobs[0].1 = 0.75;
    assert_ne!(
        WireJob::of(&other).with_text.scene_hash,
        wire.with_text.scene_hash
    );
    other.request.overrides.knobs = job.request.overrides.knobs.clone();
    other.request.overrides.spp = None;
    let none = WireJob::of(&other);
    assert_eq!(none.with_text.spp, 0, "no spp is 0 on the wire");
    assert_ne!(none.with_text.scene_hash, wire.with_text.scene_hash);
}

#[test]
fn a_tile_is_accepted_through_the_farms_state_kept_by_the_sink_and_counted() {
    let sink = Arc::new(Sink::default());
    let (shared, units) = shared_with_job(Some(sink.clone() as Arc<dyn TileSink>));
    let service = Service(Arc::clone(&shared));
    let worker = shared.lock().scheduler.register("a", 1, Instant::now());
    let mut bytes = 0;
    for _ in 0..units.len() {
        let (id, job, unit) = assign(&shared, &worker);
        assert_eq!(job, 7);
        let params = tile_params(&worker, id, &unit);
        bytes += params.pixels.len() as u64;
        let result = service.submit(params).expect("a well-formed tile");
        assert!(result.accepted);
        assert!(result.next.is_none(), "no next unit asked for");
    }
    let kept = sink.tiles.lock().unwrap();
    assert_eq!(kept.len(), units.len());
    assert!(
        kept.iter()
            .all(|(a, _)| a.job == 7 && a.worker == "a" && !a.held)
    );
    let state = shared.lock();
    assert_eq!(state.stats.latency_count, units.len() as u64);
    assert_eq!(
        shared.tile_bytes.load(std::sync::atomic::Ordering::Relaxed),
        bytes
    );
    assert!(state.scheduler.has_completed());
    assert!(state.scheduler.job_finished(7));
}

#[test]
fn a_forged_or_unkept_tile_is_refused_with_its_grpc_code() {
    let sink = Arc::new(Sink::default());
    let (shared, _) = shared_with_job(Some(sink.clone() as Arc<dyn TileSink>));
    let service = Service(Arc::clone(&shared));
    let worker = shared.lock().scheduler.register("a", 1, Instant::now());
    let (id, _, unit) = assign(&shared, &worker);

    let forged = service
        .submit(tile_params(&worker, id + 100, &unit))
        .unwrap_err();
    assert_eq!(forged.code(), tonic::Code::InvalidArgument);
    let stranger = service.submit(tile_params("w9-00", id, &unit)).unwrap_err();
    assert_eq!(stranger.code(), tonic::Code::NotFound);

    sink.full.store(true, std::sync::atomic::Ordering::Relaxed);
    let unkept = service.submit(tile_params(&worker, id, &unit)).unwrap_err();
    assert_eq!(unkept.code(), tonic::Code::FailedPrecondition);
    assert!(
        unkept.message().contains("the disk is full"),
        "{}",
        unkept.message()
    );
    assert!(
        shared.lock().scheduler.paused(),
        "nothing goes out while tiles cannot be kept"
    );
    assert!(sink.tiles.lock().unwrap().is_empty());
}

#[test]
fn refusals_map_to_the_grpc_codes_workers_act_on() {
    let codes = [
        (Refusal::UnknownWorker("w1".into()), tonic::Code::NotFound),
        (Refusal::NotHeld(1), tonic::Code::FailedPrecondition),
        (
            Refusal::Unstored {
                id: 1,
                reason: "full".into(),
            },
            tonic::Code::FailedPrecondition,
        ),
        (Refusal::NeverAssigned(1), tonic::Code::InvalidArgument),
        (Refusal::WrongUnit(1), tonic::Code::InvalidArgument),
    ];
    for (r, code) in codes {
        let text = r.to_string();
        let status = refusal(r);
        assert_eq!(status.code(), code, "{text}");
        assert_eq!(status.message(), text);
    }
}

#[test]
fn a_cancelled_job_withdraws_its_units_from_their_workers() {
    let (shared, _) = shared_with_job(None);
    let mut withdrawals = shared.withdrawals.subscribe();
    let (a, b) = {
        let mut s = shared.lock();
        let now = Instant::now();
        (
            s.scheduler.register("a", 1, now),
            s.scheduler.register("b", 1, now),
        )
    };
    let (first, _, _) = assign(&shared, &a);
    let (second, _, _) = assign(&shared, &b);
    assert!(shared.remove_job(7));
    let mut withdrawn = withdrawals.try_recv().expect("one message").to_vec();
    withdrawn.sort_by_key(|w| w.1);
    assert_eq!(withdrawn, [(a.clone(), first), (b, second)]);
    assert!(!shared.lock().wire.contains_key(&7));
    assert!(matches!(
        shared.lock().scheduler.next(&a, Instant::now()),
        Ok(Next::Wait)
    ));
    // Unknown, or already gone: nothing to withdraw.
    assert!(!shared.remove_job(7));
    assert!(withdrawals.try_recv().is_err());
}
