//! Soft objects (section 2.1) and the generalized booleans (section 2.2).
//!
//! A soft object is a density function D(x) with range [0, 1]: 1 in its hard
//! region, 0 outside, and in between over a soft region of non-zero thickness.
//! Every primitive here uses the paper's sphere falloff: with `r1 = r - s/2` the
//! inner (D = 1) radius and `r0 = r + s/2` the outer (D = 0) radius of a distance
//! `d` from the primitive's core, `D = (r0² - d²) / (r0² - r1²)` in between.

use glam::Vec3;

use crate::field::domain::Points;
use crate::math::simd::{LANES, Lanes};
use crate::mesh::SampleLanes;

/// The paper's quadratic falloff, with the squared radii precomputed.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Falloff {
    /// `r1 = r - s/2`, the inner (D = 1) radius.
    inner: f32,
    /// `r1²`.
    inner2: f32,
    /// `r0²`, the outer (D = 0) radius squared.
    outer2: f32,
    /// `r0 = r + s/2`, the outer (D = 0) radius.
    outer: f32,
    /// `1 / (r0² - r1²)` (0 for a hard object, s = 0).
    inv_width: f32,
}

impl Falloff {
    /// The falloff of radius `radius` and softness `softness`
    /// (validated at load: `0 ≤ softness ≤ 2·radius`).
    pub fn new(radius: f32, softness: f32) -> Self {
        let inner = radius - softness / 2.0;
        let outer = radius + softness / 2.0;
        let (inner2, outer2) = (inner * inner, outer * outer);
        let width = outer2 - inner2;
        Falloff {
            inner,
            inner2,
            outer2,
            outer,
            inv_width: if width > 0.0 { 1.0 / width } else { 0.0 },
        }
    }

    /// D for a squared distance `d2` from the core.
    #[inline(always)]
    pub fn density(&self, d2: f32) -> f32 {
        if d2 <= self.inner2 {
            1.0
        } else if d2 >= self.outer2 {
            0.0
        } else {
            (self.outer2 - d2) * self.inv_width
        }
    }

    /// Whether D at the squared distance `d2·s²` is the same for every s in
    /// `[lo, hi]`: 0 (outside the outer radius for the smallest |s|), or 1
    /// when `hard` counts (inside the inner radius for the largest |s|). The
    /// radii are narrowed by 0.1% and s kept ≥ 0.01, far more than the
    /// rounding of the scaled point's squared distance, so a settled D is
    /// also the D of the point computed with any such s.
    #[inline(always)]
    pub fn settled(&self, d2: f32, lo: f32, hi: f32, hard: bool) -> bool {
        let outside = (lo >= 0.01) & (d2 * (lo * lo) >= self.outer2 * 1.001);
        let inner2 = self.inner2 * 0.999;
        let inside = hard & (d2 * (lo * lo) <= inner2) & (d2 * (hi * hi) <= inner2);
        outside | inside
    }

    /// [`Falloff::density`] as selects rather than branches, so that lane loops
    /// vectorise; the same value for every input, NaN included.
    #[inline(always)]
    pub fn density_select(&self, d2: f32) -> f32 {
        let soft = (self.outer2 - d2) * self.inv_width;
        let d = if d2 >= self.outer2 { 0.0 } else { soft };
        if d2 <= self.inner2 { 1.0 } else { d }
    }

    /// The inner (D = 1) radius.
    pub fn inner(&self) -> f32 {
        self.inner
    }

    /// The outer (D = 0) radius.
    #[inline]
    pub fn outer(&self) -> f32 {
        self.outer
    }
}

/// A soft sphere: the paper's `D[c, r, s](x)`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SoftSphere {
    /// Centre c.
    pub centre: Vec3,
    /// Radial falloff from radius r and softness s.
    pub falloff: Falloff,
}

impl SoftSphere {
    /// D(x).
    #[inline(always)]
    pub fn density(&self, x: Vec3) -> f32 {
        self.falloff.density((x - self.centre).length_squared())
    }

    /// x projected perpendicularly onto the inner (D = 1) surface.
    #[inline(always)]
    pub fn project(&self, x: Vec3) -> Vec3 {
        self.centre + direction_or(x - self.centre, Vec3::Y) * self.falloff.inner
    }
}

impl ProjectBlock for SoftSphere {
    /// [`SoftSphere::project`] of N lanes in place.
    #[inline(always)]
    fn project_block<const N: usize>(&self, x: &mut [f32; N], y: &mut [f32; N], z: &mut [f32; N]) {
        let (c, inner) = (self.centre, self.falloff.inner);
        for l in 0..N {
            let (vx, vy, vz) = (x[l] - c.x, y[l] - c.y, z[l] - c.z);
            let len2 = vx * vx + vy * vy + vz * vz;
            let len = len2.sqrt();
            // `direction_or(v, Y)`.
            let (dx, dy, dz) = if len2 > 1e-20 {
                (vx / len, vy / len, vz / len)
            } else {
                (0.0, 1.0, 0.0)
            };
            x[l] = c.x + dx * inner;
            y[l] = c.y + dy * inner;
            z[l] = c.z + dz * inner;
        }
    }
}

impl SoftSphere {
    /// [`SoftSphere::density`] at each of the lanes' points, written
    /// lane-parallel with exactly the scalar operations (so the same bits).
    #[inline(always)]
    pub fn density_lanes(&self, x: &Lanes, y: &Lanes, z: &Lanes) -> Lanes {
        let c = self.centre;
        let mut out = [0.0; LANES];
        for l in 0..LANES {
            let (qx, qy, qz) = (x[l] - c.x, y[l] - c.y, z[l] - c.z);
            out[l] = self.falloff.density_select(qx * qx + qy * qy + qz * qz);
        }
        out
    }
}

/// A soft box: the generalized intersection (product) of three soft slabs, one
/// per axis, each with the paper's falloff on the distance from the mid-plane.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SoftBox {
    /// Centre of the box.
    pub centre: Vec3,
    /// Per-axis falloff from the half size and softness.
    pub falloff: [Falloff; 3],
}

impl SoftBox {
    /// D(x) = D_x · D_y · D_z.
    #[inline(always)]
    pub fn density(&self, x: Vec3) -> f32 {
        let q = x - self.centre;
        let dx = self.falloff[0].density(q.x * q.x);
        if dx == 0.0 {
            return 0.0;
        }
        let dy = self.falloff[1].density(q.y * q.y);
        if dy == 0.0 {
            return 0.0;
        }
        dx * dy * self.falloff[2].density(q.z * q.z)
    }

    /// x projected onto the inner (D = 1) box: the nearest point of its surface.
    pub fn project(&self, x: Vec3) -> Vec3 {
        let h = Vec3::new(
            self.falloff[0].inner,
            self.falloff[1].inner,
            self.falloff[2].inner,
        );
        self.centre + nearest_on_box(x - self.centre, h)
    }
}

/// A soft torus: a tube of radius r and softness s around a circle of radius R.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SoftTorus {
    /// Centre of the ring.
    pub centre: Vec3,
    /// Unit axis of the ring (the donut's hole runs along it).
    pub axis: Vec3,
    /// Radius R of the ring (the core circle).
    pub major_radius: f32,
    /// Falloff around the core circle from the minor radius r and softness s.
    pub falloff: Falloff,
}

impl SoftTorus {
    /// The point of the core circle nearest to x.
    #[inline(always)]
    fn core_point(&self, x: Vec3) -> Vec3 {
        let q = x - self.centre;
        let radial = q - self.axis * q.dot(self.axis);
        self.centre + direction_or(radial, self.axis.any_orthonormal_vector()) * self.major_radius
    }

    /// D(x), from the squared distance to the core circle.
    #[inline(always)]
    pub fn density(&self, x: Vec3) -> f32 {
        let q = x - self.centre;
        let h = q.dot(self.axis);
        let radial = (q - self.axis * h).length() - self.major_radius;
        self.falloff.density(radial * radial + h * h)
    }

    /// x projected perpendicularly onto the inner (D = 1) surface of the tube.
    #[inline(always)]
    pub fn project(&self, x: Vec3) -> Vec3 {
        let core = self.core_point(x);
        core + direction_or(x - core, self.axis) * self.falloff.inner
    }
}

impl SoftTorus {
    /// [`SoftTorus::density`] at each of the lanes' points, written
    /// lane-parallel with exactly the scalar operations (so the same bits).
    #[inline(always)]
    pub fn density_lanes(&self, x: &Lanes, y: &Lanes, z: &Lanes) -> Lanes {
        let (c, a) = (self.centre, self.axis);
        let mut out = [0.0; LANES];
        for l in 0..LANES {
            let (qx, qy, qz) = (x[l] - c.x, y[l] - c.y, z[l] - c.z);
            let h = qx * a.x + qy * a.y + qz * a.z;
            let (rx, ry, rz) = (qx - a.x * h, qy - a.y * h, qz - a.z * h);
            let radial = (rx * rx + ry * ry + rz * rz).sqrt() - self.major_radius;
            out[l] = self.falloff.density_select(radial * radial + h * h);
        }
        out
    }

    /// [`SoftTorus::project`] at each of the lanes' points (the same bits).
    #[inline(always)]
    pub fn project_lanes(&self, x: &mut Lanes, y: &mut Lanes, z: &mut Lanes) {
        self.project_lanes_live(x, y, z, u32::MAX);
    }
}

impl ProjectBlock for SoftTorus {
    /// [`SoftTorus::project`] of N lanes in place.
    #[inline(always)]
    fn project_block<const N: usize>(&self, x: &mut [f32; N], y: &mut [f32; N], z: &mut [f32; N]) {
        let (c, a) = (self.centre, self.axis);
        let fallback = a.any_orthonormal_vector();
        let inner = self.falloff.inner;
        for l in 0..N {
            let (px, py, pz) = (x[l], y[l], z[l]);
            // The nearest point of the core circle.
            let (qx, qy, qz) = (px - c.x, py - c.y, pz - c.z);
            let h = qx * a.x + qy * a.y + qz * a.z;
            let (rx, ry, rz) = (qx - a.x * h, qy - a.y * h, qz - a.z * h);
            let len2 = rx * rx + ry * ry + rz * rz;
            let len = len2.sqrt();
            let long = len2 > 1e-20;
            let (dx, dy, dz) = if long {
                (rx / len, ry / len, rz / len)
            } else {
                (fallback.x, fallback.y, fallback.z)
            };
            let r = self.major_radius;
            let (kx, ky, kz) = (c.x + dx * r, c.y + dy * r, c.z + dz * r);
            // Out from it to the inner surface.
            let (vx, vy, vz) = (px - kx, py - ky, pz - kz);
            let len2 = vx * vx + vy * vy + vz * vz;
            let len = len2.sqrt();
            let long = len2 > 1e-20;
            let (ex, ey, ez) = if long {
                (vx / len, vy / len, vz / len)
            } else {
                (a.x, a.y, a.z)
            };
            x[l] = kx + ex * inner;
            y[l] = ky + ey * inner;
            z[l] = kz + ez * inner;
        }
    }
}

/// An object's projection onto its inner surface in lanes (a sphere's, a
/// torus's), written lane-parallel with exactly the scalar operations (so
/// the same bits).
pub(crate) trait ProjectBlock {
    /// The projection of N lanes in place.
    fn project_block<const N: usize>(&self, x: &mut [f32; N], y: &mut [f32; N], z: &mut [f32; N]);

    /// The projection at the lanes of the blocks with a lane set in `live`
    /// ([`crate::math::simd::live_blocks`]): all [`crate::math::simd::LANES`] in one go,
    /// or the live block alone. The other points are left.
    #[inline(always)]
    fn project_lanes_live(&self, x: &mut Lanes, y: &mut Lanes, z: &mut Lanes, live: u32) {
        use crate::math::simd::{BLOCK, LiveBlocks, live_blocks};
        // Lanes i·BLOCK .. (i + 1)·BLOCK, as an array.
        fn h(a: &mut Lanes, i: usize) -> &mut [f32; BLOCK] {
            &mut a.as_chunks_mut::<BLOCK>().0[i]
        }
        match live_blocks(live) {
            LiveBlocks::All => self.project_block(x, y, z),
            LiveBlocks::First => self.project_block(h(x, 0), h(y, 0), h(z, 0)),
            LiveBlocks::Second => self.project_block(h(x, 1), h(y, 1), h(z, 1)),
            LiveBlocks::None => {}
        }
    }
}

/// A closed triangle mesh as a soft object: D = 1 inside the mesh, and
/// outside it the paper's falloff on the distance d to the surface with inner
/// radius 0 and outer radius s, `D = (s² - d²) / s²` (a soft sphere of
/// softness s swept over the surface), so the mesh's surface is the inner
/// (D = 1) surface. The mesh is placed at `centre` and scaled by `scale`.
///
/// With a distance field ([`crate::mesh::Band`]), d and the closest point are
/// read from it by trilinear interpolation; outside its band D is 0 or 1
/// without a distance, and the few queries that need a distance there (a
/// projection from deep inside, say) fall back to the exact search. Without
/// one (`sdf: Exact`) every query is the exact search.
#[derive(Clone, Debug, PartialEq)]
pub struct SoftMesh {
    /// The mesh and its distance queries.
    pub mesh: std::sync::Arc<crate::mesh::Mesh>,
    /// The mesh's distance field, or `None` for the exact search.
    pub field: Option<std::sync::Arc<crate::mesh::Band>>,
    /// Where the mesh's origin goes.
    pub centre: Vec3,
    /// Uniform scale about the mesh's origin.
    pub scale: f32,
    /// `1 / scale`.
    inv_scale: f32,
    /// The falloff of inner radius 0 and outer radius s.
    pub falloff: Falloff,
    /// Whether the field's band reaches past what a distortion of the mesh
    /// can move a point by ([`SoftMesh::covering`]).
    covered: bool,
}

/// Where a point lies for a soft mesh: what D needs.
enum Near {
    /// Outside the soft region (D = 0).
    Outside,
    /// Inside the mesh (D = 1).
    Inside,
    /// The signed distance (scene units) and the closest point.
    At(crate::mesh::Closest),
}

impl SoftMesh {
    /// The mesh with softness `softness`, moved to `centre` and scaled by
    /// `scale`, read exactly (no field).
    pub fn new(
        mesh: std::sync::Arc<crate::mesh::Mesh>,
        centre: Vec3,
        scale: f32,
        softness: f32,
    ) -> Self {
        SoftMesh {
            mesh,
            field: None,
            centre,
            scale,
            inv_scale: 1.0 / scale,
            falloff: Falloff::new(softness / 2.0, softness),
            covered: false,
        }
    }

    /// The mesh under a distortion that moves points by at most `moves`
    /// (0 without one): [`SoftMesh::covers_distortion`] when its field's
    /// band reaches `moves` and [`crate::mesh::FIELD_MARGIN_VOXELS`] voxels
    /// past the soft region (as [`crate::desc::MeshDesc::field_spec`] builds
    /// it under a distortion).
    pub fn covering(self, moves: f32) -> Self {
        let covered = self.field.as_ref().is_some_and(|f| {
            moves == 0.0
                || f.reach()
                    >= (self.falloff.outer() + moves) * self.inv_scale
                        + crate::mesh::FIELD_MARGIN_VOXELS * f.voxel()
        });
        SoftMesh { covered, ..self }
    }

    /// Whether the field's band reaches so far that from any point beyond
    /// it (a slot beyond the band, or a sample [`crate::mesh::Sample::Outside`]
    /// or `Inside`), every point the distortion can move it to has D = 0
    /// (or 1 inside): there H is 0 (or the hard region) whatever the
    /// distortion's vector, which is then taken as 0.
    pub fn covers_distortion(&self) -> bool {
        self.covered
    }

    /// Whether x lies in a slot of the field wholly beyond its band (no
    /// field: false).
    #[inline]
    pub fn beyond(&self, x: Vec3) -> bool {
        self.field
            .as_ref()
            .is_some_and(|f| f.beyond((x - self.centre) * self.inv_scale))
    }

    /// [`SoftMesh::beyond`] at each lane's point: bit l for lane l.
    #[inline(always)]
    pub fn beyond_lanes(&self, x: &Lanes, y: &Lanes, z: &Lanes) -> u32 {
        match &self.field {
            Some(f) => {
                let m = self.to_mesh_lanes(x, y, z);
                f.beyond_lanes(&m[0], &m[1], &m[2])
            }
            None => 0,
        }
    }

    /// The mesh of a scene's `Mesh(..)`, with its field when it has one.
    pub fn from_desc(
        mesh: std::sync::Arc<crate::mesh::Mesh>,
        desc: &crate::desc::MeshDesc,
    ) -> Self {
        SoftMesh {
            field: desc.field.clone(),
            ..SoftMesh::new(mesh, desc.centre.0, desc.scale, desc.softness)
        }
    }

    /// The closest point of the surface in the mesh's own coordinates, with
    /// the signed distance in the scene's.
    #[inline]
    fn closest(&self, x: Vec3) -> crate::mesh::Closest {
        let c = self.mesh.closest((x - self.centre) * self.inv_scale);
        self.to_scene(c)
    }

    /// A closest point in the mesh's coordinates moved to the scene's.
    #[inline]
    fn to_scene(&self, c: crate::mesh::Closest) -> crate::mesh::Closest {
        crate::mesh::Closest {
            point: self.centre + c.point * self.scale,
            distance: c.distance * self.scale,
            outward: c.outward,
        }
    }

    /// Where x lies: from the field when there is one (its closest point's
    /// `outward` is unset, zero), else from the exact search.
    #[inline]
    fn near(&self, x: Vec3) -> Near {
        let Some(field) = &self.field else {
            return Near::At(self.closest(x));
        };
        match field.sample((x - self.centre) * self.inv_scale) {
            crate::mesh::Sample::Outside => Near::Outside,
            crate::mesh::Sample::Inside => Near::Inside,
            crate::mesh::Sample::Near { distance, point } => {
                Near::At(self.to_scene(crate::mesh::Closest {
                    point,
                    distance,
                    outward: Vec3::ZERO,
                }))
            }
        }
    }

    /// The closest point and signed distance from the field where it has
    /// them, else exact.
    #[inline]
    fn closest_near(&self, x: Vec3) -> crate::mesh::Closest {
        match self.near(x) {
            Near::At(c) => c,
            Near::Outside | Near::Inside => self.closest(x),
        }
    }

    /// The box (min, max) outside which D is 0.
    pub fn support(&self) -> (Vec3, Vec3) {
        let (lo, hi) = self.mesh.bounds();
        let s = Vec3::splat(self.falloff.outer());
        (
            self.centre + lo * self.scale - s,
            self.centre + hi * self.scale + s,
        )
    }

    /// D(x).
    #[inline]
    pub fn density(&self, x: Vec3) -> f32 {
        let (lo, hi) = self.support();
        if x.cmplt(lo).any() || x.cmpgt(hi).any() {
            return 0.0;
        }
        let d = match self.near(x) {
            Near::Outside => return 0.0,
            Near::Inside => return 1.0,
            Near::At(c) => c.distance,
        };
        if d <= 0.0 {
            1.0
        } else {
            self.falloff.density(d * d)
        }
    }

    /// x projected onto the inner (D = 1) surface: the mesh's nearest point.
    #[inline]
    pub fn project(&self, x: Vec3) -> Vec3 {
        self.closest_near(x).point
    }

    /// The lanes' points in the mesh's coordinates, `(x − centre) / scale`
    /// as [`SoftMesh::near`] computes it.
    #[inline(always)]
    fn to_mesh_lanes(&self, x: &Lanes, y: &Lanes, z: &Lanes) -> [Lanes; 3] {
        let (c, k) = (self.centre, self.inv_scale);
        [
            std::array::from_fn(|l| (x[l] - c.x) * k),
            std::array::from_fn(|l| (y[l] - c.y) * k),
            std::array::from_fn(|l| (z[l] - c.z) * k),
        ]
    }

    /// [`SoftMesh::density`] at each lane's point (the same bits): the field
    /// read a register at a time, or the exact search point by point.
    #[inline(always)]
    pub fn density_lanes(&self, x: &Lanes, y: &Lanes, z: &Lanes) -> Lanes {
        match self.sample_lanes(x, y, z) {
            Some(s) => self.density_sampled(x, y, z, &s),
            None => std::array::from_fn(|l| self.density(Vec3::new(x[l], y[l], z[l]))),
        }
    }

    /// The field at each lane's point, or `None` without a field.
    #[inline(always)]
    pub fn sample_lanes(&self, x: &Lanes, y: &Lanes, z: &Lanes) -> Option<SampleLanes> {
        let field = self.field.as_ref()?;
        let m = self.to_mesh_lanes(x, y, z);
        Some(field.sample_lanes(&m[0], &m[1], &m[2]))
    }

    /// [`SoftMesh::density_lanes`] from the field's samples `s` at the
    /// lanes' points ([`SoftMesh::sample_lanes`]).
    #[inline(always)]
    pub fn density_sampled(&self, x: &Lanes, y: &Lanes, z: &Lanes, s: &SampleLanes) -> Lanes {
        let (lo, hi) = self.support();
        let mut out = [0.0; LANES];
        for l in 0..LANES {
            let beyond = x[l] < lo.x
                || y[l] < lo.y
                || z[l] < lo.z
                || x[l] > hi.x
                || y[l] > hi.y
                || z[l] > hi.z;
            // `to_scene`'s distance.
            let d = s.distance[l] * self.scale;
            let near = if d <= 0.0 {
                1.0
            } else {
                self.falloff.density_select(d * d)
            };
            out[l] = if beyond || s.outside >> l & 1 != 0 {
                0.0
            } else if s.inside >> l & 1 != 0 {
                1.0
            } else {
                near
            };
        }
        out
    }

    /// [`SoftMesh::project`] of the lanes set in `live` (the same bits), in
    /// place: the field read a register at a time; the exact search for
    /// the points outside its band, and for every point without one.
    #[inline(always)]
    pub fn project_lanes_live(&self, x: &mut Lanes, y: &mut Lanes, z: &mut Lanes, live: u32) {
        match self.sample_lanes(x, y, z) {
            Some(s) => self.project_sampled(x, y, z, live, &s),
            None => {
                for l in 0..LANES {
                    if live >> l & 1 != 0 {
                        let p = self.project(Vec3::new(x[l], y[l], z[l]));
                        (x[l], y[l], z[l]) = (p.x, p.y, p.z);
                    }
                }
            }
        }
    }

    /// [`SoftMesh::project_lanes_live`] from the field's samples `s` at the
    /// lanes' points ([`SoftMesh::sample_lanes`]).
    #[inline(always)]
    pub fn project_sampled(
        &self,
        x: &mut Lanes,
        y: &mut Lanes,
        z: &mut Lanes,
        live: u32,
        s: &SampleLanes,
    ) {
        // The exact search's points first, while x holds the lanes' points.
        let exact = (s.outside | s.inside) & live;
        let mut found = [Vec3::ZERO; LANES];
        let mut rest = exact;
        while rest != 0 {
            let l = rest.trailing_zeros() as usize;
            rest &= rest - 1;
            found[l] = self.closest(Vec3::new(x[l], y[l], z[l])).point;
        }
        let (c, k) = (self.centre, self.scale);
        for l in 0..LANES {
            if live >> l & 1 != 0 {
                // `to_scene`'s point, coordinate by coordinate.
                x[l] = c.x + s.point[0][l] * k;
                y[l] = c.y + s.point[1][l] * k;
                z[l] = c.z + s.point[2][l] * k;
            }
        }
        let mut rest = exact;
        while rest != 0 {
            let l = rest.trailing_zeros() as usize;
            rest &= rest - 1;
            (x[l], y[l], z[l]) = (found[l].x, found[l].y, found[l].z);
        }
    }

    /// The nearest point of the outer (D = 0) surface, s outside the mesh.
    #[inline]
    pub fn boundary_point(&self, x: Vec3) -> Vec3 {
        let mut c = match self.near(x) {
            Near::At(c) => c,
            // Nothing the vector does matters here (`covers_distortion`):
            // none.
            Near::Outside | Near::Inside if self.covered => return x,
            Near::Outside | Near::Inside => self.closest(x),
        };
        let away = if c.distance > 0.0 {
            x - c.point
        } else {
            c.point - x
        };
        if away.length_squared() <= 1e-20 && c.outward == Vec3::ZERO {
            // On the surface: the exact search's pseudo-normal.
            c = self.closest(x);
        }
        c.point + direction_or(away, c.outward) * self.falloff.outer()
    }

    /// [`SoftMesh::boundary_point`] at each lane's point (the same bits):
    /// the field read a register at a time, the exact search where the
    /// scalar path takes it.
    #[inline(always)]
    pub fn boundary_point_lanes(&self, x: &Points) -> Points {
        let Some(s) = self.sample_lanes(&x.x, &x.y, &x.z) else {
            return x.map(|p| self.boundary_point(p));
        };
        let mut out = Points::default();
        // Lanes the scalar path answers (off the band without the
        // distortion's cover, or on the surface).
        let mut scalar = if self.covered {
            0
        } else {
            s.outside | s.inside
        };
        let outer = self.falloff.outer();
        for l in 0..LANES {
            let p = x.get(l);
            if (s.outside | s.inside) >> l & 1 != 0 {
                out.set(l, p);
                continue;
            }
            // `to_scene`, then the scalar path's formula.
            let point =
                self.centre + Vec3::new(s.point[0][l], s.point[1][l], s.point[2][l]) * self.scale;
            let distance = s.distance[l] * self.scale;
            let away = if distance > 0.0 { p - point } else { point - p };
            if away.length_squared() <= 1e-20 {
                scalar |= 1 << l;
            }
            out.set(l, point + direction_or(away, Vec3::ZERO) * outer);
        }
        while scalar != 0 {
            let l = scalar.trailing_zeros() as usize;
            scalar &= scalar - 1;
            out.set(l, self.boundary_point(x.get(l)));
        }
        out
    }

    /// The distance from x to the outer (D = 0) surface, 0 outside it.
    #[inline]
    pub fn exit_distance(&self, x: Vec3) -> f32 {
        let d = match self.near(x) {
            Near::Outside => return 0.0,
            Near::Inside => self.closest(x).distance,
            Near::At(c) => c.distance,
        };
        (self.falloff.outer() - d).max(0.0)
    }
}

/// The primitives differentiated ([`crate::math::dual`]): the same formulas on a
/// point with its Jacobian.
mod dual {
    use glam::Vec3;

    use super::{Falloff, SoftBox, SoftSphere, SoftTorus};
    use crate::math::dual::{Dual, DualPoint};

    impl Falloff {
        /// [`Falloff::density`] of a squared distance with its gradient.
        #[inline]
        pub fn density_dual(&self, d2: Dual) -> Dual {
            if d2.v <= self.inner2 {
                Dual::constant(1.0)
            } else if d2.v >= self.outer2 {
                Dual::constant(0.0)
            } else {
                (-d2 + self.outer2) * self.inv_width
            }
        }
    }

    impl SoftSphere {
        /// [`SoftSphere::density`] with its gradient.
        #[inline]
        pub fn density_dual(&self, x: &DualPoint) -> Dual {
            self.falloff
                .density_dual(x.offset(-self.centre).length_squared())
        }

        /// [`SoftSphere::project`] with its Jacobian.
        #[inline]
        pub fn project_dual(&self, x: &DualPoint) -> DualPoint {
            x.offset(-self.centre)
                .direction_or(Vec3::Y)
                .times(self.falloff.inner)
                .offset(self.centre)
        }
    }

    impl SoftBox {
        /// [`SoftBox::density`] with its gradient.
        #[inline]
        pub fn density_dual(&self, x: &DualPoint) -> Dual {
            let q = x.offset(-self.centre);
            let dx = self.falloff[0].density_dual(q.x * q.x);
            if dx.v == 0.0 {
                return Dual::constant(0.0);
            }
            let dy = self.falloff[1].density_dual(q.y * q.y);
            if dy.v == 0.0 {
                return Dual::constant(0.0);
            }
            dx * dy * self.falloff[2].density_dual(q.z * q.z)
        }

        /// [`SoftBox::project`] with its Jacobian: the coordinate pushed onto
        /// a face is constant there, the clamped ones too.
        #[inline]
        pub fn project_dual(&self, x: &DualPoint) -> DualPoint {
            let h = Vec3::new(
                self.falloff[0].inner,
                self.falloff[1].inner,
                self.falloff[2].inner,
            );
            let q = x.offset(-self.centre);
            let v = q.value();
            let mut p = q;
            let clamp = |c: Dual, h: f32| {
                if c.v < -h {
                    Dual::constant(-h)
                } else if c.v > h {
                    Dual::constant(h)
                } else {
                    c
                }
            };
            if v.abs().cmple(h).all() {
                let gap = h - v.abs();
                if gap.x <= gap.y && gap.x <= gap.z {
                    p.x = Dual::constant(h.x.copysign(v.x));
                } else if gap.y <= gap.z {
                    p.y = Dual::constant(h.y.copysign(v.y));
                } else {
                    p.z = Dual::constant(h.z.copysign(v.z));
                }
            } else {
                p = DualPoint {
                    x: clamp(q.x, h.x),
                    y: clamp(q.y, h.y),
                    z: clamp(q.z, h.z),
                };
            }
            p.offset(self.centre)
        }
    }

    impl SoftTorus {
        /// The core circle's nearest point, with its Jacobian.
        #[inline]
        fn core_point_dual(&self, x: &DualPoint) -> DualPoint {
            let q = x.offset(-self.centre);
            let radial = q.sub(&DualPoint::along(self.axis, q.dot(self.axis)));
            radial
                .direction_or(self.axis.any_orthonormal_vector())
                .times(self.major_radius)
                .offset(self.centre)
        }

        /// [`SoftTorus::density`] with its gradient.
        #[inline]
        pub fn density_dual(&self, x: &DualPoint) -> Dual {
            let q = x.offset(-self.centre);
            let h = q.dot(self.axis);
            let radial = q
                .sub(&DualPoint::along(self.axis, h))
                .length_squared()
                .sqrt()
                - self.major_radius;
            self.falloff.density_dual(radial * radial + h * h)
        }

        /// [`SoftTorus::project`] with its Jacobian.
        #[inline]
        pub fn project_dual(&self, x: &DualPoint) -> DualPoint {
            let core = self.core_point_dual(x);
            x.sub(&core)
                .direction_or(self.axis)
                .times(self.falloff.inner)
                .add(&core)
        }
    }
}

/// The nearest point of each primitive's outer (D = 0) surface: where Gilet &
/// Dischler's default vector field points (section 4.3).
pub mod boundary_point {
    use glam::Vec3;

    use super::{SoftBox, SoftSphere, SoftTorus, direction_or};

    /// On the sphere of radius `r + s/2` about the centre.
    #[inline]
    pub fn sphere(s: &SoftSphere, x: Vec3) -> Vec3 {
        s.centre + direction_or(x - s.centre, Vec3::Y) * s.falloff.outer()
    }

    /// On the outer box (half sizes `h + s/2`): clamped from outside, pushed out
    /// through the nearest face from inside.
    #[inline]
    pub fn soft_box(b: &SoftBox, x: Vec3) -> Vec3 {
        let h = Vec3::new(
            b.falloff[0].outer(),
            b.falloff[1].outer(),
            b.falloff[2].outer(),
        );
        b.centre + super::nearest_on_box(x - b.centre, h)
    }

    /// On the tube of radius `r + s/2` around the core circle.
    #[inline]
    pub fn torus(t: &SoftTorus, x: Vec3) -> Vec3 {
        let core = t.core_point(x);
        core + direction_or(x - core, t.axis) * t.falloff.outer()
    }
}

/// A soft primitive of the density tree, borrowed: the soft object whose
/// outer (D = 0) surface Gilet & Dischler's vector fields follow (section 4.3).
#[derive(Clone, Copy, Debug)]
pub enum Primitive<'a> {
    /// A soft sphere.
    Sphere(&'a SoftSphere),
    /// A soft box.
    Box(&'a SoftBox),
    /// A soft torus.
    Torus(&'a SoftTorus),
    /// A closed triangle mesh.
    Mesh(&'a SoftMesh),
}

impl Primitive<'_> {
    /// The distance from x along the unit vector u to the outer surface (0
    /// when x lies outside it). Exact for spheres and boxes; for a torus, the
    /// distance to the nearest point of its outer surface.
    #[inline]
    pub fn exit_distance(self, x: Vec3, u: Vec3) -> f32 {
        match self {
            Primitive::Sphere(s) => {
                let q = x - s.centre;
                let r = s.falloff.outer();
                let c = q.length_squared() - r * r;
                if c >= 0.0 {
                    return 0.0;
                }
                let b = q.dot(u);
                -b + (b * b - c).max(0.0).sqrt()
            }
            Primitive::Box(b) => {
                let q = x - b.centre;
                let mut t = f32::INFINITY;
                for axis in 0..3 {
                    let h = b.falloff[axis].outer();
                    if q[axis].abs() >= h {
                        return 0.0;
                    }
                    if u[axis] != 0.0 {
                        let wall = if u[axis] > 0.0 { h } else { -h };
                        t = t.min((wall - q[axis]) / u[axis]);
                    }
                }
                t
            }
            Primitive::Torus(t) => {
                let nearest = boundary_point::torus(t, x) - x;
                if t.density(x) > 0.0 {
                    nearest.length()
                } else {
                    0.0
                }
            }
            // As for a torus: the distance to the nearest point of the outer surface.
            Primitive::Mesh(m) => m.exit_distance(x),
        }
    }

    /// The nearest point of the outer (D = 0) surface ([`boundary_point`]).
    #[inline(always)]
    pub fn boundary_point(self, x: Vec3) -> Vec3 {
        match self {
            Primitive::Sphere(s) => boundary_point::sphere(s, x),
            Primitive::Box(b) => boundary_point::soft_box(b, x),
            Primitive::Torus(t) => boundary_point::torus(t, x),
            Primitive::Mesh(m) => m.boundary_point(x),
        }
    }
}

/// The nearest point of the surface of the box of half sizes `h` about the
/// origin to `q`: clamped from outside, pushed out through the nearest face
/// from inside.
#[inline]
fn nearest_on_box(q: Vec3, h: Vec3) -> Vec3 {
    if q.abs().cmple(h).all() {
        let gap = h - q.abs();
        let mut p = q;
        if gap.x <= gap.y && gap.x <= gap.z {
            p.x = h.x.copysign(q.x);
        } else if gap.y <= gap.z {
            p.y = h.y.copysign(q.y);
        } else {
            p.z = h.z.copysign(q.z);
        }
        p
    } else {
        q.clamp(-h, h)
    }
}

/// `v` normalised, or `fallback` where `v` is too short to have a direction.
#[inline(always)]
fn direction_or(v: Vec3, fallback: Vec3) -> Vec3 {
    let len2 = v.length_squared();
    if len2 > 1e-20 {
        v / len2.sqrt()
    } else {
        fallback
    }
}

/// The generalized booleans of section 2.2 on densities `a` and `b`.
pub mod boolean {
    /// Union `A ∪ B = a + b - ab`.
    #[inline]
    pub fn union(a: f32, b: f32) -> f32 {
        a + b - a * b
    }

    /// Intersection `A ∩ B = ab`.
    #[inline]
    pub fn intersection(a: f32, b: f32) -> f32 {
        a * b
    }

    /// Difference `A - B = a - ab`.
    #[inline]
    pub fn difference(a: f32, b: f32) -> f32 {
        a - a * b
    }

    /// Complement `1 - a`.
    #[inline]
    pub fn complement(a: f32) -> f32 {
        1.0 - a
    }
}

#[cfg(test)]
mod tests {
    use super::boolean::*;
    use super::*;

    fn sphere() -> SoftSphere {
        SoftSphere {
            centre: Vec3::ZERO,
            falloff: Falloff::new(1.0, 0.5),
        }
    }

    #[test]
    fn sphere_regions() {
        let s = sphere();
        assert_eq!(s.density(Vec3::ZERO), 1.0);
        assert_eq!(s.density(Vec3::new(0.75, 0.0, 0.0)), 1.0);
        assert_eq!(s.density(Vec3::new(1.25, 0.0, 0.0)), 0.0);
        assert_eq!(s.density(Vec3::new(0.0, 3.0, 0.0)), 0.0);
        // The paper's quadratic falloff: (r0² - d²) / (r0² - r1²).
        let d = s.density(Vec3::new(0.0, 0.0, 1.0));
        assert!((d - (1.5625 - 1.0) / (1.5625 - 0.5625)).abs() < 1e-6);
        let p = s.project(Vec3::new(0.0, 2.0, 0.0));
        assert!((p - Vec3::new(0.0, 0.75, 0.0)).length() < 1e-6);
    }

    #[test]
    fn a_settled_density_is_the_same_over_the_whole_range() {
        let falloff = Falloff::new(1.0, 0.3);
        let mut r = crate::math::random::SplitMix64::new(7);
        let (mut outside, mut inside) = (0, 0);
        for _ in 0..20_000 {
            let d2 = 4.0 * r.next_f32();
            let lo = 2.0 * r.next_f32() - 0.5;
            let hi = lo + 0.5 * r.next_f32();
            for hard in [false, true] {
                if !falloff.settled(d2, lo, hi, hard) {
                    continue;
                }
                let at = |s: f32| falloff.density(d2 * (s * s));
                let d = at(lo);
                assert!(d == 0.0 || (hard && d == 1.0), "{d} at {d2}, [{lo}, {hi}]");
                for k in 1..=16 {
                    let s = lo + (hi - lo) * k as f32 / 16.0;
                    assert_eq!(at(s), d, "{d2} at s = {s} of [{lo}, {hi}]");
                }
                outside += usize::from(d == 0.0);
                inside += usize::from(d == 1.0);
            }
        }
        assert!(
            outside > 1000 && inside > 1000,
            "{outside} outside, {inside} inside"
        );
    }

    #[test]
    fn torus_regions_and_projection() {
        let t = SoftTorus {
            centre: Vec3::ZERO,
            axis: Vec3::Y,
            major_radius: 1.0,
            falloff: Falloff::new(0.475, 0.25),
        };
        assert_eq!(t.density(Vec3::new(1.0, 0.0, 0.0)), 1.0);
        assert_eq!(t.density(Vec3::new(1.34, 0.0, 0.0)), 1.0);
        assert_eq!(t.density(Vec3::new(0.0, 0.0, 1.61)), 0.0);
        assert_eq!(t.density(Vec3::ZERO), 0.0);
        let d = t.density(Vec3::new(0.0, 0.5, -1.0));
        assert!(d > 0.0 && d < 1.0);
        let p = t.project(Vec3::new(1.5, 0.0, 0.0));
        assert!((p - Vec3::new(1.35, 0.0, 0.0)).length() < 1e-5);
        let p = t.project(Vec3::new(0.0, 0.5, -1.0));
        assert!((p - Vec3::new(0.0, 0.35, -1.0)).length() < 1e-5);
    }

    #[test]
    fn box_is_a_product_of_slabs() {
        let b = SoftBox {
            centre: Vec3::ZERO,
            falloff: [Falloff::new(1.0, 0.2); 3],
        };
        assert_eq!(b.density(Vec3::splat(0.85)), 1.0);
        assert_eq!(b.density(Vec3::new(1.2, 0.0, 0.0)), 0.0);
        let edge = b.density(Vec3::new(1.0, 0.0, 0.0));
        assert!(edge > 0.0 && edge < 1.0);
        assert!((b.density(Vec3::new(1.0, 1.0, 0.0)) - edge * edge).abs() < 1e-6);
        let p = b.project(Vec3::new(0.1, 0.2, 0.85));
        assert_eq!(p, Vec3::new(0.1, 0.2, 0.9));
        let p = b.project(Vec3::new(2.0, 0.0, 0.0));
        assert_eq!(p, Vec3::new(0.9, 0.0, 0.0));
    }

    #[test]
    fn generalized_booleans() {
        let (a, b) = (0.25, 0.5);
        assert_eq!(union(a, b), 0.625);
        assert_eq!(intersection(a, b), 0.125);
        assert_eq!(difference(a, b), 0.125);
        assert_eq!(complement(a), 0.75);
        // Hard sets behave as ordinary sets.
        for (a, b) in [(0.0, 0.0), (0.0, 1.0), (1.0, 0.0), (1.0, 1.0)] {
            let (sa, sb) = (a == 1.0, b == 1.0);
            assert_eq!(union(a, b) == 1.0, sa || sb);
            assert_eq!(intersection(a, b) == 1.0, sa && sb);
            assert_eq!(difference(a, b) == 1.0, sa && !sb);
        }
        // The paper's remark: A ∩ A ≠ A for a soft A.
        assert_ne!(intersection(a, a), a);
    }
}
