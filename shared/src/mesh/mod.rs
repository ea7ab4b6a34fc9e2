//! Triangle meshes for soft objects: a triangle mesh read from an OBJ file
//! (the module `obj`), with its exact signed distance.
//!
//! The distance to the surface is the distance to the closest triangle, found
//! through a bounding volume hierarchy (the module `bvh`). Its sign (inside or
//! outside) comes from one of two rules, chosen per mesh from how its faces
//! meet (the module `topology`):
//!
//! - On a closed, edge-manifold, consistently oriented mesh, from the
//!   angle-weighted pseudo-normal of the closest feature (Bærentzen & Aanæs,
//!   "Signed distance computation using the angle weighted pseudonormal",
//!   IEEE TVCG 2005): the face's normal when the closest point lies inside a
//!   face, the sum of the two faces' normals on an edge, and the normals of
//!   the faces around a vertex weighted by their angles there. x is outside
//!   when it lies on the pseudo-normal's side of the closest point. That is
//!   exact on such a mesh.
//! - On any other mesh (open, non-manifold, inconsistently oriented, or made
//!   of parts whose boxes overlap, nested or crossing), from the generalized
//!   winding number w (the module `winding`): x is inside where w ≥ ½. Such a mesh loads with warnings
//!   that count its boundary, non-manifold and misoriented edges
//!   ([`Mesh::warnings`]). Where a hole lets the inside meet the outside, the
//!   sign changes across the hole while the distance to the triangles does
//!   not fall to 0 there.
//!
//! An inside-out mesh (negative signed volume) is turned the right way round;
//! triangles without area are left out, with a warning.
//!
//! Building is single-threaded and uses no hashing with random state: the same
//! file gives the same triangles in the same order, the same tree, and so the
//! same bits for every query.

mod band;
mod bvh;
mod obj;
mod topology;
mod winding;

pub use band::{
    Band, BandKey, BandSpec, DEFAULT_MAX_FIELD_BYTES, FIELD_MARGIN_VOXELS, FieldError, Sample,
    SampleLanes, displaced_icosphere_obj,
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

/// Where the sign of the distance comes from.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Sign {
    /// The angle-weighted pseudo-normal of the closest feature (a closed,
    /// edge-manifold, consistently oriented mesh whose parts' boxes do not
    /// overlap).
    PseudoNormal,
    /// The generalized winding number (any other mesh).
    Winding,
}

/// A triangle mesh ready for signed distance queries: immutable, shared by
/// every thread and every scene that names the same file.
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
    /// Connected parts (faces joined through shared vertices).
    parts: usize,
    /// Where the sign of the distance comes from.
    sign: Sign,
    /// The winding number's far-field expansions over the tree's nodes.
    winding: winding::WindingTree,
    /// The file's faces run clockwise seen from outside: the winding
    /// number is negated.
    flipped: bool,
    /// What is wrong with the mesh but does not stop it being used.
    warnings: Vec<String>,
}

impl std::fmt::Debug for Mesh {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Mesh")
            .field("hash", &format_args!("{:016x}", self.hash))
            .field("triangles", &self.triangles.len())
            .field("vertices", &self.vertices)
            .field("bounds", &self.bounds)
            .field("parts", &self.parts)
            .field("sign", &self.sign)
            .field("warnings", &self.warnings)
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
    /// Reads a triangle mesh from OBJ text ([`obj`](self) describes what
    /// is read); `path` names it in errors. Polygons are fanned into
    /// triangles; equal positions are welded; triangles without area are left
    /// out. A mesh that is open, non-manifold or inconsistently oriented loads
    /// with warnings ([`Mesh::warnings`]) and takes its sign from the winding
    /// number.
    pub fn from_obj(path: &str, bytes: &[u8], limits: MeshLimits) -> Result<Mesh, MeshError> {
        let fail = |message: String| MeshError {
            path: path.to_string(),
            message,
        };
        let obj = obj::read(bytes, limits.max_triangles).map_err(fail)?;
        Mesh::build(content_hash(bytes), &obj.positions, obj.faces).map_err(fail)
    }

    /// The mesh of welded `positions` and `faces` (indices into them), its
    /// identity `hash`.
    fn build(hash: u64, positions: &[Vec3], faces: Vec<[u32; 3]>) -> Result<Mesh, String> {
        let all = faces.len();
        let faces: Vec<[u32; 3]> = faces
            .into_iter()
            .filter(|f| face_normal(positions, f).is_some())
            .collect();
        if faces.is_empty() {
            return Err(format!(
                "none of the {all} triangles has an area: a mesh needs faces that are not degenerate"
            ));
        }
        let edges = topology::edges(&faces);
        let parts = topology::parts(positions, &faces);
        let mut warnings = Vec::new();
        if faces.len() < all {
            warnings.push(format!(
                "{} triangles have no area and are left out (Blender's Merge by Distance removes them)",
                all - faces.len()
            ));
        }
        warnings.extend(edges.warnings());
        let mut triangles = triangles_of(positions, &faces, &edges);
        // An inside-out mesh (negative volume) is turned the right way round.
        let volume: f32 = triangles
            .iter()
            .map(|t| t.v[0].dot(t.v[1].cross(t.v[2])))
            .sum();
        let flipped = volume < 0.0;
        if flipped {
            for t in &mut triangles {
                t.normal = -t.normal;
                t.vertex = t.vertex.map(|n| -n);
                t.edge = t.edge.map(|n| -n);
            }
        }
        let bounds = faces
            .iter()
            .flatten()
            .map(|&i| positions[i as usize])
            .fold((Vec3::INFINITY, Vec3::NEG_INFINITY), |(lo, hi), v| {
                (lo.min(v), hi.max(v))
            });
        let (bvh, order) = bvh::Bvh::build(&triangles.iter().map(|t| t.v).collect::<Vec<_>>());
        let triangles: Vec<Triangle> = order.iter().map(|&i| triangles[i as usize]).collect();
        let winding = winding::WindingTree::build(&bvh, |i| triangles[i].v);
        Ok(Mesh {
            hash,
            triangles,
            bvh,
            bounds,
            vertices: positions.len(),
            parts: parts.count,
            sign: if edges.closed() && !parts.overlapping {
                Sign::PseudoNormal
            } else {
                Sign::Winding
            },
            winding,
            flipped,
            warnings,
        })
    }

    /// What is wrong with the mesh but does not stop it being used, one
    /// sentence each with its count: open, non-manifold, inconsistently
    /// oriented, triangles without area. Empty for a closed, edge-manifold,
    /// consistently oriented mesh.
    pub fn warnings(&self) -> &[String] {
        &self.warnings
    }

    /// The mesh is closed, edge-manifold and consistently oriented, and no
    /// two of its parts' boxes overlap: the sign of the distance comes from
    /// the pseudo-normal (otherwise from the winding number).
    pub fn is_closed(&self) -> bool {
        self.sign == Sign::PseudoNormal
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
            + self.winding.memory_bytes()
    }

    /// The number of connected parts (faces joined through shared vertices).
    pub fn part_count(&self) -> usize {
        self.parts
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
        let outside = match self.sign {
            Sign::PseudoNormal => (p - point).dot(pseudo) >= 0.0,
            Sign::Winding => self.winding_number(p) < 0.5,
        };
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

    /// The generalized winding number at `p`: about 1 inside and 0 outside
    /// a closed mesh, fractional near an open mesh's holes. Its far field
    /// comes from the tree's expansions: within 0.02 of the exact sum, and
    /// within 10⁻³ on average (the tests bound both).
    #[inline]
    pub fn winding_number(&self, p: Vec3) -> f32 {
        let w = self
            .winding
            .winding_number(&self.bvh, |i| self.triangles[i].v, p);
        if self.flipped { -w } else { w }
    }

    /// `p` is inside the mesh: the sign of [`Mesh::closest`]'s distance
    /// without its closest point. On a mesh that takes its sign from the
    /// winding number, w ≥ ½. On a closed mesh, the winding number where it
    /// is clearly 0 or 1 (below ¼ or above ¾) and the pseudo-normal's sign
    /// in between, which happens only next to the surface.
    pub fn is_inside(&self, p: Vec3) -> bool {
        let w = self.winding_number(p);
        match self.sign {
            Sign::Winding => w >= 0.5,
            Sign::PseudoNormal if w > 0.75 => true,
            Sign::PseudoNormal if w < 0.25 => false,
            Sign::PseudoNormal => self.closest(p).distance < 0.0,
        }
    }
}

/// The unit normal of face `f` (corners counter-clockwise seen from its
/// front), `None` when it has no area.
fn face_normal(positions: &[Vec3], f: &[u32; 3]) -> Option<Vec3> {
    let v = f.map(|i| positions[i as usize]);
    let cross = (v[1] - v[0]).cross(v[2] - v[0]);
    let len = cross.length();
    (len > 0.0 && len.is_finite()).then(|| cross / len)
}

/// The triangles with their normals and the angle-weighted pseudo-normals of
/// their vertices and edges (every face has an area).
fn triangles_of(positions: &[Vec3], faces: &[[u32; 3]], edges: &topology::Edges) -> Vec<Triangle> {
    let mut vertex_normal = vec![Vec3::ZERO; positions.len()];
    let mut normals = Vec::with_capacity(faces.len());
    for f in faces {
        let v = f.map(|i| positions[i as usize]);
        let normal = face_normal(positions, f).unwrap_or(Vec3::ZERO);
        normals.push(normal);
        for k in 0..3 {
            let e1 = (v[(k + 1) % 3] - v[k]).normalize();
            let e2 = (v[(k + 2) % 3] - v[k]).normalize();
            let angle = libm::acosf(e1.dot(e2).clamp(-1.0, 1.0));
            vertex_normal[f[k] as usize] += normal * angle;
        }
    }
    let mut edge_normal = vec![Vec3::ZERO; edges.count];
    for (e, n) in edges.of_face.iter().zip(&normals) {
        for k in e {
            edge_normal[*k as usize] += *n;
        }
    }
    faces
        .iter()
        .zip(&normals)
        .zip(&edges.of_face)
        .map(|((f, &normal), e)| Triangle {
            v: f.map(|i| positions[i as usize]),
            normal,
            vertex: f.map(|i| vertex_normal[i as usize]),
            edge: e.map(|k| edge_normal[k as usize]),
        })
        .collect()
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
