//! The coordinator: loads a scene, renders it, writes the image.
//!
//! The binary (`main.rs`) only parses arguments and calls [`run`].

pub mod cli;
pub mod farm;
pub mod files;
pub mod guard;
pub mod logging;
pub mod pipeline;
pub mod service;

use std::io::IsTerminal;
use std::num::NonZeroUsize;
use std::path::PathBuf;
use std::time::{Duration, Instant};

use hypertexture::{Film, Overrides, Scene, SceneError};

/// Everything a render needs to know.
#[derive(Clone, Debug)]
pub struct Config {
    /// Scene file.
    pub scene: PathBuf,
    /// Output image (.png or .exr).
    pub out: PathBuf,
    /// Width override.
    pub width: Option<u32>,
    /// Height override.
    pub height: Option<u32>,
    /// Render threads (default: every core).
    pub threads: Option<NonZeroUsize>,
    /// Frame number.
    pub frame: u32,
    /// Samples per pixel (overrides the scene's).
    pub spp: Option<u32>,
    /// Marching step preset (default: the scene's step, i.e. high quality).
    pub quality: Option<hypertexture::Quality>,
    /// Render this inclusive range of frames as a numbered sequence instead.
    pub frames: Option<(u32, u32)>,
    /// Knob overrides (`--set name=value`).
    pub knobs: Vec<(String, f64)>,
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
    /// A configuration rendering `scene` to `out` with every default.
    pub fn new(scene: impl Into<PathBuf>, out: impl Into<PathBuf>) -> Config {
        Config {
            scene: scene.into(),
            out: out.into(),
            width: None,
            height: None,
            threads: None,
            frame: 0,
            spp: None,
            quality: None,
            frames: None,
            knobs: Vec::new(),
            progress: false,
            farm: None,
        }
    }
}

/// Why a render failed.
#[derive(Debug, thiserror::Error)]
pub enum CoordinatorError {
    /// The scene could not be loaded.
    #[error(transparent)]
    Scene(#[from] SceneError),
    /// The image could not be written.
    #[error(transparent)]
    Output(#[from] crate::pipeline::output::OutputError),
    /// The farm failed.
    #[error(transparent)]
    Farm(#[from] farm::FarmError),
    /// A file named on the command line cannot be used.
    #[error(transparent)]
    File(#[from] files::FileError),
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
    /// The service failed.
    #[error(transparent)]
    Service(Box<service::ServiceError>),
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
pub fn frame_path(out: &std::path::Path, frame: u32) -> PathBuf {
    let stem = out
        .file_stem()
        .map_or_else(|| "frame".into(), |s| s.to_string_lossy().into_owned());
    let ext = out
        .extension()
        .map_or_else(String::new, |e| format!(".{}", e.to_string_lossy()));
    out.with_file_name(format!("{stem}_{frame:04}{ext}"))
}

/// Renders every frame of `config.frames` (or the single `config.frame`) and writes
/// each image; a sequence goes to numbered files beside `config.out`. On the
/// farm a sequence is one session: the server and workers stay up from the
/// first frame to the last, and each image is written as soon as it is complete.
pub fn run_all(config: Config) -> Result<Vec<Summary>, CoordinatorError> {
    // Fail on a bad output name before spending any time rendering.
    crate::pipeline::output::ImageFormat::from_path(&config.out)?;
    // A sequence's files go beside `config.out`: one directory to check.
    files::check_writable(&config.out)?;
    let (scene_text, scene_name, config) = scene_of(config)?;
    let frames: Vec<farm::FrameOut> = match config.frames {
        None => vec![farm::FrameOut {
            frame: config.frame,
            out: config.out.clone(),
        }],
        Some((first, last)) => (first..=last)
            .map(|frame| farm::FrameOut {
                frame,
                out: frame_path(&config.out, frame),
            })
            .collect(),
    };
    let overrides = Overrides {
        width: config.width,
        height: config.height,
        spp: config.spp,
        quality: config.quality,
        knobs: config.knobs.clone(),
    };
    let scene = Scene::from_text(&scene_text, &scene_name, overrides.clone())?;
    let metadata =
        crate::pipeline::output::ImageMetadata::new(&scene, &scene_name, &scene_text, &overrides);
    let Some(options) = &config.farm else {
        let threads = config.threads.map_or_else(
            || std::thread::available_parallelism().map_or(1, NonZeroUsize::get),
            NonZeroUsize::get,
        );
        let how = format!("{threads} thread{}", if threads == 1 { "" } else { "s" });
        return frames
            .into_iter()
            .map(|f| {
                let (film, time) = render_in_process(&scene, f.frame, threads, config.progress)?;
                let image = crate::farm::canvas::FrameImage::Film(film);
                let meta = metadata.at_frame(f.frame);
                write_frame(&config, &scene, &image, &meta, time, &f.out, &how)
            })
            .collect();
    };
    render_on_farm(&config, options, &scene, metadata, frames)
}

/// The scene text and name `config` renders, and the configuration with the
/// settings an image stores: a scene file is read as it is; a PNG or EXR written
/// by the coordinator gives the scene it stores, its name, and its size, frame,
/// samples, quality and knobs, so that the render comes out the same again.
fn scene_of(config: Config) -> Result<(String, String, Config), CoordinatorError> {
    if crate::pipeline::output::ImageFormat::from_path(&config.scene).is_err() {
        let text = hypertexture::scene::read_text(&config.scene)?;
        let name = config.scene.display().to_string();
        return Ok((text, name, config));
    }
    let stored = crate::pipeline::output::read_stored_render(&config.scene)?;
    tracing::info!(
        "{}: the scene {} stored in the image",
        config.scene.display(),
        stored.scene_name
    );
    let o = stored.options;
    let config = Config {
        width: config.width.or(Some(stored.width)),
        height: config.height.or(Some(stored.height)),
        frame: if config.frames.is_some() || config.frame != 0 {
            config.frame
        } else {
            stored.frame
        },
        spp: config.spp.or(o.spp),
        quality: config.quality.or(o.quality),
        knobs: o.knobs.into_iter().chain(config.knobs).collect(),
        ..config
    };
    Ok((stored.scene_text, stored.scene_name, config))
}

/// Renders the one frame `config.frame` (see [`run_all`]).
pub fn run(config: Config) -> Result<Summary, CoordinatorError> {
    let mut summaries = run_all(Config {
        frames: None,
        ..config
    })?;
    Ok(summaries.remove(0))
}

/// Writes a frame's image and says so.
fn write_frame(
    config: &Config,
    scene: &Scene,
    image: &crate::farm::canvas::FrameImage,
    meta: &crate::pipeline::output::ImageMetadata,
    render_time: Duration,
    out: &std::path::Path,
    how: &str,
) -> Result<Summary, CoordinatorError> {
    crate::pipeline::output::write_frame_image(image, out, meta)?;
    let frame = meta.frame;
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

/// Renders `frames` on the farm as one session (starting local workers as
/// configured), writing each image, on a thread of its own, as soon as its
/// frame is complete.
pub fn render_on_farm(
    config: &Config,
    options: &FarmOptions,
    scene: &Scene,
    metadata: crate::pipeline::output::ImageMetadata,
    frames: Vec<farm::FrameOut>,
) -> Result<Vec<Summary>, CoordinatorError> {
    let metadata = std::sync::Arc::new(metadata);
    let job = farm::FrameJob {
        scene_text: metadata.scene_text.clone(),
        scene_name: metadata.scene_name.clone(),
        width: scene.width(),
        height: scene.height(),
        spp: config.spp,
        quality: config.quality,
        knobs: config.knobs.clone(),
        pixel_format: crate::pipeline::output::pixel_format_for(
            frames.iter().map(|f| f.out.as_path()),
        ),
        frames,
        metadata: metadata.clone(),
        bake: None,
        assets: farm::Asset::of_scene(scene, &metadata.scene_name)
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
    let session = std::thread::scope(|scope| {
        let writer = scope.spawn(move || {
            finished
                .into_iter()
                .map(|done| {
                    let f = done.frame;
                    write_frame(
                        config,
                        scene,
                        &f.image,
                        &metadata.at_frame(f.frame),
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
    });
    let (session, written) = session?;
    // A frame rendered again (it held a liar's tiles) replaced its first file.
    let mut summaries: Vec<Summary> = Vec::with_capacity(written.len());
    for summary in written {
        match summaries.iter_mut().find(|s| s.out == summary.out) {
            Some(earlier) => *earlier = summary,
            None => summaries.push(summary),
        }
    }
    let written = summaries;
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
        "{} frame{} on {n} worker{} in {:.3} s",
        written.len(),
        if written.len() == 1 { "" } else { "s" },
        if n == 1 { "" } else { "s" },
        session.render_time.as_secs_f64()
    );
    Ok(written)
}

/// `coordinator eval`: the value of `expression` at `at` (see [`hypertexture::pse::surface::probe`]).
pub fn eval(
    expression: &str,
    scene: Option<&std::path::Path>,
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
