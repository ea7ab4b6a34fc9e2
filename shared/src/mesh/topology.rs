//! How a triangle mesh's faces meet along their edges: which edges are on a
//! boundary (one face), which are non-manifold (more than two faces), and
//! which join two faces that run along them the same way (inconsistent
//! orientation). A mesh with none of the three is closed, edge-manifold and
//! consistently oriented: the angle-weighted pseudo-normal then gives the
//! exact sign of the distance.
//!
//! The edges are found by sorting, not hashing: the same faces give the same
//! edges in the same order.

/// The edges of a mesh and how its faces meet along them.
#[derive(Debug)]
pub(super) struct Edges {
    /// For each face, the edges v0v1, v1v2, v2v0 as indices into the edges.
    pub(super) of_face: Vec<[u32; 3]>,
    /// The number of distinct edges.
    pub(super) count: usize,
    /// Edges of one face only.
    pub(super) boundary: usize,
    /// Edges of more than two faces.
    pub(super) non_manifold: usize,
    /// Edges of two faces that run along them the same way.
    pub(super) misoriented: usize,
}

impl Edges {
    /// Every edge joins two faces that run along it in opposite directions.
    pub(super) fn closed(&self) -> bool {
        self.boundary == 0 && self.non_manifold == 0 && self.misoriented == 0
    }

    /// One sentence for each way the mesh is not closed, with its count.
    pub(super) fn warnings(&self) -> Vec<String> {
        let consequence = "inside and outside come from the generalized winding number";
        let mut out = Vec::new();
        if self.boundary > 0 {
            out.push(format!(
                "the mesh is open: {} edges belong to one triangle only; {consequence}",
                self.boundary
            ));
        }
        if self.non_manifold > 0 {
            out.push(format!(
                "the mesh is not manifold: {} edges belong to more than two triangles; {consequence}",
                self.non_manifold
            ));
        }
        if self.misoriented > 0 {
            out.push(format!(
                "the mesh is not consistently oriented: along {} edges both triangles run the same way; {consequence}",
                self.misoriented
            ));
        }
        out
    }
}

/// The edges of `faces` (vertex indices) and how the faces meet along them.
pub(super) fn edges(faces: &[[u32; 3]]) -> Edges {
    let ends = |slot: u32| {
        let f = &faces[slot as usize / 3];
        let k = slot as usize % 3;
        (f[k], f[(k + 1) % 3])
    };
    let key = |slot: u32| {
        let (a, b) = ends(slot);
        (u64::from(a.min(b)) << 32) | u64::from(a.max(b))
    };
    // Every face's edges (face · 3 + k), grouped by their two vertices.
    let mut slots: Vec<u32> = (0..faces.len() as u32 * 3).collect();
    slots.sort_unstable_by_key(|&s| (key(s), s));
    let mut edges = Edges {
        of_face: vec![[0; 3]; faces.len()],
        count: 0,
        boundary: 0,
        non_manifold: 0,
        misoriented: 0,
    };
    for group in slots.chunk_by(|&a, &b| key(a) == key(b)) {
        for &s in group {
            edges.of_face[s as usize / 3][s as usize % 3] = edges.count as u32;
        }
        edges.count += 1;
        match group {
            [_] => edges.boundary += 1,
            [a, b] => {
                if ends(*a) == ends(*b) {
                    edges.misoriented += 1;
                }
            }
            _ => edges.non_manifold += 1,
        }
    }
    edges
}

/// The connected parts of a mesh (faces joined through shared vertices).
#[derive(Debug)]
pub(super) struct Parts {
    /// How many.
    pub(super) count: usize,
    /// Two parts' boxes overlap: one may lie inside or across another, where
    /// the closest triangle's pseudo-normal no longer tells inside from
    /// outside of their union.
    pub(super) overlapping: bool,
}

/// The connected parts of `faces` over `positions`.
pub(super) fn parts(positions: &[glam::Vec3], faces: &[[u32; 3]]) -> Parts {
    // Union-find over the vertices, each root the smallest index of its set.
    let mut parent: Vec<u32> = (0..positions.len() as u32).collect();
    fn root(parent: &mut [u32], mut i: u32) -> u32 {
        while parent[i as usize] != i {
            let up = parent[parent[i as usize] as usize];
            parent[i as usize] = up;
            i = up;
        }
        i
    }
    for f in faces {
        for k in 1..3 {
            let (a, b) = (root(&mut parent, f[0]), root(&mut parent, f[k]));
            parent[a.max(b) as usize] = a.min(b);
        }
    }
    // Each part's box, by its root.
    let empty = (glam::Vec3::INFINITY, glam::Vec3::NEG_INFINITY);
    let mut boxes = vec![empty; positions.len()];
    for f in faces {
        for &i in f {
            let r = root(&mut parent, i) as usize;
            let p = positions[i as usize];
            boxes[r] = (boxes[r].0.min(p), boxes[r].1.max(p));
        }
    }
    let mut boxes: Vec<_> = boxes.into_iter().filter(|b| b.0.x <= b.1.x).collect();
    // Sweep along x: each box against those that start before it ends.
    boxes.sort_unstable_by(|a, b| a.0.x.total_cmp(&b.0.x).then(a.1.x.total_cmp(&b.1.x)));
    let overlapping = (0..boxes.len()).any(|i| {
        let (lo, hi) = boxes[i];
        boxes[i + 1..]
            .iter()
            .take_while(|b| b.0.x <= hi.x)
            .any(|b| b.0.y <= hi.y && lo.y <= b.1.y && b.0.z <= hi.z && lo.z <= b.1.z)
    });
    Parts {
        count: boxes.len(),
        overlapping,
    }
}
