//! A mesh's signed distance sampled once on a sparse narrow-band grid, so a
//! soft object on a mesh costs a grid lookup per sample instead of a
//! closest-triangle search.
//!
//! Space is cut into bricks of 8³ cells (OpenVDB's leaves). A coarse dense
//! grid of brick slots covers the mesh's box grown by the band's outer reach;
//! a slot holds a brick where the surface's band (signed distance in
//! `(-inner, outer)`, with a margin) may reach it, and otherwise says whether
//! the whole slot lies inside the mesh or outside the band. A brick holds 9³
//! samples (its 8³ cells' corners, the last layer shared with its
//! neighbours), each the exact signed distance and closest surface point
//! ([`super::Mesh::closest`]) at a lattice point, so a cell is read from one
//! brick. Between samples the distance and the closest point are trilinear.
//!
//! Every sample is a pure function of its lattice point, computed brick by
//! brick on every core and assembled in brick order: the same bits for any
//! number of threads. Fields are shared process-wide by their [`BandKey`]
//! ([`Band::shared`]), so every scene built in one process from the same mesh
//! and resolution reads one field.

use std::collections::BTreeMap;
use std::sync::{Arc, Mutex, Weak};

use glam::Vec3;

use super::Mesh;

/// Cells along a brick's edge.
const BRICK: usize = 8;
/// Samples along a brick's edge (its cells' corners).
const SIDE: usize = BRICK + 1;
/// Samples per brick.
const SAMPLES: usize = SIDE * SIDE * SIDE;
/// A slot wholly outside the band, away from the mesh.
const OUTSIDE: u32 = u32::MAX;
/// A slot wholly inside the mesh.
const INSIDE: u32 = u32::MAX - 1;

/// The largest field built unless the scene allows more.
pub const DEFAULT_MAX_FIELD_BYTES: u64 = 1 << 30;

/// What a field is built from, besides the mesh: lengths in the mesh's own
/// coordinates.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct BandSpec {
    /// The cell's edge.
    pub voxel: f32,
    /// How far outside the surface the samples reach (the soft region).
    pub outer: f32,
    /// How far inside the surface the samples reach.
    pub inner: f32,
    /// The most bytes the field may take.
    pub max_bytes: u64,
}

/// A field's identity: the mesh's content hash and the grid's lengths.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub struct BandKey {
    /// [`Mesh::hash`].
    pub mesh: u64,
    /// The bits of the voxel size, the outer and the inner reach.
    pub lengths: [u32; 3],
}

/// The field at a point.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Sample {
    /// Outside the band, away from the mesh: farther than the outer reach.
    Outside,
    /// Inside the mesh, deeper than the inner reach.
    Inside,
    /// In the band: the interpolated signed distance (negative inside) and
    /// closest surface point.
    Near {
        /// Signed distance.
        distance: f32,
        /// Closest surface point.
        point: Vec3,
    },
}

/// A mesh's sparse narrow-band distance field (see the module's doc).
pub struct Band {
    key: BandKey,
    /// The lattice point (0, 0, 0).
    origin: Vec3,
    /// `1 / voxel`.
    inv_voxel: f32,
    /// Slots along x, y, z.
    dims: [usize; 3],
    /// Per slot (x fastest): a brick's index, [`INSIDE`] or [`OUTSIDE`].
    slots: Vec<u32>,
    /// Per brick, [`SAMPLES`] samples (x fastest): distance and closest point.
    samples: Vec<[f32; 4]>,
}

impl std::fmt::Debug for Band {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Band")
            .field("key", &self.key)
            .field("dims", &self.dims)
            .field("bricks", &self.bricks())
            .finish()
    }
}

/// Two fields are equal when their keys are.
impl PartialEq for Band {
    fn eq(&self, other: &Self) -> bool {
        self.key == other.key
    }
}

/// Calls `f(i)` for `i` in `0..n` on `threads` threads, the results in order.
fn par_map<T: Send>(threads: usize, n: usize, f: impl Fn(usize) -> T + Sync) -> Vec<T> {
    let threads = threads.min(n.max(1));
    if threads <= 1 {
        return (0..n).map(f).collect();
    }
    let chunk = n.div_ceil(threads);
    std::thread::scope(|scope| {
        let f = &f;
        let parts: Vec<_> = (0..threads)
            .map(|t| {
                scope.spawn(move || {
                    (t * chunk..n.min((t + 1) * chunk))
                        .map(f)
                        .collect::<Vec<T>>()
                })
            })
            .collect();
        parts
            .into_iter()
            .flat_map(|p| match p.join() {
                Ok(v) => v,
                Err(e) => std::panic::resume_unwind(e),
            })
            .collect::<Vec<T>>()
    })
}

impl Band {
    /// The field's identity for `mesh` and `spec`.
    pub fn key(mesh: &Mesh, spec: &BandSpec) -> BandKey {
        BandKey {
            mesh: mesh.hash(),
            lengths: [spec.voxel, spec.outer, spec.inner].map(f32::to_bits),
        }
    }

    /// The field of `mesh` for `spec`, built once per process and key and
    /// shared while anything holds it.
    pub fn shared(mesh: &Mesh, spec: &BandSpec) -> Result<Arc<Band>, String> {
        type Slot = Arc<Mutex<Weak<Band>>>;
        static CACHE: Mutex<BTreeMap<BandKey, Slot>> = Mutex::new(BTreeMap::new());
        let key = Band::key(mesh, spec);
        let slot = {
            let mut cache = CACHE.lock().unwrap_or_else(|e| e.into_inner());
            // Forget fields nobody holds or builds.
            cache.retain(|_, s| {
                Arc::strong_count(s) > 1 || s.try_lock().is_ok_and(|w| w.strong_count() > 0)
            });
            Arc::clone(cache.entry(key).or_default())
        };
        // One build per key; other keys build meanwhile.
        let mut held = slot.lock().unwrap_or_else(|e| e.into_inner());
        if let Some(band) = held.upgrade() {
            return Ok(band);
        }
        let band = Arc::new(Band::build(mesh, spec)?);
        *held = Arc::downgrade(&band);
        Ok(band)
    }

    /// Builds the field of `mesh` for `spec` with the exact queries on every
    /// core; the error says why not (the caller names the mesh).
    pub fn build(mesh: &Mesh, spec: &BandSpec) -> Result<Band, String> {
        let threads = std::thread::available_parallelism().map_or(1, |t| t.get());
        Band::build_on(mesh, spec, threads)
    }

    /// [`Band::build`] on `threads` threads (the same bits for any number).
    fn build_on(mesh: &Mesh, spec: &BandSpec, threads: usize) -> Result<Band, String> {
        let voxel = spec.voxel;
        if !(voxel.is_finite() && voxel > 0.0 && spec.outer >= 0.0 && spec.inner >= 0.0) {
            return Err(format!(
                "the distance field's voxel size {voxel} is not a positive length"
            ));
        }
        let grid = Grid::new(mesh, spec);
        let too_big = |bytes: f64| {
            format!(
                "the distance field would take {:.0} MiB, more than the {:.0} MiB allowed: give the mesh a larger voxel (`sdf: Field(voxel: Some(..))`), allow more (`max_mib`), or use `sdf: Exact`",
                bytes / 1048576.0,
                spec.max_bytes as f64 / 1048576.0
            )
        };
        let slot_bytes = grid.slot_count() * 4.0;
        if !slot_bytes.is_finite() || slot_bytes > spec.max_bytes as f64 {
            return Err(too_big(slot_bytes));
        }
        // A slot whose centre lies farther from the soft region than the
        // slot's half-diagonal holds no point of it: wholly inside or
        // outside. The others are bricks.
        let half = grid.side * 0.5 * 3f32.sqrt();
        let class: Vec<u32> = par_map(threads, grid.dims.iter().product(), |i| {
            let d = mesh
                .closest(grid.slot_origin(i) + Vec3::splat(grid.side * 0.5))
                .distance;
            if d.abs() - half <= grid.reach {
                0
            } else if d < 0.0 {
                INSIDE
            } else {
                OUTSIDE
            }
        });
        let brick_slot: Vec<usize> = (0..class.len()).filter(|&i| class[i] == 0).collect();
        let bytes = slot_bytes + (brick_slot.len() * SAMPLES * 16) as f64;
        if bytes > spec.max_bytes as f64 {
            return Err(too_big(bytes));
        }
        let mut slots = class;
        for (b, &i) in brick_slot.iter().enumerate() {
            slots[i] = b as u32;
        }
        let samples: Vec<Vec<[f32; 4]>> = par_map(threads, brick_slot.len(), |b| {
            grid.brick(mesh, brick_slot[b])
        });
        Ok(Band {
            key: Band::key(mesh, spec),
            origin: grid.origin,
            inv_voxel: 1.0 / voxel,
            dims: grid.dims,
            slots,
            samples: samples.concat(),
        })
    }

    /// The number of bricks.
    pub fn bricks(&self) -> usize {
        self.samples.len() / SAMPLES
    }

    /// The bytes the field holds.
    pub fn memory_bytes(&self) -> usize {
        std::mem::size_of::<Band>()
            + self.slots.capacity() * 4
            + self.samples.capacity() * std::mem::size_of::<[f32; 4]>()
    }

    /// The field's identity.
    pub fn band_key(&self) -> BandKey {
        self.key
    }

    /// The field at `p` (the mesh's coordinates): trilinear in a brick.
    #[inline]
    pub fn sample(&self, p: Vec3) -> Sample {
        let g = (p - self.origin) * self.inv_voxel;
        let [nx, ny, nz] = self.dims;
        let s = g * (1.0 / BRICK as f32);
        // NaN fails every comparison: outside.
        let above = s.x >= 0.0 && s.y >= 0.0 && s.z >= 0.0;
        if !(above && s.x < nx as f32 && s.y < ny as f32 && s.z < nz as f32) {
            return Sample::Outside;
        }
        let (sx, sy, sz) = (s.x as usize, s.y as usize, s.z as usize);
        let brick = self.slots[sx + nx * (sy + ny * sz)];
        match brick {
            OUTSIDE => return Sample::Outside,
            INSIDE => return Sample::Inside,
            _ => {}
        }
        let local = |g: f32, s: usize| {
            let l = g - (s * BRICK) as f32;
            let c = (l as usize).min(BRICK - 1);
            (c, (l - c as f32).clamp(0.0, 1.0))
        };
        let ((cx, tx), (cy, ty), (cz, tz)) = (local(g.x, sx), local(g.y, sy), local(g.z, sz));
        let base = brick as usize * SAMPLES + cx + SIDE * (cy + SIDE * cz);
        let v = |dx: usize, dy: usize, dz: usize| self.samples[base + dx + SIDE * (dy + SIDE * dz)];
        let r = trilinear(&self.samples[base..], [tx, ty, tz]).to_array();
        if !r[0].is_finite() {
            // A corner beyond the reach: the whole cell is on its side.
            let far = (0..8)
                .map(|k| v(k & 1, k >> 1 & 1, k >> 2)[0])
                .find(|d| d.is_infinite());
            return match far {
                Some(d) if d < 0.0 => Sample::Inside,
                _ => Sample::Outside,
            };
        }
        Sample::Near {
            distance: r[0],
            point: Vec3::new(r[1], r[2], r[3]),
        }
    }
}

mod lanes;
mod measure;

pub use lanes::SampleLanes;
pub use measure::{FieldError, displaced_icosphere_obj};

#[cfg(test)]
mod tests;

/// The samples of a cell, from its corner (0, 0, 0) at `cell[0]`, interpolated
/// at `t` within it: `a + (b − a)·t` along x, then y, then z, the four
/// values (distance and closest point) in one register.
#[inline(always)]
fn trilinear(cell: &[[f32; 4]], [tx, ty, tz]: [f32; 3]) -> glam::Vec4 {
    let v = |d: usize| glam::Vec4::from_array(cell[d]);
    let lerp = |a: glam::Vec4, b: glam::Vec4, t: f32| a + (b - a) * t;
    let (dy, dz) = (SIDE, SIDE * SIDE);
    let x00 = lerp(v(0), v(1), tx);
    let x10 = lerp(v(dy), v(dy + 1), tx);
    let x01 = lerp(v(dz), v(dz + 1), tx);
    let x11 = lerp(v(dy + dz), v(dy + dz + 1), tx);
    lerp(lerp(x00, x10, ty), lerp(x01, x11, ty), tz)
}

/// The distance from the surface within which samples are exact, for an
/// outer and an inner reach: the larger, and a little more.
fn reach(outer: f32, inner: f32) -> f32 {
    outer.max(inner) * 1.001
}

/// The voxels a field's band reaches past the soft region and a
/// distortion's largest displacement, so that from any point beyond the
/// band no displaced point reaches the soft region (see
/// [`crate::field::soft::SoftMesh::covers_distortion`]): a displaced point
/// lies within a voxel's diagonal (√3) of a lattice point beyond the reach
/// twice over, once from a far sample's cell and once from its own cell.
pub const FIELD_MARGIN_VOXELS: f32 = 4.0;

/// The lattice of a field being built.
struct Grid {
    /// The lattice point (0, 0, 0).
    origin: Vec3,
    /// The cell's edge.
    voxel: f32,
    /// A brick's edge.
    side: f32,
    /// Slots along x, y, z.
    dims: [usize; 3],
    /// The distance from the surface within which samples are exact (the
    /// soft region, or the inner reach if farther).
    reach: f32,
}

impl Grid {
    fn new(mesh: &Mesh, spec: &BandSpec) -> Grid {
        let voxel = spec.voxel;
        let side = voxel * BRICK as f32;
        let (lo, hi) = mesh.bounds();
        let grow = Vec3::splat(spec.outer + voxel);
        let origin = lo - grow;
        let span = (hi + grow - origin) / side;
        Grid {
            origin,
            voxel,
            side,
            dims: span.to_array().map(|s| (s.ceil().min(1e9) as usize).max(1)),
            reach: reach(spec.outer, spec.inner),
        }
    }

    fn slot_count(&self) -> f64 {
        self.dims.iter().map(|&d| d as f64).product()
    }

    fn slot_xyz(&self, i: usize) -> [usize; 3] {
        let [nx, ny, _] = self.dims;
        [i % nx, i / nx % ny, i / (nx * ny)]
    }

    fn slot_origin(&self, i: usize) -> Vec3 {
        let [x, y, z] = self.slot_xyz(i);
        self.origin + Vec3::new(x as f32, y as f32, z as f32) * self.side
    }

    /// The samples of the brick in `slot`. The brick is cut into blocks of
    /// 2³ cells; a block whose centre lies farther from the soft region
    /// than its half-diagonal holds no point of it, and its samples are ±∞
    /// (the centre's side); the samples of the other blocks are exact.
    fn brick(&self, mesh: &Mesh, slot: usize) -> Vec<[f32; 4]> {
        const BLOCKS: usize = BRICK / 2;
        let base = self.slot_origin(slot);
        let lattice = |x: usize, y: usize, z: usize| {
            base + Vec3::new(x as f32, y as f32, z as f32) * self.voxel
        };
        let half = self.voxel * 3f32.sqrt();
        // Per block: 0 near, else the side (-1 inside, 1 outside).
        let mut far = [0i8; BLOCKS * BLOCKS * BLOCKS];
        for (k, f) in far.iter_mut().enumerate() {
            let (x, y, z) = (k % BLOCKS, k / BLOCKS % BLOCKS, k / (BLOCKS * BLOCKS));
            let d = mesh
                .closest(lattice(2 * x + 1, 2 * y + 1, 2 * z + 1))
                .distance;
            if d.abs() - half > self.reach {
                *f = if d < 0.0 { -1 } else { 1 };
            }
        }
        // The blocks a sample's coordinate lies in: one, or two on a face
        // between blocks.
        let blocks = |x: usize| {
            let hi = (x / 2).min(BLOCKS - 1);
            let lo = if x.is_multiple_of(2) && x > 0 {
                x / 2 - 1
            } else {
                hi
            };
            lo..=hi
        };
        let mut out = Vec::with_capacity(SAMPLES);
        for z in 0..SIDE {
            for y in 0..SIDE {
                for x in 0..SIDE {
                    let mut side = 0;
                    let mut near = false;
                    for bz in blocks(z) {
                        for by in blocks(y) {
                            for bx in blocks(x) {
                                let f = far[bx + BLOCKS * (by + BLOCKS * bz)];
                                near |= f == 0;
                                side = f;
                            }
                        }
                    }
                    out.push(if near {
                        let c = mesh.closest(lattice(x, y, z));
                        [c.distance, c.point.x, c.point.y, c.point.z]
                    } else {
                        [f32::INFINITY.copysign(f32::from(side)), 0.0, 0.0, 0.0]
                    });
                }
            }
        }
        out
    }
}
