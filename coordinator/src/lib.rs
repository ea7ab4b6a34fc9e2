//! The coordinator: loads a scene, renders it, writes the image.
//!
//! The binary (`main.rs`) only parses arguments and calls [`run`].

pub mod cli;
pub mod logging;
pub mod output;

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
    /// Show a progress bar when stderr is a terminal.
    pub progress: bool,
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
            progress: false,
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
    Output(#[from] output::OutputError),
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

/// Loads the scene, renders it in-process and writes the image.
pub fn run(config: Config) -> Result<Summary, CoordinatorError> {
    // Fail on a bad output name before spending any time rendering.
    output::ImageFormat::from_path(&config.out)?;
    let scene = Scene::load(
        &config.scene,
        Overrides {
            width: config.width,
            height: config.height,
        },
    )?;
    let threads = config.threads.map_or_else(
        || std::thread::available_parallelism().map_or(1, NonZeroUsize::get),
        NonZeroUsize::get,
    );
    let (film, render_time) = render_in_process(&scene, config.frame, threads, config.progress)?;
    output::write_image(&film, &config.out)?;
    tracing::info!(
        "rendered {} ({}×{}, frame {}) with {threads} thread{} in {:.3} s → {}",
        config.scene.display(),
        scene.width(),
        scene.height(),
        config.frame,
        if threads == 1 { "" } else { "s" },
        render_time.as_secs_f64(),
        config.out.display()
    );
    Ok(Summary {
        render_time,
        out: config.out,
    })
}

/// Renders the whole frame on a pool of `threads` threads in this process.
pub fn render_in_process(
    scene: &Scene,
    frame: u32,
    threads: usize,
    progress: bool,
) -> Result<(Film, Duration), CoordinatorError> {
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .thread_name(|i| format!("render-{i}"))
        .build()
        .map_err(|e| CoordinatorError::Threads {
            threads,
            message: e.to_string(),
        })?;
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
