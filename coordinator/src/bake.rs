//! `coordinator bake`: samples a scene's hypertexture H(x) on a voxel lattice
//! over the box where it can be non-zero and writes it as an OpenVDB file
//! ([`crate::vdb`]): a `density` grid (fog volume) and a `color` grid (the
//! unlit colour of each sample, as the marcher colours it), holding only the
//! 8³ leaves with a non-zero density.
//!
//! The lattice is cut into slabs, one layer of leaves along x each, which the
//! render threads bake independently; each voxel is a pure function of
//! (scene, frame, voxel), so the file is the same for any number of threads.

use std::num::NonZeroUsize;
use std::path::PathBuf;
use std::time::{Duration, Instant};

use glam::Vec3;
use hypertexture::{Overrides, Scene};
use rayon::prelude::*;

use crate::CoordinatorError;
use crate::vdb::{self, AnyGrid, Grid, LEAF_DIM, Leaf, Meta, Transform};

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
}

/// The voxel lattice of a bake: voxel (i, j, k) is centred at
/// `origin + voxel · (i, j, k)`, for `0 ≤ (i, j, k) < dims`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Lattice {
    /// The centre of voxel (0, 0, 0).
    pub origin: Vec3,
    /// The edge of a voxel.
    pub voxel: f32,
    /// Voxels along each axis.
    pub dims: [u32; 3],
}

impl Lattice {
    /// The lattice of `resolution` voxels along the longest edge of the box
    /// where the scene's density can be non-zero at `frame`.
    pub fn of(scene: &Scene, frame: u32, resolution: u32) -> Lattice {
        let (lo, hi) = scene.density_box(frame);
        let extent = (hi - lo).max(Vec3::ZERO);
        let longest = extent.max_element().max(f32::MIN_POSITIVE);
        let voxel = longest / resolution.max(1) as f32;
        let along = |e: f32| ((e / voxel).ceil() as u32).clamp(1, resolution.max(1));
        Lattice {
            origin: lo + Vec3::splat(0.5 * voxel),
            voxel,
            dims: [along(extent.x), along(extent.y), along(extent.z)],
        }
    }

    /// The world position of voxel (i, j, k): `origin + voxel · ijk` in
    /// double precision rounded once to f32, which is what a reader that
    /// applies the file's transform (in double) and rounds gets.
    pub fn point(&self, ijk: [u32; 3]) -> Vec3 {
        let axis = |o: f32, i: u32| (f64::from(o) + f64::from(i) * f64::from(self.voxel)) as f32;
        Vec3::new(
            axis(self.origin.x, ijk[0]),
            axis(self.origin.y, ijk[1]),
            axis(self.origin.z, ijk[2]),
        )
    }

    /// The number of slabs: layers of leaves along x.
    pub fn slabs(&self) -> u32 {
        self.dims[0].div_ceil(LEAF_DIM as u32)
    }

    /// The file's index-to-world map.
    pub fn transform(&self) -> Transform {
        Transform {
            voxel_size: f64::from(self.voxel),
            translation: self.origin.to_array().map(f64::from),
        }
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
                        let p = lattice.point([x, y, z]);
                        let f = scene.density_at(p, frame);
                        if f != 0.0 {
                            let n = (((x - x0) * d + (y - y0)) * d + (z - z0)) as usize;
                            density.set(n, f);
                            colour.set(n, scene.colour_at(p, f, frame).to_array());
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

/// Bakes every slab of `lattice` on the current rayon pool, in slab order.
pub fn bake(scene: &Scene, lattice: &Lattice, frame: u32) -> Leaves {
    let slabs: Vec<Leaves> = (0..lattice.slabs())
        .into_par_iter()
        .map(|s| bake_slab(scene, lattice, frame, s))
        .collect();
    let mut all = Leaves::default();
    for s in slabs {
        all.density.extend(s.density);
        all.colour.extend(s.colour);
    }
    all
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
    vdb::encode(&meta, &lattice.transform(), &grids)
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

/// `coordinator bake`: bakes each frame and writes its file.
pub fn run(config: &BakeConfig) -> Result<Vec<BakeSummary>, CoordinatorError> {
    let frames: Vec<u32> = match config.frames {
        Some((a, b)) => (a..=b).collect(),
        None => vec![config.frame],
    };
    if frames.len() > 1 && !config.out.contains('#') {
        return Err(CoordinatorError::Bake(format!(
            "--out {:?}: {} frames need a # in the name (e.g. fur.####.vdb)",
            config.out,
            frames.len()
        )));
    }
    if !(2..=MAX_RESOLUTION).contains(&config.resolution) {
        return Err(CoordinatorError::Bake(format!(
            "--resolution {}: expected 2 to {MAX_RESOLUTION} voxels along the longest edge",
            config.resolution
        )));
    }
    let first = PathBuf::from(crate::service::expand_pattern(&config.out, frames[0]));
    crate::files::check_writable(&first)?;
    let text = hypertexture::scene::read_text(&config.scene)?;
    let name = config.scene.display().to_string();
    let overrides = Overrides {
        knobs: config.knobs.clone(),
        ..Overrides::default()
    };
    let scene = Scene::from_text(&text, &name, overrides)?;
    let threads = config.threads.map_or_else(
        || std::thread::available_parallelism().map_or(1, NonZeroUsize::get),
        NonZeroUsize::get,
    );
    let pool = crate::thread_pool(threads, "bake")?;
    frames
        .into_iter()
        .map(|frame| {
            let out = PathBuf::from(crate::service::expand_pattern(&config.out, frame));
            let lattice = Lattice::of(&scene, frame, config.resolution);
            let start = Instant::now();
            let leaves = pool.install(|| bake(&scene, &lattice, frame));
            let bake_time = start.elapsed();
            let active_voxels = leaves.density.iter().map(Leaf::active).sum();
            let count = leaves.density.len();
            let bytes = encode(&name, frame, &lattice, leaves);
            crate::output::write_atomically(&out, &bytes)?;
            let [nx, ny, nz] = lattice.dims;
            tracing::info!(
                "baked {name} (frame {frame}, {nx}×{ny}×{nz} voxels of {}) with {threads} thread{} in {:.3} s: {count} leaves, {active_voxels} active voxels, {} bytes → {}",
                lattice.voxel,
                if threads == 1 { "" } else { "s" },
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

#[cfg(test)]
mod tests {
    use super::*;

    const SCENE: &str = include_str!("../../scenes/noisy_sphere.ron");

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
