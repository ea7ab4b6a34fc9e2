//! Triangle meshes for soft objects: a closed triangle mesh read from an OBJ
//! file, with its exact signed distance.
//!
//! The distance to the surface is the distance to the closest triangle, found
//! through a bounding volume hierarchy (the module `bvh`). Its sign comes from the
//! angle-weighted pseudo-normal of the closest feature (Bærentzen & Aanæs,
//! "Signed distance computation using the angle weighted pseudonormal", IEEE
//! TVCG 2005): the face's normal when the closest point lies inside a face, the
//! sum of the two faces' normals on an edge, and the normals of the faces
//! around a vertex weighted by their angles there. x is outside when it lies on
//! the pseudo-normal's side of the closest point. That is exact for a closed,
//! edge-manifold, consistently oriented mesh, so the loader refuses any other
//! (an open mesh has no inside).
//!
//! Building is single-threaded and uses no hashing with random state: the same
//! file gives the same triangles in the same order, the same tree, and so the
//! same bits for every query.

mod band;
mod bvh;

pub use band::{
    Band, BandKey, BandSpec, DEFAULT_MAX_FIELD_BYTES, FieldError, Sample, displaced_icosphere_obj,
};

use std::collections::BTreeMap;

use glam::Vec3;

use crate::math::random::Fnv1a;

/// The most triangles a mesh may have unless the caller allows more
/// ([`MeshLimits`]).
pub const DEFAULT_MAX_TRIANGLES: usize = 2_000_000;

/// The largest OBJ file read (a 2 M-triangle OBJ is about 120 MB).
pub const MAX_OBJ_BYTES: u64 = 512 * 1024 * 1024;

/// What a mesh may cost.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct MeshLimits {
    /// The most triangles.
    pub max_triangles: usize,
}

impl Default for MeshLimits {
    fn default() -> Self {
        MeshLimits {
            max_triangles: DEFAULT_MAX_TRIANGLES,
        }
    }
}

/// Why a mesh could not be loaded. Every message starts with the file's path.
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
#[error("{path}: {message}")]
pub struct MeshError {
    /// The OBJ file, as the scene names it or as found on disk.
    pub path: String,
    /// What is wrong with it.
    pub message: String,
}

/// One triangle with everything the signed distance needs.
#[derive(Clone, Copy, Debug, PartialEq)]
struct Triangle {
    /// Corners, counter-clockwise seen from outside.
    v: [Vec3; 3],
    /// Unit face normal (outward).
    normal: Vec3,
    /// Angle-weighted pseudo-normals of the corners (not normalised: only
    /// their direction matters).
    vertex: [Vec3; 3],
    /// Pseudo-normals of the edges v0v1, v1v2, v2v0 (the sum of the two faces'
    /// unit normals).
    edge: [Vec3; 3],
}

/// A closed triangle mesh ready for signed distance queries: immutable, shared
/// by every thread and every scene that names the same file.
#[derive(Clone)]
pub struct Mesh {
    /// FNV-1a of the OBJ file's bytes: the mesh's identity on the farm.
    hash: u64,
    /// The triangles, in the order of the tree's leaves.
    triangles: Vec<Triangle>,
    /// The tree over them.
    bvh: bvh::Bvh,
    /// The box of every vertex.
    bounds: (Vec3, Vec3),
    /// Distinct vertices (after welding equal positions).
    vertices: usize,
}

impl std::fmt::Debug for Mesh {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Mesh")
            .field("hash", &format_args!("{:016x}", self.hash))
            .field("triangles", &self.triangles.len())
            .field("vertices", &self.vertices)
            .field("bounds", &self.bounds)
            .finish()
    }
}

/// Two meshes are equal when their files are.
impl PartialEq for Mesh {
    fn eq(&self, other: &Self) -> bool {
        self.hash == other.hash
    }
}

/// The content hash of an asset's bytes (FNV-1a, as the farm's scene hash).
pub fn content_hash(bytes: &[u8]) -> u64 {
    let mut h = Fnv1a::default();
    h.write(bytes.iter().copied());
    h.finish()
}

/// Where a point's closest surface point lies on its triangle.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Feature {
    Face,
    Edge(usize),
    Vertex(usize),
}

/// The closest point to `p` on triangle `abc` and the feature it lies on
/// (Ericson, *Real-Time Collision Detection*, 5.1.5).
#[inline]
fn closest_on_triangle(p: Vec3, [a, b, c]: [Vec3; 3]) -> (Vec3, Feature) {
    let ab = b - a;
    let ac = c - a;
    let ap = p - a;
    let d1 = ab.dot(ap);
    let d2 = ac.dot(ap);
    if d1 <= 0.0 && d2 <= 0.0 {
        return (a, Feature::Vertex(0));
    }
    let bp = p - b;
    let d3 = ab.dot(bp);
    let d4 = ac.dot(bp);
    if d3 >= 0.0 && d4 <= d3 {
        return (b, Feature::Vertex(1));
    }
    let vc = d1 * d4 - d3 * d2;
    if vc <= 0.0 && d1 >= 0.0 && d3 <= 0.0 {
        let v = d1 / (d1 - d3);
        return (a + ab * v, Feature::Edge(0));
    }
    let cp = p - c;
    let d5 = ab.dot(cp);
    let d6 = ac.dot(cp);
    if d6 >= 0.0 && d5 <= d6 {
        return (c, Feature::Vertex(2));
    }
    let vb = d5 * d2 - d1 * d6;
    if vb <= 0.0 && d2 >= 0.0 && d6 <= 0.0 {
        let w = d2 / (d2 - d6);
        return (a + ac * w, Feature::Edge(2));
    }
    let va = d3 * d6 - d5 * d4;
    if va <= 0.0 && (d4 - d3) >= 0.0 && (d5 - d6) >= 0.0 {
        let w = (d4 - d3) / ((d4 - d3) + (d5 - d6));
        return (b + (c - b) * w, Feature::Edge(1));
    }
    let denom = 1.0 / (va + vb + vc);
    let v = vb * denom;
    let w = vc * denom;
    (a + ab * v + ac * w, Feature::Face)
}

/// The closest surface point to a query point.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Closest {
    /// The point of the surface nearest to the query.
    pub point: Vec3,
    /// The signed distance: negative inside the mesh.
    pub distance: f32,
    /// The unit outward pseudo-normal at `point` (the direction away from
    /// the mesh where the query point is too close to give one).
    pub outward: Vec3,
}

impl Mesh {
    /// Reads a triangle mesh from OBJ text; `path` names it in errors.
    /// Polygons are fanned into triangles; equal positions are welded; the
    /// mesh must be closed, edge-manifold and consistently oriented (an
    /// inside-out mesh is turned the right way), with no degenerate triangle.
    pub fn from_obj(path: &str, bytes: &[u8], limits: MeshLimits) -> Result<Mesh, MeshError> {
        let fail = |message: String| MeshError {
            path: path.to_string(),
            message,
        };
        let options = tobj::LoadOptions {
            triangulate: true,
            single_index: false,
            ignore_points: true,
            ignore_lines: true,
        };
        let mut reader = std::io::BufReader::new(bytes);
        let (models, _materials) = tobj::load_obj_buf(&mut reader, &options, |_| {
            // Materials do not shape a density: an mtllib is ignored.
            Ok(Default::default())
        })
        .map_err(|e| fail(format!("not a readable OBJ file: {e}")))?;
        let mut positions: Vec<Vec3> = Vec::new();
        let mut welded: BTreeMap<[u32; 3], u32> = BTreeMap::new();
        let mut faces: Vec<[u32; 3]> = Vec::new();
        for model in &models {
            let m = &model.mesh;
            let count = m.positions.len() / 3;
            let mut index = Vec::with_capacity(count);
            for p in m.positions.chunks_exact(3) {
                let v = Vec3::new(p[0], p[1], p[2]);
                if !v.is_finite() {
                    return Err(fail(format!(
                        "model `{}`: a vertex is not finite ({v})",
                        model.name
                    )));
                }
                // -0 and +0 are one position.
                let key = (v + Vec3::ZERO).to_array().map(f32::to_bits);
                let next = positions.len() as u32;
                index.push(*welded.entry(key).or_insert_with(|| {
                    positions.push(v);
                    next
                }));
            }
            if m.indices.len() % 3 != 0 {
                return Err(fail(format!(
                    "model `{}`: {} face indices do not make whole triangles",
                    model.name,
                    m.indices.len()
                )));
            }
            for t in m.indices.chunks_exact(3) {
                let mut face = [0u32; 3];
                for (k, &i) in t.iter().enumerate() {
                    face[k] = *index.get(i as usize).ok_or_else(|| {
                        fail(format!(
                            "model `{}`: a face names vertex {} of {count}",
                            model.name,
                            i as usize + 1
                        ))
                    })?;
                }
                faces.push(face);
                if faces.len() > limits.max_triangles {
                    return Err(fail(format!(
                        "more than {} triangles, the most a mesh may have here",
                        limits.max_triangles
                    )));
                }
            }
        }
        if faces.is_empty() {
            return Err(fail("no triangles: a mesh needs faces (`f` lines)".into()));
        }
        check_closed(&faces).map_err(fail)?;
        let mut triangles = triangles_of(&positions, &faces).map_err(fail)?;
        // An inside-out mesh (negative volume) is turned the right way round.
        let volume: f32 = triangles
            .iter()
            .map(|t| t.v[0].dot(t.v[1].cross(t.v[2])))
            .sum();
        if volume < 0.0 {
            for t in &mut triangles {
                t.normal = -t.normal;
                t.vertex = t.vertex.map(|n| -n);
                t.edge = t.edge.map(|n| -n);
            }
        }
        let bounds = positions
            .iter()
            .fold((Vec3::INFINITY, Vec3::NEG_INFINITY), |(lo, hi), &v| {
                (lo.min(v), hi.max(v))
            });
        let (bvh, order) = bvh::Bvh::build(&triangles.iter().map(|t| t.v).collect::<Vec<_>>());
        let triangles = order.iter().map(|&i| triangles[i as usize]).collect();
        Ok(Mesh {
            hash: content_hash(bytes),
            triangles,
            bvh,
            bounds,
            vertices: positions.len(),
        })
    }

    /// FNV-1a of the OBJ file's bytes.
    pub fn hash(&self) -> u64 {
        self.hash
    }

    /// The number of triangles.
    pub fn triangle_count(&self) -> usize {
        self.triangles.len()
    }

    /// The number of distinct vertices.
    pub fn vertex_count(&self) -> usize {
        self.vertices
    }

    /// The bytes this mesh holds: its triangles and its tree (what a cache of
    /// meshes counts against its budget).
    pub fn memory_bytes(&self) -> usize {
        std::mem::size_of::<Mesh>()
            + self.triangles.capacity() * std::mem::size_of::<Triangle>()
            + self.bvh.memory_bytes()
    }

    /// The box of every vertex (min, max).
    pub fn bounds(&self) -> (Vec3, Vec3) {
        self.bounds
    }

    /// The closest surface point to `p` and the signed distance to it
    /// (negative inside).
    #[inline]
    pub fn closest(&self, p: Vec3) -> Closest {
        let mut best = f32::INFINITY;
        let mut found = (p, 0usize, Feature::Face);
        self.bvh.visit(p, |i| {
            let (q, feature) = closest_on_triangle(p, self.triangles[i].v);
            let d2 = (p - q).length_squared();
            if d2 < best {
                best = d2;
                found = (q, i, feature);
            }
            best
        });
        let (point, i, feature) = found;
        let t = &self.triangles[i];
        let pseudo = match feature {
            Feature::Face => t.normal,
            Feature::Edge(k) => t.edge[k],
            Feature::Vertex(k) => t.vertex[k],
        };
        let distance = best.sqrt();
        let outside = (p - point).dot(pseudo) >= 0.0;
        Closest {
            point,
            distance: if outside { distance } else { -distance },
            outward: pseudo.normalize_or(t.normal),
        }
    }

    /// The signed distance to the surface (negative inside).
    #[inline]
    pub fn signed_distance(&self, p: Vec3) -> f32 {
        self.closest(p).distance
    }
}

/// Checks that every edge is shared by exactly two faces that run along it in
/// opposite directions: closed, edge-manifold and consistently oriented.
fn check_closed(faces: &[[u32; 3]]) -> Result<(), String> {
    // (low, high) → (faces running low→high, faces running high→low).
    let mut edges: BTreeMap<(u32, u32), (u32, u32)> = BTreeMap::new();
    for f in faces {
        for k in 0..3 {
            let (a, b) = (f[k], f[(k + 1) % 3]);
            let e = edges.entry((a.min(b), a.max(b))).or_default();
            if a < b {
                e.0 += 1;
            } else {
                e.1 += 1;
            }
        }
    }
    for (&(a, b), &(up, down)) in &edges {
        let (a, b) = (a + 1, b + 1);
        match (up, down) {
            (1, 1) => {}
            (1, 0) | (0, 1) => {
                return Err(format!(
                    "the mesh is open: the edge between vertices {a} and {b} belongs to one triangle only. The sign of the distance (inside or outside) is defined only for a closed mesh: close the holes (e.g. Blender's Fill Holes) or use a watertight mesh"
                ));
            }
            (u, d) if u + d == 2 => {
                return Err(format!(
                    "the triangles on both sides of the edge between vertices {a} and {b} run along it the same way: the faces are not consistently oriented (recalculate the normals outside)"
                ));
            }
            (u, d) => {
                return Err(format!(
                    "the mesh is not manifold: the edge between vertices {a} and {b} belongs to {} triangles, and only a closed mesh whose every edge joins two triangles has a well-defined inside",
                    u + d
                ));
            }
        }
    }
    Ok(())
}

/// The triangles with their normals and the angle-weighted pseudo-normals of
/// their vertices and edges.
fn triangles_of(positions: &[Vec3], faces: &[[u32; 3]]) -> Result<Vec<Triangle>, String> {
    let mut vertex_normal = vec![Vec3::ZERO; positions.len()];
    let mut normals = Vec::with_capacity(faces.len());
    for (n, f) in faces.iter().enumerate() {
        let v = f.map(|i| positions[i as usize]);
        let cross = (v[1] - v[0]).cross(v[2] - v[0]);
        let len = cross.length();
        if !(len > 0.0 && len.is_finite()) {
            return Err(format!(
                "triangle {} (vertices {}, {}, {}) has no area: remove degenerate faces (e.g. Blender's Merge by Distance)",
                n + 1,
                f[0] + 1,
                f[1] + 1,
                f[2] + 1
            ));
        }
        let normal = cross / len;
        normals.push(normal);
        for k in 0..3 {
            let e1 = (v[(k + 1) % 3] - v[k]).normalize();
            let e2 = (v[(k + 2) % 3] - v[k]).normalize();
            let angle = libm::acosf(e1.dot(e2).clamp(-1.0, 1.0));
            vertex_normal[f[k] as usize] += normal * angle;
        }
    }
    let mut edge_normal: BTreeMap<(u32, u32), Vec3> = BTreeMap::new();
    for (f, n) in faces.iter().zip(&normals) {
        for k in 0..3 {
            let (a, b) = (f[k], f[(k + 1) % 3]);
            *edge_normal.entry((a.min(b), a.max(b))).or_default() += *n;
        }
    }
    Ok(faces
        .iter()
        .zip(&normals)
        .map(|(f, &normal)| {
            let edge = |k: usize| {
                let (a, b) = (f[k], f[(k + 1) % 3]);
                edge_normal[&(a.min(b), a.max(b))]
            };
            Triangle {
                v: f.map(|i| positions[i as usize]),
                normal,
                vertex: f.map(|i| vertex_normal[i as usize]),
                edge: [edge(0), edge(1), edge(2)],
            }
        })
        .collect())
}

/// An icosphere as OBJ text: an icosahedron subdivided `levels` times, its
/// vertices pushed onto the sphere of radius `r` about `centre`, its faces
/// outward. The known answer of the mesh tests, and the probe's stand-in for
/// a scene's mesh.
pub(crate) fn icosphere_obj(centre: Vec3, r: f32, levels: u32) -> String {
    let t = (1.0 + 5f32.sqrt()) / 2.0;
    let mut v: Vec<Vec3> = [
        (-1.0, t, 0.0),
        (1.0, t, 0.0),
        (-1.0, -t, 0.0),
        (1.0, -t, 0.0),
        (0.0, -1.0, t),
        (0.0, 1.0, t),
        (0.0, -1.0, -t),
        (0.0, 1.0, -t),
        (t, 0.0, -1.0),
        (t, 0.0, 1.0),
        (-t, 0.0, -1.0),
        (-t, 0.0, 1.0),
    ]
    .iter()
    .map(|&(x, y, z)| Vec3::new(x, y, z).normalize())
    .collect();
    let mut f: Vec<[usize; 3]> = vec![
        [0, 11, 5],
        [0, 5, 1],
        [0, 1, 7],
        [0, 7, 10],
        [0, 10, 11],
        [1, 5, 9],
        [5, 11, 4],
        [11, 10, 2],
        [10, 7, 6],
        [7, 1, 8],
        [3, 9, 4],
        [3, 4, 2],
        [3, 2, 6],
        [3, 6, 8],
        [3, 8, 9],
        [4, 9, 5],
        [2, 4, 11],
        [6, 2, 10],
        [8, 6, 7],
        [9, 8, 1],
    ];
    for _ in 0..levels {
        let mut mid = BTreeMap::new();
        let mut half = |a: usize, b: usize, v: &mut Vec<Vec3>| {
            *mid.entry((a.min(b), a.max(b))).or_insert_with(|| {
                v.push(((v[a] + v[b]) * 0.5).normalize());
                v.len() - 1
            })
        };
        let mut next = Vec::new();
        for [a, b, c] in f {
            let (ab, bc, ca) = (half(a, b, &mut v), half(b, c, &mut v), half(c, a, &mut v));
            next.extend([[a, ab, ca], [b, bc, ab], [c, ca, bc], [ab, bc, ca]]);
        }
        f = next;
    }
    let mut s = String::new();
    for p in &v {
        let p = *p * r + centre;
        s += &format!("v {} {} {}\n", p.x, p.y, p.z);
    }
    for [a, b, c] in f {
        s += &format!("f {} {} {}\n", a + 1, b + 1, c + 1);
    }
    s
}

#[cfg(test)]
pub(crate) mod tests;
