//! A unit's render on the worker's pool: the assignment decoded against its
//! built scene, the pixels rendered on the render threads with the CPU time
//! they took, and the tile encoded as the farm carries it.

use std::sync::Arc;
use std::sync::atomic::AtomicBool;

use hypertexture::render::bake::Lattice;
use hypertexture::render::interleave::WorkUnit;
use hypertexture::{PixelFormat, Scene};
use hypertexture_proto::{FailureKind, convert, pb};
use tokio::sync::oneshot;

use crate::cpu::{CpuClock, process_cpu_micros};
use crate::withdrawals::Withdrawn;
use crate::{Fault, Fetched, SceneCache, WorkerError};

/// The render threads, and the clock that tells their CPU time from the
/// async thread's.
pub(crate) struct RenderPool {
    pub(crate) threads: rayon::ThreadPool,
    /// The CPU clock of the async thread (the one that runs [`crate::run`]).
    pub(crate) async_clock: CpuClock,
}

impl RenderPool {
    /// `threads` render threads, and the clock of the calling (async) thread.
    pub(crate) fn new(threads: usize) -> Result<RenderPool, WorkerError> {
        Ok(RenderPool {
            threads: rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .thread_name(|i| format!("render-{i}"))
                .build()
                .map_err(|e| WorkerError::Threads {
                    threads,
                    message: e.to_string(),
                })?,
            async_clock: CpuClock::of_this_thread(),
        })
    }
}

/// A rendered tile: the unit, its pixels on the wire, the CPU microseconds.
type Tile = (WorkUnit, hypertexture_proto::Bytes, u64);

/// A unit on the render pool: its tile, or why it could not be rendered.
/// The result of a unit: its tile, nothing when it was withdrawn, or the
/// message of a panic.
pub(crate) type Rendering = oneshot::Receiver<Result<Option<Tile>, String>>;

/// A unit ready to render: what its assignment says, decoded against its
/// built scene.
struct UnitWork {
    scene: Arc<Scene>,
    unit: WorkUnit,
    frame: u32,
    format: PixelFormat,
    /// A bake's lattice: the unit's pixels are its voxels.
    bake: Option<Lattice>,
}

/// Starts rendering an assignment on the pool (the async thread goes on with
/// heartbeats and tiles). The result comes straight from the render thread: the
/// tile, or the message of a panic. An assignment that cannot be started (its
/// scene does not build here, it is malformed) is an error with its kind.
pub(crate) fn start_render(
    assignment: &pb::Assignment,
    (pool, withdrawn): (&RenderPool, &Arc<Withdrawn>),
    (scenes, fetched): (&mut SceneCache, &Fetched),
    fault: Option<Fault>,
) -> Result<Rendering, (FailureKind, String)> {
    let work = unit_work(assignment, (scenes, fetched), fault)?;
    let (done, result) = oneshot::channel();
    let assignment_id = assignment.assignment_id;
    let Some(stop) = withdrawn.start(assignment_id) else {
        let _ = done.send(Ok(None));
        return Ok(result);
    };
    let withdrawn = Arc::clone(withdrawn);
    let cpu = RenderCpu {
        one_thread: pool.threads.current_num_threads() == 1,
        async_clock: pool.async_clock,
    };
    pool.threads.spawn(move || {
        let render = || render_unit(work, &stop, cpu, fault);
        let tile = std::panic::catch_unwind(std::panic::AssertUnwindSafe(render))
            .map_err(|payload| format!("the render panicked: {}", panic_message(&*payload)));
        withdrawn.finish(assignment_id);
        let _ = done.send(tile);
    });
    Ok(result)
}

/// Decodes an assignment: its job's scene (built, or from the cache), its
/// unit, pixel format and bake lattice. Errors say whether the scene fails
/// here or only the assignment is unusable.
fn unit_work(
    assignment: &pb::Assignment,
    (scenes, fetched): (&mut SceneCache, &Fetched),
    fault: Option<Fault>,
) -> Result<UnitWork, (FailureKind, String)> {
    let job = assignment
        .job
        .as_ref()
        .ok_or((FailureKind::Assignment, "the assignment has no job".into()))?;
    let scene = match fault {
        Some(Fault::Scene) => Err((
            FailureKind::Scene,
            format!(
                "{}: the scene fails to build on purpose (fault injection)",
                job.scene_name
            ),
        )),
        _ => scenes.get(job, fetched),
    }?;
    if fault == Some(Fault::RenderClaim) {
        return Err((
            FailureKind::Render,
            "this unit cannot be rendered here (fault injection)".into(),
        ));
    }
    let unit = assignment
        .unit
        .as_ref()
        .ok_or(convert::WireError::Missing("unit"))
        .and_then(|u| convert::unit_from_wire(u, scene.width(), scene.height()))
        .map_err(|e| (FailureKind::Assignment, e.to_string()))?;
    let (format, bake) = tile_form(job, &scene)?;
    Ok(UnitWork {
        scene,
        unit,
        frame: job.frame,
        format,
        bake,
    })
}

/// How a job's tiles are made: their pixel format, and a bake's lattice (a
/// bake's pixels are the voxels of its lattice, `hypertexture::render::bake`).
pub(crate) fn tile_form(
    job: &pb::Job,
    scene: &Scene,
) -> Result<(PixelFormat, Option<Lattice>), (FailureKind, String)> {
    let format = convert::pixel_format_from_wire(job.pixel_format)
        .map_err(|e| (FailureKind::Assignment, e.to_string()))?;
    let bake = job
        .bake
        .as_ref()
        .map(|l| convert::lattice_from_wire(l, scene.width(), scene.height()))
        .transpose()
        .map_err(|e| (FailureKind::Assignment, e.to_string()))?;
    Ok((format, bake))
}

/// How a unit's render CPU is read. With one render thread, that thread's
/// own clock: exact, and blind to other workers in the same process (the
/// coordinator's in-process fallback). With several, the process's CPU but
/// the async thread's; the next unit's first pixels may overlap this one's
/// last: an estimate.
#[derive(Clone, Copy)]
struct RenderCpu {
    one_thread: bool,
    async_clock: CpuClock,
}

impl RenderCpu {
    /// The render CPU so far, in microseconds, read on a render thread
    /// (`own` is its clock).
    fn micros(self, own: CpuClock) -> u64 {
        if self.one_thread {
            own.micros()
        } else {
            process_cpu_micros().saturating_sub(self.async_clock.micros())
        }
    }
}

/// Renders a unit on a render thread: its tile, with the render threads' CPU
/// while it renders and its tile is encoded (the worker's whole cost of the
/// unit's pixels); `None` when it was withdrawn before the end.
fn render_unit(
    work: UnitWork,
    stop: &AtomicBool,
    cpu: RenderCpu,
    fault: Option<Fault>,
) -> Option<Tile> {
    if fault == Some(Fault::Panic) {
        panic!("the render panics on purpose (fault injection)");
    }
    let UnitWork {
        scene,
        unit,
        frame,
        format,
        bake,
    } = work;
    let pixels: Vec<(u32, u32)> = unit.pixels(scene.width()).collect();
    let own = CpuClock::of_this_thread();
    let before = cpu.micros(own);
    let mut tile = render_tile(&scene, &pixels, frame, format, bake.as_ref(), stop)?;
    let lies = match fault {
        Some(Fault::Garbage) => true,
        Some(Fault::GarbageFrom(first)) => frame >= first,
        _ => false,
    };
    if lies {
        tile = garbage(&tile, format).into();
    }
    let cpu = cpu.micros(own).saturating_sub(before);
    Some((unit, tile, cpu))
}

/// The tile of `pixels` encoded as the farm carries it: what a worker sends
/// and what the coordinator's own check of a unit compares. `None`: stopped.
pub(crate) fn render_tile(
    scene: &Scene,
    pixels: &[(u32, u32)],
    frame: u32,
    format: PixelFormat,
    bake: Option<&Lattice>,
    stop: &AtomicBool,
) -> Option<hypertexture_proto::Bytes> {
    let samples = match bake {
        Some(lattice) => {
            hypertexture::render::bake::sample_pixels(scene, lattice, frame, scene.width(), pixels)
        }
        None => hypertexture::render::render_pixels_until(scene, frame, pixels, stop)?,
    };
    Some(convert::tile_to_wire(&samples, format))
}

/// `tile` with every byte replaced by garbage of the same size ([`Fault::Garbage`]).
fn garbage(tile: &[u8], format: PixelFormat) -> Vec<u8> {
    let pattern: [u8; 4] = match format {
        PixelFormat::Srgb8 => [255, 0, 255, 255],
        PixelFormat::Samples => 1e38f32.to_le_bytes(),
    };
    pattern.iter().copied().cycle().take(tile.len()).collect()
}

/// The message a panic was raised with.
pub(crate) fn panic_message(payload: &(dyn std::any::Any + Send)) -> &str {
    payload
        .downcast_ref::<&str>()
        .copied()
        .or_else(|| payload.downcast_ref::<String>().map(String::as_str))
        .unwrap_or("(no message)")
}

/// Renders units exactly as a worker does, outside the farm: the
/// coordinator's own check of a unit (verified rendering) builds the scene
/// from the assignment's wire job with the worker's code and renders the
/// tile with the worker's function, so the bytes are those every worker of
/// this build must send. It renders on the caller's rayon pool.
pub struct UnitRenderer {
    scenes: SceneCache,
}

impl Default for UnitRenderer {
    fn default() -> UnitRenderer {
        UnitRenderer {
            scenes: SceneCache::new(crate::cache::DEFAULT_ASSET_CACHE_MB << 20),
        }
    }
}

impl UnitRenderer {
    /// Builds the scene of `job` (which carries its text), with the files it
    /// names from `files` (by content hash), as a worker would.
    pub fn build(
        &mut self,
        job: &pb::Job,
        files: &dyn Fn(u64) -> Option<Arc<Vec<u8>>>,
    ) -> Result<Arc<Scene>, (FailureKind, String)> {
        let mut fetched = Fetched::new();
        for a in self.scenes.missing(job) {
            let bytes = files(a.hash).ok_or_else(|| {
                (
                    FailureKind::Assignment,
                    format!(
                        "{}: no file {} with hash {:016x}",
                        job.scene_name, a.path, a.hash
                    ),
                )
            })?;
            let mesh = hypertexture::mesh::Mesh::from_obj(&a.path, &bytes, Default::default())
                .map_err(|e| (FailureKind::Scene, format!("{}: {e}", job.scene_name)))?;
            fetched.insert(a.hash, Arc::new(mesh));
        }
        self.scenes.get(job, &fetched)
    }

    /// The tile of `unit` of `job` (which carries its scene text and frame),
    /// as a worker sends it; `None` when `stop` was set before the end.
    pub fn render(
        &mut self,
        job: &pb::Job,
        unit: &WorkUnit,
        files: &dyn Fn(u64) -> Option<Arc<Vec<u8>>>,
        stop: &AtomicBool,
    ) -> Result<Option<Vec<u8>>, (FailureKind, String)> {
        let scene = self.build(job, files)?;
        let (format, bake) = tile_form(job, &scene)?;
        let pixels: Vec<(u32, u32)> = unit.pixels(scene.width()).collect();
        Ok(
            render_tile(&scene, &pixels, job.frame, format, bake.as_ref(), stop)
                .map(|t| t.to_vec()),
        )
    }
}

#[cfg(test)]
mod tests {
    use std::sync::atomic::AtomicBool;

    use hypertexture::render::interleave::work_units;

    use super::*;
    use crate::UnitRenderer;

    /// A job of scenes/noisy_sphere.ron at 8 × 8, as a coordinator sends it.
    fn job(pixel_format: pb::PixelFormat) -> pb::Job {
        let text = std::fs::read_to_string(concat!(
            env!("CARGO_MANIFEST_DIR"),
            "/../scenes/noisy_sphere.ron"
        ))
        .unwrap();
        pb::Job {
            scene_hash: convert::scene_hash(&text, 8, 8, 0, 0, &[]),
            scene_text: text,
            scene_name: "noisy_sphere.ron".into(),
            width: 8,
            height: 8,
            pixel_format: pixel_format as i32,
            ..Default::default()
        }
    }

    /// The unit of all 64 pixels.
    fn whole_image() -> WorkUnit {
        let units = work_units(8, 8, 1, 4096);
        assert_eq!(units.len(), 1);
        units[0]
    }

    fn assignment(assignment_id: u64, job: pb::Job) -> pb::Assignment {
        pb::Assignment {
            assignment_id,
            job: Some(job),
            unit: Some(convert::unit_to_wire(&whole_image())),
        }
    }

    /// Starts `assignment` on a pool of one thread and waits for its result.
    fn rendered(
        assignment: &pb::Assignment,
        withdrawn: &Arc<Withdrawn>,
        fault: Option<Fault>,
    ) -> Result<Result<Option<Tile>, String>, (FailureKind, String)> {
        let pool = RenderPool::new(1).unwrap();
        let mut scenes = SceneCache::new(1 << 20);
        let started = start_render(
            assignment,
            (&pool, withdrawn),
            (&mut scenes, &Fetched::new()),
            fault,
        )?;
        Ok(started.blocking_recv().unwrap())
    }

    #[test]
    fn a_unit_on_the_pool_renders_as_the_unit_renderer_does() {
        let job = job(pb::PixelFormat::Samples);
        let withdrawn = Arc::new(Withdrawn::default());
        let (unit, tile, _cpu) = rendered(&assignment(1, job.clone()), &withdrawn, None)
            .unwrap()
            .unwrap()
            .unwrap();
        assert_eq!(unit, whole_image());
        assert_eq!(tile.len(), 64 * PixelFormat::Samples.bytes_per_pixel());
        let expected = UnitRenderer::default()
            .render(&job, &unit, &|_| None, &AtomicBool::new(false))
            .unwrap()
            .unwrap();
        assert_eq!(tile.to_vec(), expected);
        assert!(
            withdrawn.start(1).is_some(),
            "a finished unit is no longer rendering"
        );
    }

    #[test]
    fn a_unit_withdrawn_before_it_starts_never_renders() {
        let withdrawn = Arc::new(Withdrawn::default());
        withdrawn.withdraw(&[7]);
        let result = rendered(
            &assignment(7, job(pb::PixelFormat::Samples)),
            &withdrawn,
            None,
        );
        assert_eq!(result, Ok(Ok(None)));
    }

    #[test]
    fn a_lying_worker_sends_garbage_of_the_right_size() {
        let withdrawn = Arc::new(Withdrawn::default());
        for format in [pb::PixelFormat::Samples, pb::PixelFormat::Srgb8] {
            let a = assignment(1, job(format));
            let truthful = rendered(&a, &withdrawn, None).unwrap().unwrap().unwrap();
            let lying = rendered(&a, &withdrawn, Some(Fault::Garbage))
                .unwrap()
                .unwrap()
                .unwrap();
            assert_eq!(lying.1.len(), truthful.1.len());
            assert_ne!(lying.1, truthful.1);
            // From frame 1 on: frame 0 is true.
            let from_next = rendered(&a, &withdrawn, Some(Fault::GarbageFrom(1)))
                .unwrap()
                .unwrap()
                .unwrap();
            assert_eq!(from_next.1, truthful.1);
        }
    }

    #[test]
    fn a_render_that_panics_comes_back_as_its_message() {
        let withdrawn = Arc::new(Withdrawn::default());
        let a = assignment(3, job(pb::PixelFormat::Samples));
        let message = rendered(&a, &withdrawn, Some(Fault::Panic))
            .unwrap()
            .unwrap_err();
        assert_eq!(
            message,
            "the render panicked: the render panics on purpose (fault injection)"
        );
        assert!(
            withdrawn.start(3).is_some(),
            "a panicked unit is no longer rendering"
        );
    }

    #[test]
    fn an_assignment_that_cannot_start_says_why() {
        let withdrawn = Arc::new(Withdrawn::default());
        let good = assignment(1, job(pb::PixelFormat::Samples));
        let kind = |a: &pb::Assignment, fault| match rendered(a, &withdrawn, fault) {
            Err((kind, message)) => {
                assert!(!message.is_empty());
                kind
            }
            Ok(r) => panic!("started: {r:?}"),
        };
        assert_eq!(kind(&good, Some(Fault::Scene)), FailureKind::Scene);
        assert_eq!(kind(&good, Some(Fault::RenderClaim)), FailureKind::Render);
        let no_job = pb::Assignment {
            job: None,
            ..good.clone()
        };
        assert_eq!(kind(&no_job, None), FailureKind::Assignment);
        let no_unit = pb::Assignment {
            unit: None,
            ..good.clone()
        };
        assert_eq!(kind(&no_unit, None), FailureKind::Assignment);
        let unspecified = assignment(1, job(pb::PixelFormat::Unspecified));
        assert_eq!(kind(&unspecified, None), FailureKind::Assignment);
        let mut forged = job(pb::PixelFormat::Samples);
        forged.scene_hash ^= 1;
        assert_eq!(kind(&assignment(1, forged), None), FailureKind::Scene);
    }

    #[test]
    fn garbage_is_opaque_magenta_or_huge_floats() {
        assert_eq!(
            garbage(&[0; 8], PixelFormat::Srgb8),
            [255, 0, 255, 255, 255, 0, 255, 255]
        );
        let floats = garbage(&[0; 8], PixelFormat::Samples);
        assert_eq!(floats.len(), 8);
        for f in floats.chunks(4) {
            assert_eq!(f32::from_le_bytes(f.try_into().unwrap()), 1e38);
        }
        assert!(garbage(&[], PixelFormat::Samples).is_empty());
    }

    #[test]
    fn a_panics_message_is_its_text() {
        let text: Box<dyn std::any::Any + Send> = Box::new("static");
        assert_eq!(panic_message(&*text), "static");
        let formatted: Box<dyn std::any::Any + Send> = Box::new(format!("n = {}", 3));
        assert_eq!(panic_message(&*formatted), "n = 3");
        let other: Box<dyn std::any::Any + Send> = Box::new(42u32);
        assert_eq!(panic_message(&*other), "(no message)");
    }
}
