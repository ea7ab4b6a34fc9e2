//! `coordinator bake`: samples a scene's hypertexture H(x) on a voxel lattice
//! over the box where it can be non-zero and writes it as an OpenVDB file
//! ([`crate::pipeline::vdb`]): a `density` grid (fog volume) and a `color` grid (the
//! unlit colour of each sample, as the marcher colours it), holding only the
//! 8³ leaves with a non-zero density.
//!
//! The lattice is cut into slabs, one layer of leaves along x each, which the
//! render threads bake independently; each voxel is a pure function of
//! (scene, frame, voxel), so the file is the same for any number of threads.

use std::num::NonZeroUsize;
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

pub use hypertexture::render::bake::Lattice;
use hypertexture::{Film, Overrides, RenderRequest, Scene};
use rayon::prelude::*;

use crate::CoordinatorError;
use crate::pipeline::vdb::{self, AnyGrid, Grid, LEAF_DIM, Leaf, Meta, Transform};

/// The largest `--resolution` (voxels along the box's longest edge).
pub const MAX_RESOLUTION: u32 = 512;

/// What `coordinator bake` is asked to do.
#[derive(Clone, Debug)]
pub struct BakeConfig {
    /// The scene file.
    pub scene: PathBuf,
    /// The output file; each run of `#` is the frame number padded to the
    /// run's length (`fur.####.vdb`).
    pub out: String,
    /// Voxels along the longest edge of the box.
    pub resolution: u32,
    /// The frame of a single bake.
    pub frame: u32,
    /// Bake this inclusive range of frames, one file each, instead.
    pub frames: Option<(u32, u32)>,
    /// Threads (default: every core).
    pub threads: Option<NonZeroUsize>,
    /// Knob overrides (`--set name=value`).
    pub knobs: Vec<(String, f64)>,
    /// Bake on the farm with these options; `None`: in-process.
    pub farm: Option<crate::pipeline::run::FarmOptions>,
}

/// The number of slabs of a lattice: layers of leaves along x.
pub fn slabs(lattice: &Lattice) -> u32 {
    lattice.dims[0].div_ceil(LEAF_DIM as u32)
}

/// The file's index-to-world map of a lattice.
pub fn transform(lattice: &Lattice) -> Transform {
    Transform {
        voxel_size: f64::from(lattice.voxel),
        translation: lattice.origin.to_array().map(f64::from),
    }
}

/// The leaves of one slab, or of a whole bake: `density[n]` and `colour[n]`
/// share an origin and their active voxels.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Leaves {
    /// H(x) at each active voxel (those where it is not 0).
    pub density: Vec<Leaf<f32>>,
    /// The unlit colour there.
    pub colour: Vec<Leaf<[f32; 3]>>,
}

/// Bakes slab `slab` (leaves with x origin `8 · slab`) of `lattice` at
/// `frame`: every leaf holding a voxel of non-zero density, in (y, z) order.
pub fn bake_slab(scene: &Scene, lattice: &Lattice, frame: u32, slab: u32) -> Leaves {
    slab_leaves(lattice, slab, |ijk| {
        hypertexture::render::bake::voxel(scene, lattice, frame, ijk)
    })
}

/// The leaves of slab `slab` of `lattice` with each voxel's (density,
/// colour) from `value`: every leaf holding a voxel of non-zero density, in
/// (y, z) order.
fn slab_leaves(
    lattice: &Lattice,
    slab: u32,
    value: impl Fn([u32; 3]) -> (f32, [f32; 3]),
) -> Leaves {
    let d = LEAF_DIM as u32;
    let [nx, ny, nz] = lattice.dims;
    let mut out = Leaves::default();
    let x0 = slab * d;
    for y0 in (0..ny).step_by(d as usize) {
        for z0 in (0..nz).step_by(d as usize) {
            let origin = [x0, y0, z0].map(|c| c as i32);
            let mut density = Leaf::empty(origin);
            let mut colour = Leaf::empty(origin);
            for x in x0..(x0 + d).min(nx) {
                for y in y0..(y0 + d).min(ny) {
                    for z in z0..(z0 + d).min(nz) {
                        let (f, c) = value([x, y, z]);
                        if f != 0.0 {
                            let n = (((x - x0) * d + (y - y0)) * d + (z - z0)) as usize;
                            density.set(n, f);
                            colour.set(n, c);
                        }
                    }
                }
            }
            if density.active() > 0 {
                out.density.push(density);
                out.colour.push(colour);
            }
        }
    }
    out
}

/// Every slab of `lattice` on the current rayon pool, in slab order.
fn all_slabs(lattice: &Lattice, slab: impl Fn(u32) -> Leaves + Send + Sync) -> Leaves {
    let slabs: Vec<Leaves> = (0..slabs(lattice)).into_par_iter().map(slab).collect();
    let mut all = Leaves::default();
    for s in slabs {
        all.density.extend(s.density);
        all.colour.extend(s.colour);
    }
    all
}

/// Bakes every slab of `lattice` on the current rayon pool, in slab order.
pub fn bake(scene: &Scene, lattice: &Lattice, frame: u32) -> Leaves {
    all_slabs(lattice, |s| bake_slab(scene, lattice, frame, s))
}

/// The leaves of a bake the farm sampled: `film` is the lattice laid out as
/// an image ([`hypertexture::render::bake::Lattice::image_size`]), each pixel's
/// sample its voxel's value ([`hypertexture::render::bake::to_sample`]). The same
/// leaves as [`bake`] gives when the workers' arithmetic is the same.
pub fn leaves_of_film(lattice: &Lattice, film: &Film) -> Leaves {
    let pixels = film.pixels();
    all_slabs(lattice, |s| {
        slab_leaves(lattice, s, |ijk| {
            hypertexture::render::bake::from_sample(&pixels[lattice.index(ijk) as usize])
        })
    })
}

/// The OpenVDB file of a bake.
pub fn encode(scene_name: &str, frame: u32, lattice: &Lattice, leaves: Leaves) -> Vec<u8> {
    let meta = [
        (
            "creator",
            Meta::String(format!("hypertexture {}", env!("CARGO_PKG_VERSION"))),
        ),
        ("scene", Meta::String(scene_name.to_string())),
        ("frame", Meta::Int64(i64::from(frame))),
    ];
    let grids = [
        AnyGrid::Float(Grid {
            name: "density".into(),
            class: "fog volume",
            leaves: leaves.density,
        }),
        AnyGrid::Vec3(Grid {
            name: "color".into(),
            class: "unknown",
            leaves: leaves.colour,
        }),
    ];
    vdb::encode(&meta, &transform(lattice), &grids)
}

/// What one baked frame reports.
#[derive(Clone, Debug)]
pub struct BakeSummary {
    /// Where the file went.
    pub out: PathBuf,
    /// Wall time of the sampling (not loading, not writing).
    pub bake_time: Duration,
    /// Leaves written per grid.
    pub leaves: usize,
    /// Voxels of non-zero density.
    pub active_voxels: u64,
    /// The file's size in bytes.
    pub bytes: usize,
}

/// `coordinator bake`: bakes each frame and writes its file, on the farm
/// (one session a frame: each frame's lattice is its own image) or on a
/// thread pool in this process. Both write the same bytes.
pub fn run(config: &BakeConfig) -> Result<Vec<BakeSummary>, CoordinatorError> {
    let frames: Vec<u32> = match config.frames {
        Some((a, b)) => (a..=b).collect(),
        None => vec![config.frame],
    };
    let range = hypertexture::FrameRange::new(frames[0], frames[frames.len() - 1]);
    crate::pipeline::destination::check_pattern(&config.out, range, Path::new(""))
        .map_err(|e| CoordinatorError::Bake(format!("--{e}")))?;
    if !(2..=MAX_RESOLUTION).contains(&config.resolution) {
        return Err(CoordinatorError::Bake(format!(
            "--resolution {}: expected 2 to {MAX_RESOLUTION} voxels along the longest edge",
            config.resolution
        )));
    }
    let first = PathBuf::from(crate::pipeline::destination::expand_pattern(
        &config.out,
        frames[0],
    ));
    crate::files::check_writable(&first)?;
    let name = config.scene.display().to_string();
    let request = RenderRequest {
        overrides: Overrides {
            knobs: Overrides::knob_list(config.knobs.iter().cloned()),
            ..Overrides::default()
        },
        ..RenderRequest::new(hypertexture::scene::read_text(&config.scene)?, &name)
    };
    let scene = request.build(None)?;
    let pool = match &config.farm {
        Some(_) => None,
        None => {
            let threads = config.threads.map_or_else(
                || std::thread::available_parallelism().map_or(1, NonZeroUsize::get),
                NonZeroUsize::get,
            );
            Some((crate::pipeline::run::thread_pool(threads, "bake")?, threads))
        }
    };
    // The farm's leaves are put together from the frame on the pool of this
    // process (the render threads of its local workers have finished).
    let assemble = crate::pipeline::run::thread_pool(
        std::thread::available_parallelism().map_or(1, NonZeroUsize::get),
        "leaves",
    )?;
    frames
        .into_iter()
        .map(|frame| {
            let out = PathBuf::from(crate::pipeline::destination::expand_pattern(&config.out, frame));
            let lattice = Lattice::of(&scene, frame, config.resolution);
            let (leaves, bake_time, how) = match (&pool, &config.farm) {
                (Some((pool, threads)), _) => {
                    let start = Instant::now();
                    let leaves = pool.install(|| bake(&scene, &lattice, frame));
                    let how = format!("{threads} thread{}", if *threads == 1 { "" } else { "s" });
                    (leaves, start.elapsed(), how)
                }
                (None, Some(options)) => {
                    let (film, time) =
                        bake_on_farm(config, options, &scene, &request, &lattice, frame)?;
                    let leaves = assemble.install(|| leaves_of_film(&lattice, &film));
                    (leaves, time, "the farm".to_string())
                }
                (None, None) => unreachable!("a pool is made when there is no farm"),
            };
            let active_voxels = leaves.density.iter().map(Leaf::active).sum();
            let count = leaves.density.len();
            let bytes = encode(&name, frame, &lattice, leaves);
            crate::image::output::write_atomically(&out, &bytes)?;
            let [nx, ny, nz] = lattice.dims;
            tracing::info!(
                "baked {name} (frame {frame}, {nx}×{ny}×{nz} voxels of {}) with {how} in {:.3} s: {count} leaves, {active_voxels} active voxels, {} bytes → {}",
                lattice.voxel,
                bake_time.as_secs_f64(),
                bytes.len(),
                out.display()
            );
            Ok(BakeSummary {
                out,
                bake_time,
                leaves: count,
                active_voxels,
                bytes: bytes.len(),
            })
        })
        .collect()
}

/// Samples `lattice` at `frame` on the farm (one session, starting local
/// workers as configured): the lattice laid out as an image
/// ([`hypertexture::render::bake`]), each pixel its voxel's value. Returns the image
/// and the time from the first unit handed out to the last tile.
fn bake_on_farm(
    config: &BakeConfig,
    options: &crate::pipeline::run::FarmOptions,
    scene: &Scene,
    request: &RenderRequest,
    lattice: &Lattice,
    frame: u32,
) -> Result<(Film, Duration), CoordinatorError> {
    let [nx, ny, nz] = lattice.dims;
    let (width, height) = lattice.image_size().ok_or_else(|| {
        CoordinatorError::Bake(format!(
            "--resolution {}: the farm bakes at most {} voxels and this lattice has {nx}×{ny}×{nz}; lower --resolution or bake with --in-process",
            config.resolution,
            hypertexture::desc::MAX_PIXELS
        ))
    })?;
    let job = crate::farm::FrameJob {
        request: RenderRequest {
            overrides: Overrides {
                width: Some(width),
                height: Some(height),
                ..request.overrides.clone()
            },
            frames: hypertexture::FrameRange::one(frame),
            pixel_format: hypertexture::PixelFormat::Samples,
            bake: Some(*lattice),
            ..request.clone()
        },
        frames: vec![crate::farm::FrameOut {
            frame,
            out: PathBuf::new(),
        }],
        metadata: std::sync::Arc::new(crate::image::output::ImageMetadata::new(scene, request)),
        assets: crate::farm::Asset::of_scene(scene, &request.scene_name)
            .map_err(CoordinatorError::Asset)?,
    };
    let farm_config = options.farm_config(config.threads, false)?;
    let runtime = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .map_err(CoordinatorError::Runtime)?;
    let mut done = None;
    let session = runtime.block_on(crate::farm::render_frames(
        job,
        farm_config,
        &mut |f| {
            done = Some(f.frame);
            Ok(())
        },
        worker::shutdown_signal(),
    ))?;
    for w in &session.workers {
        tracing::info!(
            "worker {}: {} units, {} voxels, render cpu {:.3} s",
            w.name,
            w.units,
            w.pixels,
            w.render_cpu_micros as f64 / 1e6
        );
    }
    let frame = done.ok_or_else(|| {
        CoordinatorError::Bake("the farm finished without the bake's frame".into())
    })?;
    match frame.image {
        crate::image::canvas::FrameImage::Film(film) => Ok((film, frame.render_time)),
        crate::image::canvas::FrameImage::Srgb8 { .. } => Err(CoordinatorError::Bake(
            "the farm returned 8-bit colour for a bake".into(),
        )),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::Vec3;

    const SCENE: &str = include_str!("../../../scenes/noisy_sphere.ron");

    #[test]
    fn a_bake_is_the_same_on_one_thread_and_many() {
        let scene = Scene::from_text(SCENE, "noisy_sphere.ron", Overrides::default())
            .expect("the repository's scene builds");
        let lattice = Lattice::of(&scene, 0, 20);
        let one = rayon::ThreadPoolBuilder::new()
            .num_threads(1)
            .build()
            .expect("a pool of one thread")
            .install(|| bake(&scene, &lattice, 0));
        let many = rayon::ThreadPoolBuilder::new()
            .num_threads(3)
            .build()
            .expect("a pool of three threads")
            .install(|| bake(&scene, &lattice, 0));
        assert_eq!(one, many);
        assert!(!one.density.is_empty());
        // Every active voxel holds the library's density at its point.
        for leaf in &one.density {
            for n in 0..vdb::LEAF_VOXELS {
                let local = [n / 64, n / 8 % 8, n % 8];
                let ijk = [0, 1, 2].map(|a| leaf.origin[a] as u32 + local[a] as u32);
                let active = leaf.mask[n / 64] >> (n % 64) & 1 == 1;
                if active {
                    let p = lattice.point(ijk);
                    assert_eq!(leaf.values[n], scene.density_at(p, 0));
                }
            }
        }
    }

    #[test]
    fn the_lattice_covers_the_box_along_its_longest_edge() {
        let scene = Scene::from_text(SCENE, "noisy_sphere.ron", Overrides::default())
            .expect("the repository's scene builds");
        let lattice = Lattice::of(&scene, 0, 32);
        let (lo, hi) = scene.density_box(0);
        assert_eq!(lattice.dims.iter().max(), Some(&32));
        let last = lattice.point(lattice.dims.map(|d| d - 1));
        assert!(
            (last + Vec3::splat(0.5 * lattice.voxel) - hi)
                .abs()
                .max_element()
                < lattice.voxel
        );
        assert!(
            (lattice.origin - Vec3::splat(0.5 * lattice.voxel) - lo)
                .abs()
                .max_element()
                < 1e-6
        );
    }
}
