//! Command-line arguments, converted into a library [`Config`].

use std::num::NonZeroUsize;
use std::path::PathBuf;

use clap::Parser;

use crate::Config;

/// Render a hypertexture scene to PNG or OpenEXR.
#[derive(Debug, Parser)]
#[command(version, about, long_about = None)]
pub struct Cli {
    /// Scene file (RON), e.g. scenes/fur.ron.
    #[arg(long, value_name = "FILE")]
    pub scene: PathBuf,
    /// Output image; the extension chooses the format (.png or .exr).
    /// Default: the scene's name with .png, in the current directory.
    #[arg(long, value_name = "FILE")]
    pub out: Option<PathBuf>,
    /// Image width in pixels (overrides the scene's).
    #[arg(long, value_name = "PIXELS", value_parser = clap::value_parser!(u32).range(1..=16384))]
    pub width: Option<u32>,
    /// Image height in pixels (overrides the scene's).
    #[arg(long, value_name = "PIXELS", value_parser = clap::value_parser!(u32).range(1..=16384))]
    pub height: Option<u32>,
    /// Render in this process with a thread pool, without the farm.
    #[arg(long)]
    pub in_process: bool,
    /// Threads to render with (default: every core). 1 is the serial baseline.
    #[arg(long, value_name = "N")]
    pub threads: Option<NonZeroUsize>,
    /// Frame number (animated scenes drift their noise by frame · flow).
    #[arg(long, value_name = "F", default_value_t = 0)]
    pub frame: u32,
    /// No progress bar and no log lines; errors are still printed.
    #[arg(long, short)]
    pub quiet: bool,
}

impl Cli {
    /// The library configuration these arguments ask for.
    pub fn into_config(self) -> Config {
        let out = self.out.unwrap_or_else(|| {
            let stem = self
                .scene
                .file_stem()
                .map_or_else(|| "render".into(), |s| s.to_os_string());
            PathBuf::from(stem).with_extension("png")
        });
        Config {
            scene: self.scene,
            out,
            width: self.width,
            height: self.height,
            threads: self.threads,
            frame: self.frame,
            progress: !self.quiet,
        }
    }
}
