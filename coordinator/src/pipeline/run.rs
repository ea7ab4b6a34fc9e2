//! `coordinator --scene …`: loads a scene, renders it on the farm or in
//! this process, writes the image (or a numbered sequence of images).

use std::io::IsTerminal;
use std::num::NonZeroUsize;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::{Duration, Instant};

use hypertexture::{Film, FrameRange, Overrides, RenderRequest, Scene, SceneError};

use crate::farm;
use crate::image::output::{ImageFormat, ImageMetadata};

/// Everything a render needs to know.
#[derive(Clone, Debug)]
pub struct Config {
    /// The scene file, or an image the coordinator wrote (for messages).
    pub scene: PathBuf,
    /// Output image (.png or .exr); a sequence's files go beside it.
    pub out: PathBuf,
    /// What to render: the scene's text and name, overrides, frames, pixel format.
    pub request: RenderRequest,
    /// The frames are a numbered sequence (`--frames`) rather than one image.
    pub sequence: bool,
    /// Render threads (default: every core).
    pub threads: Option<NonZeroUsize>,
    /// Show a progress bar when stderr is a terminal.
    pub progress: bool,
    /// Render on the farm with these options; `None`: in-process.
    pub farm: Option<FarmOptions>,
}

/// How to run the farm (from the command line).
#[derive(Clone, Debug)]
pub struct FarmOptions {
    /// Listen address.
    pub listen: std::net::SocketAddr,
    /// Shared secret.
    pub token: Option<String>,
    /// Lease time-out.
    pub lease: Duration,
    /// Give up after this long without workers.
    pub worker_timeout: Duration,
    /// Local workers to start.
    pub local_workers: usize,
    /// Preview interval.
    pub preview_every: Option<Duration>,
    /// TLS certificate and key files.
    pub tls: Option<(PathBuf, PathBuf)>,
    /// The interleave B.
    pub interleave: u32,
    /// The fraction of units rendered twice and compared (verified rendering).
    pub verify: f64,
}

impl FarmOptions {
    /// The farm's configuration: these options, with `threads` per local
    /// worker (default 1) and the TLS files read.
    pub fn farm_config(
        &self,
        threads: Option<NonZeroUsize>,
        progress: bool,
    ) -> Result<farm::FarmConfig, CoordinatorError> {
        let tls = match &self.tls {
            Some((cert, key)) => Some(crate::farm::cert::read_server_tls(cert, key)?),
            None => None,
        };
        Ok(farm::FarmConfig {
            listen: self.listen,
            token: self.token.clone(),
            lease: self.lease,
            worker_timeout: self.worker_timeout,
            local_workers: self.local_workers,
            local_threads: threads.map_or(1, NonZeroUsize::get),
            preview_every: self.preview_every,
            tls,
            interleave: self.interleave,
            progress,
            gate: Default::default(),
            verify: self.verify,
            allow_hosts: Vec::new(),
        })
    }
}

impl Config {
    /// A configuration rendering the scene in the file `scene` to `out` as
    /// `request` asks (its scene text and name are read from the file), in
    /// this process with every core and no progress bar. `out` is checked
    /// first (its format, and that its directory takes files), so that a bad
    /// name fails before any time is spent; the pixel format is what `out`
    /// needs. A PNG or EXR the coordinator wrote gives the scene it stores,
    /// and its size, frame, samples, quality and knobs where `request` sets
    /// none, so that the render comes out the same again.
    pub fn load(
        scene: &Path,
        out: PathBuf,
        request: RenderRequest,
        sequence: bool,
    ) -> Result<Config, CoordinatorError> {
        ImageFormat::from_path(&out)?;
        // A sequence's files go beside `out`: one directory to check.
        crate::files::check_writable(&out)?;
        let request = RenderRequest {
            pixel_format: crate::image::output::pixel_format_for([out.as_path()]),
            ..read_scene(scene, request, sequence)?
        };
        Ok(Config {
            scene: scene.to_path_buf(),
            out,
            request,
            sequence,
            threads: None,
            progress: false,
            farm: None,
        })
    }

    /// The frames and the file each image goes to: `out` for one image, or
    /// numbered files beside it for a sequence ([`frame_path`]).
    fn frame_outputs(&self) -> Vec<farm::FrameOut> {
        let FrameRange { first, last } = self.request.frames;
        if !self.sequence {
            return vec![farm::FrameOut {
                frame: first,
                out: self.out.clone(),
            }];
        }
        (first..=last)
            .map(|frame| farm::FrameOut {
                frame,
                out: frame_path(&self.out, frame),
            })
            .collect()
    }
}

/// `request` with the scene text and name of the file `scene`: a scene file
/// as it is; a PNG or EXR written by the coordinator gives the scene it
/// stores, its name, and its size, frame, samples, quality and knobs where
/// `request` sets none (its knobs first, the request's after them); the
/// stored frame is taken unless `sequence` or a frame other than 0 is asked.
fn read_scene(
    scene: &Path,
    request: RenderRequest,
    sequence: bool,
) -> Result<RenderRequest, CoordinatorError> {
    if ImageFormat::from_path(scene).is_err() {
        return Ok(RenderRequest {
            scene_text: hypertexture::scene::read_text(scene)?,
            scene_name: scene.display().to_string(),
            ..request
        });
    }
    let stored = crate::image::output::read_stored_render(scene)?;
    tracing::info!(
        "{}: the scene {} stored in the image",
        scene.display(),
        stored.scene_name
    );
    let (o, given) = (stored.overrides, request.overrides);
    let frames = if sequence || request.frames.first != 0 {
        request.frames
    } else {
        stored.frames
    };
    Ok(RenderRequest {
        scene_text: stored.scene_text,
        scene_name: stored.scene_name,
        overrides: hypertexture::Overrides {
            width: given.width.or(o.width),
            height: given.height.or(o.height),
            spp: given.spp.or(o.spp),
            quality: given.quality.or(o.quality),
            knobs: Overrides::knob_list(o.knobs.into_iter().chain(given.knobs)),
        },
        frames,
        ..request
    })
}

/// Why a render failed.
#[derive(Debug, thiserror::Error)]
pub enum CoordinatorError {
    /// The scene could not be loaded.
    #[error(transparent)]
    Scene(#[from] SceneError),
    /// The image could not be written.
    #[error(transparent)]
    Output(#[from] crate::image::output::OutputError),
    /// The farm failed.
    #[error(transparent)]
    Farm(#[from] farm::FarmError),
    /// A file named on the command line cannot be used.
    #[error(transparent)]
    File(#[from] crate::files::FileError),
    /// A transfer-function image could not be read.
    #[error("{path}: cannot use the image as a transfer function: {message}")]
    TransferImage {
        /// The image file.
        path: PathBuf,
        /// What was wrong.
        message: String,
    },
    /// The async runtime could not be started.
    #[error("cannot start the async runtime: {0}")]
    Runtime(std::io::Error),
    /// An expression given on the command line is wrong.
    #[error("{0}")]
    Expression(String),
    /// A file the scene names (a mesh) cannot be served to the farm.
    #[error("{0}")]
    Asset(String),
    /// An image could not be recoloured.
    #[error("{path}: {message}")]
    Recolor {
        /// The file at fault.
        path: PathBuf,
        /// What went wrong.
        message: String,
    },
    /// A bake cannot be done as asked.
    #[error("{0}")]
    Bake(String),
    /// The render threads could not be started.
    #[error("cannot start {threads} render threads: {message}")]
    Threads {
        /// How many were asked for.
        threads: usize,
        /// What went wrong.
        message: String,
    },
}

/// What a finished render reports.
#[derive(Clone, Debug)]
pub struct Summary {
    /// Wall time of the render itself (not loading, not writing).
    pub render_time: Duration,
    /// Where the image went.
    pub out: PathBuf,
}

/// The file of frame `frame` of a sequence written to `out`: `fire.png` → `fire_0007.png`.
pub fn frame_path(out: &Path, frame: u32) -> PathBuf {
    let stem = out
        .file_stem()
        .map_or_else(|| "frame".into(), |s| s.to_string_lossy().into_owned());
    let ext = out
        .extension()
        .map_or_else(String::new, |e| format!(".{}", e.to_string_lossy()));
    out.with_file_name(format!("{stem}_{frame:04}{ext}"))
}

/// Renders every frame of `config.request` and writes each image; a
/// sequence goes to numbered files beside `config.out`. The scene is built
/// once. On the farm a sequence is one session: the server and workers stay
/// up from the first frame to the last, and each image is written as soon
/// as it is complete.
pub fn run_all(config: Config) -> Result<Vec<Summary>, CoordinatorError> {
    let frames = config.frame_outputs();
    let built = hypertexture_proto::request::build(&config.request, None)?;
    let metadata = ImageMetadata::new(&built.scene, &config.request);
    let Some(options) = &config.farm else {
        return render_all_in_process(&config, &built.scene, &metadata, frames);
    };
    render_on_farm(&config, options, &built, metadata, frames)
}

/// Renders `frames` one after another on a pool of the configured threads
/// in this process, writing each image.
fn render_all_in_process(
    config: &Config,
    scene: &Scene,
    metadata: &ImageMetadata,
    frames: Vec<farm::FrameOut>,
) -> Result<Vec<Summary>, CoordinatorError> {
    let threads = config.threads.map_or_else(
        || std::thread::available_parallelism().map_or(1, NonZeroUsize::get),
        NonZeroUsize::get,
    );
    let how = format!("{threads} thread{}", if threads == 1 { "" } else { "s" });
    frames
        .into_iter()
        .map(|f| {
            let (film, time) = render_in_process(scene, f.frame, threads, config.progress)?;
            let image = crate::image::canvas::FrameImage::Film(film);
            let meta = metadata.at_frame(f.frame);
            write_frame(config, scene, &image, &meta, time, &f.out, &how)
        })
        .collect()
}

/// Renders the first frame of `config.request` (see [`run_all`]).
pub fn run(config: Config) -> Result<Summary, CoordinatorError> {
    let mut summaries = run_all(Config {
        sequence: false,
        ..config
    })?;
    Ok(summaries.remove(0))
}

/// Writes a frame's image and says so.
fn write_frame(
    config: &Config,
    scene: &Scene,
    image: &crate::image::canvas::FrameImage,
    meta: &ImageMetadata,
    render_time: Duration,
    out: &Path,
    how: &str,
) -> Result<Summary, CoordinatorError> {
    crate::image::output::write_frame_image(image, out, meta)?;
    let frame = meta.frame();
    tracing::info!(
        "rendered {} ({}×{}, frame {frame}) with {how} in {:.3} s → {}",
        config.scene.display(),
        scene.width(),
        scene.height(),
        render_time.as_secs_f64(),
        out.display()
    );
    Ok(Summary {
        render_time,
        out: out.to_path_buf(),
    })
}

/// Renders `frames` of the request `built` on the farm as one session
/// (starting local workers as configured), writing each image, on a thread
/// of its own, as soon as its frame is complete.
pub fn render_on_farm(
    config: &Config,
    options: &FarmOptions,
    built: &hypertexture_proto::request::Built,
    metadata: ImageMetadata,
    frames: Vec<farm::FrameOut>,
) -> Result<Vec<Summary>, CoordinatorError> {
    let scene = &built.scene;
    let metadata = Arc::new(metadata);
    let job = farm::FrameJob {
        request: built.request.clone(),
        frames,
        metadata: metadata.clone(),
        assets: farm::Asset::of_scene(scene, &built.request.scene_name)
            .map_err(CoordinatorError::Asset)?,
    };
    let farm_config = options.farm_config(config.threads, config.progress)?;
    // One thread serves the farm: per unit it only checks and stores a tile, and
    // any thread more competes with the render threads of local workers.
    let runtime = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .map_err(CoordinatorError::Runtime)?;
    // Encoding an image takes a while: not on the thread that serves the workers.
    let (to_writer, finished) = std::sync::mpsc::channel::<farm::FrameDone>();
    let (session, written) = std::thread::scope(|scope| {
        let writer = scope.spawn(move || {
            finished
                .into_iter()
                .map(|done| {
                    let f = done.frame;
                    let meta = metadata.at_frame(f.frame);
                    write_frame(
                        config,
                        scene,
                        &f.image,
                        &meta,
                        f.render_time,
                        &done.out,
                        "the farm",
                    )
                })
                .collect::<Result<Vec<Summary>, CoordinatorError>>()
        });
        let session = runtime.block_on(farm::render_frames(
            job,
            farm_config,
            &mut |done| {
                to_writer.send(done).map_err(|_| {
                    farm::FarmError::Stopped("an image could not be written: stopping".into())
                })
            },
            worker::shutdown_signal(),
        ));
        drop(to_writer);
        // The writer's error says what went wrong; the farm's only that it stopped.
        let written = writer
            .join()
            .unwrap_or_else(|p| std::panic::resume_unwind(p))?;
        Ok::<_, CoordinatorError>((session?, written))
    })?;
    let written = last_of_each_file(written);
    log_session(&session, written.len());
    Ok(written)
}

/// The summaries of the files written, in order, each file once: a frame
/// rendered again (it held a liar's tiles) replaced its first file.
fn last_of_each_file(written: Vec<Summary>) -> Vec<Summary> {
    let mut summaries: Vec<Summary> = Vec::with_capacity(written.len());
    for summary in written {
        match summaries.iter_mut().find(|s| s.out == summary.out) {
            Some(earlier) => *earlier = summary,
            None => summaries.push(summary),
        }
    }
    summaries
}

/// Logs what each worker of a session did, and the session's frames and time.
fn log_session(session: &farm::SessionReport, frames: usize) {
    for w in &session.workers {
        tracing::info!(
            "worker {}: {} units, {} pixels, render cpu {:.3} s{}",
            w.name,
            w.units,
            w.pixels,
            w.render_cpu_micros as f64 / 1e6,
            w.process_cpu_micros.map_or_else(String::new, |c| format!(
                ", process cpu {:.3} s",
                c as f64 / 1e6
            ))
        );
    }
    let n = session.workers.len();
    tracing::info!(
        "{} frame{} on {n} worker{} in {:.3} s; {} unit{} verified by a second rendering",
        frames,
        if frames == 1 { "" } else { "s" },
        if n == 1 { "" } else { "s" },
        session.render_time.as_secs_f64(),
        session.verified,
        if session.verified == 1 { "" } else { "s" },
    );
}

/// `coordinator eval`: the value of `expression` at `at` (see [`hypertexture::pse::surface::probe`]).
pub fn eval(
    expression: &str,
    scene: Option<&Path>,
    at: [f64; 3],
    frame: u32,
    knobs: &[(String, f64)],
) -> Result<String, CoordinatorError> {
    let desc = match scene {
        Some(path) => {
            let text = hypertexture::scene::read_text(path)?;
            Some(hypertexture::scene::parse(
                &text,
                &path.display().to_string(),
            )?)
        }
        None if !knobs.is_empty() => {
            return Err(CoordinatorError::Expression(
                "--set needs --scene (knobs are declared by a scene)".into(),
            ));
        }
        None => None,
    };
    let values = match &desc {
        Some(d) => hypertexture::scene::knob_values(d, knobs)?,
        None => Default::default(),
    };
    let x = glam::Vec3::new(at[0] as f32, at[1] as f32, at[2] as f32);
    hypertexture::pse::surface::probe(expression, desc.as_ref(), &values, x, frame)
        .map(|p| p.to_string())
        .map_err(|f| {
            CoordinatorError::Expression(format!("{}: {}", f.field, f.error.render(&f.source)))
        })
}

/// A pool of `threads` threads named `name-0`, `name-1`, ….
pub(crate) fn thread_pool(
    threads: usize,
    name: &'static str,
) -> Result<rayon::ThreadPool, CoordinatorError> {
    rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .thread_name(move |i| format!("{name}-{i}"))
        .build()
        .map_err(|e| CoordinatorError::Threads {
            threads,
            message: e.to_string(),
        })
}

/// Renders the whole frame on a pool of `threads` threads in this process.
pub fn render_in_process(
    scene: &Scene,
    frame: u32,
    threads: usize,
    progress: bool,
) -> Result<(Film, Duration), CoordinatorError> {
    let pool = thread_pool(threads, "render")?;
    let bar = if progress && std::io::stderr().is_terminal() {
        let bar = indicatif::ProgressBar::new(u64::from(scene.height()));
        bar.set_style(
            indicatif::ProgressStyle::with_template(
                "{spinner} [{elapsed_precise}] {bar:40} {pos}/{len} rows, eta {eta}",
            )
            .unwrap_or_else(|_| indicatif::ProgressStyle::default_bar()),
        );
        bar
    } else {
        indicatif::ProgressBar::hidden()
    };
    let start = Instant::now();
    let film = pool.install(|| hypertexture::render::render(scene, frame, &|rows| bar.inc(rows)));
    let elapsed = start.elapsed();
    bar.finish_and_clear();
    Ok((film, elapsed))
}
