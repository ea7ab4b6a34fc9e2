//! The worker: a stateless renderer that dials the coordinator and pulls work.
//!
//! Each assignment carries the scene's content hash, and its text (a few KB)
//! unless the worker said it has built that scene; the worker builds the scene
//! once per hash, renders the unit's pixels with all its threads and submits the
//! tile. A unit it cannot render (the scene does not build here, the assignment
//! is unusable, the render panics) goes back to the coordinator with the reason
//! (ReportFailure), never held in silence. Tiles go up on one SubmitTiles stream,
//! a message per unit; the reply to a tile brings the next unit, and one unit
//! is always assigned ahead and queued on the render pool, so the render
//! threads never wait for the network or for this thread: while unit n
//! renders, tile n − 1 travels and its reply brings unit n + 1. A background
//! task heartbeats so the coordinator knows it is alive. When the coordinator
//! goes away the worker reconnects with exponential backoff; when asked to stop
//! (SIGTERM) it finishes and delivers the unit rendering, says goodbye (the
//! coordinator puts the unit assigned ahead back in the queue at once, with no
//! lease to wait out) and returns. With `idle_exit` it also returns after that
//! long with nothing to render, its coordinator reached or not.
//!
//! The modules, from the outside in: [`run`] (`run.rs`) connects, registers
//! and reconnects; `connection` holds the coordinator's address, TLS, token
//! and backoff; `register` the known-answer probe, registration, heartbeat
//! and goodbye; `session` the work loop over one registration, one unit
//! ahead; `tiles` the SubmitTiles stream; `withdrawals` the units taken
//! back; `assets` the meshes fetched; `render` a unit's render on the pool;
//! `cpu` the CPU clocks; `idle` the time without work (`--idle-exit`);
//! `signal` the stop signals. This file holds the
//! configuration, the error, the built scenes ([`UnitRenderer`] and the
//! scene cache, by content hash).

pub mod body;
pub mod cache;
pub mod cli;
pub mod logging;

mod assets;
mod connection;
mod cpu;
mod idle;
mod register;
mod render;
mod run;
mod session;
mod signal;
mod tiles;
mod withdrawals;

use std::collections::HashMap;
use std::sync::Arc;
use std::time::Duration;

use hypertexture::Scene;
use hypertexture_proto::FailureKind;
use hypertexture_proto::pb;

pub use connection::Auth;
pub use cpu::process_cpu_micros;
pub use run::run;
pub use signal::{exit_when_orphaned, shutdown_signal};

pub use render::UnitRenderer;

/// Everything a worker needs to know.
#[derive(Clone, Debug)]
pub struct WorkerConfig {
    /// The coordinator's URL.
    pub coordinator: String,
    /// Render threads.
    pub threads: usize,
    /// The farm's shared secret, if it has one.
    pub token: Option<String>,
    /// Name shown in the coordinator's logs.
    pub name: String,
    /// PEM CA certificate for TLS.
    pub ca: Option<Vec<u8>>,
    /// Return when the frame is finished instead of waiting for the next one;
    /// and fail ([`WorkerError::CoordinatorGone`]) once a coordinator this
    /// worker had reached (made a connection to, registered or not) has been
    /// unreachable for `lease`.
    pub exit_when_done: bool,
    /// How long a coordinator may be unreachable before an `exit_when_done`
    /// worker gives up on it (the coordinator's lease time-out).
    pub lease: Duration,
    /// Fail on purpose (tests of the failure path only; `None` in every binary).
    pub fault: Option<Fault>,
    /// The worker runs inside another program (the coordinator's in-process
    /// fallback), so the process's CPU is not its own: its goodbye reports
    /// none.
    pub shares_process: bool,
    /// Tags: the coordinator hands this worker only jobs whose required tags
    /// it carries.
    pub tags: Vec<String>,
    /// The most bytes of meshes kept between assignments ([`cache::AssetCache`]).
    pub asset_cache_bytes: u64,
    /// Return (with a goodbye when registered) after this long with nothing
    /// to render: no unit from the coordinator, or no coordinator reached,
    /// whether it never was or has gone (`None`: stay).
    pub idle_exit: Option<Duration>,
}

/// A failure a test asks a worker to have, to exercise what follows it.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Fault {
    /// Every scene fails to build.
    Scene,
    /// Every render panics.
    Panic,
    /// The known-answer probe's digest is one bit off, as another build's would be.
    Arithmetic,
    /// Every tile is garbage of the right size: each float 1e38 in a tile of
    /// samples, each pixel opaque magenta in an 8-bit tile (a lying worker).
    Garbage,
    /// Tiles are true in frames before this one and garbage from it on (a
    /// worker that turns liar in the middle of a sequence).
    GarbageFrom(u32),
    /// Every unit is given back as one this worker cannot render, without
    /// trying (a lying worker).
    RenderClaim,
}

/// Why a worker gave up. Network trouble is not here: it is retried forever.
#[derive(Debug, thiserror::Error)]
pub enum WorkerError {
    /// The coordinator URL cannot be used.
    #[error("invalid coordinator address {url}: {message}")]
    Address {
        /// The URL given.
        url: String,
        /// What is wrong with it.
        message: String,
    },
    /// The CA certificate file cannot be read.
    #[error("{path}: cannot read the CA certificate: {source}")]
    Ca {
        /// The file.
        path: std::path::PathBuf,
        /// What the OS said.
        source: std::io::Error,
    },
    /// A variable of the environment that a flag left out defaults to
    /// cannot be used.
    #[error("{name} in the environment: {message}")]
    Environment {
        /// The variable.
        name: &'static str,
        /// What is wrong with its value.
        message: String,
    },
    /// The coordinator refused this worker for good (wrong token, other protocol
    /// version, other arithmetic).
    #[error("the coordinator refused this worker: {0}")]
    Refused(String),
    /// This build's known-answer probe did not run (a defect of the build).
    #[error("the known-answer probe: {0}")]
    Probe(String),
    /// The render threads could not be started.
    #[error("cannot start {threads} render threads: {message}")]
    Threads {
        /// How many.
        threads: usize,
        /// Why not.
        message: String,
    },
    /// An `exit_when_done` worker's coordinator has been unreachable for the
    /// whole lease: the render it served is over, one way or another.
    #[error("{url} has been unreachable for {secs:.0} s: leaving")]
    CoordinatorGone {
        /// The coordinator.
        url: String,
        /// How long it has been unreachable.
        secs: f64,
    },
}

/// What a worker did before it returned.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct WorkerReport {
    /// Units rendered and accepted.
    pub units: u64,
    /// Units dropped unfinished because the coordinator took them back (their
    /// job was cancelled, or a studio frame superseded).
    pub withdrawn: u64,
    /// From the start of [`run`] to its first unit on the render pool: the
    /// known-answer probe, connecting, registering, fetching the scene's
    /// files and building the scene (a mesh's distance field included).
    pub first_unit_after: Option<std::time::Duration>,
    /// When [`run`] started.
    pub(crate) started: Option<std::time::Instant>,
}

/// Meshes fetched for one assignment and not kept yet: the cache takes them
/// only once the scene's hash has matched and the scene has built.
type Fetched = HashMap<u64, Arc<hypertexture::mesh::Mesh>>;

/// Scenes built from assignments, by content hash (a worker holds a few at
/// most), and the meshes they name ([`cache::AssetCache`], within a budget).
struct SceneCache {
    scenes: HashMap<u64, CachedScene>,
    /// The files scenes name (meshes), fetched, verified and built, by
    /// content hash; kept only for scenes whose hash matched.
    assets: cache::AssetCache,
    /// The hash of the scene used last (0: none): the coordinator leaves its
    /// text out of the assignments that follow.
    last: u64,
    /// Counts uses: a scene's `used` is the count at its last use.
    clock: u64,
}

struct CachedScene {
    scene: Arc<Scene>,
    /// The content hashes of the meshes it names.
    assets: Vec<u64>,
    used: u64,
}

impl SceneCache {
    const CAPACITY: usize = 4;

    /// An empty cache that keeps at most `asset_bytes` of meshes, but for
    /// those of the scene in use.
    fn new(asset_bytes: u64) -> SceneCache {
        SceneCache {
            scenes: HashMap::new(),
            assets: cache::AssetCache::new(asset_bytes),
            last: 0,
            clock: 0,
        }
    }

    /// The hash of a scene this worker has built and still holds (0: none).
    fn known(&self) -> u64 {
        if self.scenes.contains_key(&self.last) {
            self.last
        } else {
            0
        }
    }

    /// The files of `job` this worker must fetch before its scene can be
    /// built: none when that scene is built already, else those it does not
    /// hold (each once).
    fn missing<'a>(&self, job: &'a pb::Job) -> Vec<&'a pb::AssetRef> {
        if job.scene_text.is_empty() || self.scenes.contains_key(&job.scene_hash) {
            return Vec::new();
        }
        let mut missing: Vec<&pb::AssetRef> = Vec::new();
        for a in &job.assets {
            if !self.assets.contains(a.hash) && !missing.iter().any(|m| m.hash == a.hash) {
                missing.push(a);
            }
        }
        missing
    }

    /// A built scene, now the most recently used (with its meshes).
    fn touch(&mut self, hash: u64) -> Option<Arc<Scene>> {
        self.clock += 1;
        let cached = self.scenes.get_mut(&hash)?;
        cached.used = self.clock;
        for a in &cached.assets {
            self.assets.get(*a);
        }
        Some(Arc::clone(&cached.scene))
    }

    /// The built scene of a job, with the meshes `fetched` for it or kept.
    /// Errors say whether the scene itself fails here (every unit of the job
    /// would: [`FailureKind::Scene`]) or only this assignment was unusable.
    /// The scene and the meshes fetched for it are kept only once its hash
    /// has matched and it has built.
    fn get(
        &mut self,
        job: &pb::Job,
        fetched: &Fetched,
    ) -> Result<Arc<Scene>, (FailureKind, String)> {
        if job.scene_text.is_empty() {
            // Left out by the coordinator: this worker said it has the scene.
            return self.touch(job.scene_hash).ok_or_else(|| {
                // Say "none" from now on, so the next assignment brings the text.
                self.last = 0;
                (
                    FailureKind::Assignment,
                    format!(
                        "the assignment leaves out the text of scene {:016x}, which this worker has not built",
                        job.scene_hash
                    ),
                )
            });
        }
        let scene_failure = |e: String| (FailureKind::Scene, e);
        // A job whose wire form does not decode is the assignment's fault,
        // not the scene's: another try may bring it whole.
        let request = hypertexture_proto::request::from_wire(job)
            .map_err(|e| (FailureKind::Assignment, e.to_string()))?;
        let hashes: Vec<(String, u64)> = job
            .assets
            .iter()
            .map(|a| (a.path.clone(), a.hash))
            .collect();
        let hash = hypertexture_proto::request::content_hash(&request, &hashes);
        if hash != job.scene_hash {
            return Err(scene_failure(format!(
                "{}: content hash mismatch ({hash:016x} ≠ {:016x})",
                job.scene_name, job.scene_hash
            )));
        }
        if let Some(scene) = self.touch(hash) {
            self.last = hash;
            return Ok(scene);
        }
        let mut assets = hypertexture::scene::Assets::none();
        for a in &job.assets {
            let mesh = match fetched.get(&a.hash) {
                Some(mesh) => Arc::clone(mesh),
                None => self.assets.get(a.hash).ok_or_else(|| {
                    (
                        FailureKind::Assignment,
                        format!("{}: the file {} has not arrived", job.scene_name, a.path),
                    )
                })?,
            };
            assets.insert(&a.path, mesh);
        }
        // Only the files that came with the job: a worker reads none from
        // disk. The scene the coordinator of this process built is taken as it is.
        let scene = request
            .build_shared(hash, Some(&assets))
            .map_err(|e| scene_failure(e.to_string()))?;
        self.keep(hash, &scene, job, fetched);
        Ok(scene)
    }

    /// Keeps a scene that has built and the meshes fetched for it. Scenes
    /// that name a mesh the budget pushed out go too (they would hold it).
    fn keep(&mut self, hash: u64, scene: &Arc<Scene>, job: &pb::Job, fetched: &Fetched) {
        let pinned: Vec<u64> = job.assets.iter().map(|a| a.hash).collect();
        let mut dropped = Vec::new();
        for (h, mesh) in fetched.iter().filter(|(h, _)| pinned.contains(h)) {
            dropped.extend(self.assets.keep(*h, Arc::clone(mesh), &pinned));
        }
        self.scenes
            .retain(|_, s| !s.assets.iter().any(|a| dropped.contains(a)));
        if self.scenes.len() >= Self::CAPACITY {
            let oldest = self
                .scenes
                .iter()
                .min_by_key(|(_, s)| s.used)
                .map(|(h, _)| *h);
            if let Some(oldest) = oldest {
                self.scenes.remove(&oldest);
            }
        }
        self.clock += 1;
        self.scenes.insert(
            hash,
            CachedScene {
                scene: Arc::clone(scene),
                assets: pinned,
                used: self.clock,
            },
        );
        self.last = hash;
    }
}

#[cfg(test)]
mod testing;

#[cfg(test)]
mod tests {
    use super::*;
    use hypertexture_proto::convert;

    fn job(text: &str) -> pb::Job {
        pb::Job {
            scene_hash: convert::scene_hash(text, 8, 8, 0, 0, &[]),
            scene_text: text.to_string(),
            scene_name: "test.ron".into(),
            width: 8,
            height: 8,
            pixel_format: pb::PixelFormat::Srgb8 as i32,
            ..Default::default()
        }
    }

    #[test]
    fn a_scene_is_built_once_and_then_needs_no_text() {
        let text = std::fs::read_to_string(concat!(
            env!("CARGO_MANIFEST_DIR"),
            "/../scenes/noisy_sphere.ron"
        ))
        .unwrap();
        let mut scenes = SceneCache::new(1 << 20);
        assert_eq!(scenes.known(), 0);
        let full = job(&text);
        let without_text = pb::Job {
            scene_text: String::new(),
            ..full.clone()
        };
        assert!(
            scenes.get(&without_text, &Fetched::new()).is_err(),
            "no text and never built: refused"
        );
        let built = scenes.get(&full, &Fetched::new()).unwrap();
        assert_eq!(scenes.known(), full.scene_hash);
        assert!(Arc::ptr_eq(
            &built,
            &scenes.get(&without_text, &Fetched::new()).unwrap()
        ));
        let forged = pb::Job {
            scene_hash: full.scene_hash ^ 1,
            ..full
        };
        assert!(
            scenes.get(&forged, &Fetched::new()).is_err(),
            "a hash that does not match the text"
        );
    }

    /// A scene naming one mesh, `t.obj` (tetrahedron `k`), as a coordinator
    /// sends it, and the mesh as the worker builds it.
    fn mesh_job(k: u32, hash_of_text: Option<u64>) -> (pb::Job, Fetched) {
        let text = "Scene(\n    image: (width: 8, height: 8),\n    camera: (eye: (0.3, 0.3, 3.0), look_at: (0.3, 0.3, 0.3), up: (0.0, 1.0, 0.0), projection: Perspective(fov_y: 40.0)),\n    march: (bounds: (min: (-0.2, -0.2, -0.2), max: (1.2, 1.2, 1.2)), step: Length(0.05), opacity: 40.0, threshold: 0.99),\n    object: Mesh(path: \"t.obj\", softness: 0.1),\n)\n";
        let obj = cache::tetrahedron_obj(k);
        let hash = hypertexture::mesh::content_hash(obj.as_bytes());
        let mesh = hypertexture::mesh::Mesh::from_obj("t.obj", obj.as_bytes(), Default::default())
            .unwrap();
        let job = pb::Job {
            scene_hash: hash_of_text.unwrap_or_else(|| {
                convert::scene_hash_with_assets(
                    convert::scene_hash(text, 8, 8, 0, 0, &[]),
                    &[("t.obj".to_string(), hash)],
                )
            }),
            scene_text: text.to_string(),
            scene_name: "mesh.ron".into(),
            width: 8,
            height: 8,
            assets: vec![pb::AssetRef {
                path: "t.obj".into(),
                hash,
                size: obj.len() as u64,
            }],
            pixel_format: pb::PixelFormat::Srgb8 as i32,
            ..Default::default()
        };
        (job, Fetched::from([(hash, Arc::new(mesh))]))
    }

    #[test]
    fn a_mesh_is_kept_only_once_its_scenes_hash_matches() {
        let mut scenes = SceneCache::new(1 << 20);
        let (forged, fetched) = mesh_job(0, Some(42));
        let (kind, message) = scenes.get(&forged, &fetched).unwrap_err();
        assert_eq!(kind, FailureKind::Scene);
        assert!(message.contains("content hash mismatch"), "{message}");
        assert!(
            scenes.assets.is_empty(),
            "a mesh of a forged scene is not kept"
        );
        assert_eq!(scenes.missing(&forged).len(), 1, "it is fetched again");

        let (job, fetched) = mesh_job(0, None);
        scenes.get(&job, &fetched).unwrap();
        assert_eq!(scenes.assets.len(), 1);
        assert!(scenes.missing(&job).is_empty());
        assert_eq!(scenes.known(), job.scene_hash);
    }

    #[test]
    fn meshes_past_the_budget_go_with_their_scenes() {
        let one = mesh_job(0, None).1.values().next().unwrap().memory_bytes() as u64;
        let mut scenes = SceneCache::new(2 * one);
        for k in 0..50 {
            let (job, fetched) = mesh_job(k, None);
            scenes.get(&job, &fetched).unwrap();
            assert!(scenes.assets.bytes() <= 2 * one, "{k}");
            assert!(scenes.scenes.len() <= 2, "{k}: a scene holds its mesh");
            assert_eq!(scenes.known(), job.scene_hash);
        }
        // The last two are kept; the first was dropped and is fetched again.
        assert!(scenes.missing(&mesh_job(49, None).0).is_empty());
        assert!(scenes.missing(&mesh_job(48, None).0).is_empty());
        assert_eq!(scenes.missing(&mesh_job(0, None).0).len(), 1);
    }
}
