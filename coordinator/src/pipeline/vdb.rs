//! A minimal OpenVDB writer: sparse float and vec3s grids in the standard
//! tree layout (root → internal 32³ → internal 16³ → leaf 8³, the type
//! OpenVDB calls `Tree_float_5_4_3`), file format version 224, uncompressed,
//! values stored as 32-bit floats (no half floats, so values read back
//! exactly).
//!
//! The layout follows OpenVDB's `io::Archive::write`: a header (magic,
//! versions, a grid-offsets flag, a 36-character unique tag), the file's
//! metadata, the grid count, then per grid its descriptor (name, type,
//! instance parent, three stream offsets), compression flags, metadata,
//! transform (`UniformScaleTranslateMap`), topology (every node's masks,
//! internal nodes' tile values) and the leaves' values. Everything is
//! little-endian, as OpenVDB writes it on every platform it supports.

use std::collections::BTreeMap;

/// Voxels along a leaf's edge.
pub const LEAF_DIM: i32 = 8;
/// Voxels in a leaf.
pub const LEAF_VOXELS: usize = 512;
/// The file format version written (OpenVDB 6 to 12 read it).
const FILE_VERSION: u32 = 224;
/// OpenVDB's magic number, "VDB " as a little-endian int64.
const MAGIC: i64 = 0x5644_4220;
/// Each internal node's no-mask, all-values flag (`NO_MASK_AND_ALL_VALS`):
/// every value follows in full.
const ALL_VALUES: u8 = 6;

/// A voxel type OpenVDB knows by name.
pub trait Voxel: Copy + PartialEq + Send + Sync + 'static {
    /// The tree's type name in the file (`Tree_float_5_4_3`).
    const TREE_TYPE: &'static str;
    /// The zero value: background and inactive voxels.
    const ZERO: Self;
    /// Appends the value's bytes (little-endian 32-bit floats).
    fn put(&self, out: &mut Vec<u8>);
}

impl Voxel for f32 {
    const TREE_TYPE: &'static str = "Tree_float_5_4_3";
    const ZERO: Self = 0.0;
    fn put(&self, out: &mut Vec<u8>) {
        out.extend_from_slice(&self.to_le_bytes());
    }
}

impl Voxel for [f32; 3] {
    const TREE_TYPE: &'static str = "Tree_vec3s_5_4_3";
    const ZERO: Self = [0.0; 3];
    fn put(&self, out: &mut Vec<u8>) {
        for c in self {
            out.extend_from_slice(&c.to_le_bytes());
        }
    }
}

/// An 8³ leaf: its origin (index coordinates, multiples of 8), which voxels
/// are active, and every voxel's value (inactive ones are zero). Voxel
/// (x, y, z) of the leaf is at offset `64·x + 8·y + z`, OpenVDB's order.
#[derive(Clone, Debug, PartialEq)]
pub struct Leaf<V> {
    /// Index coordinates of voxel (0, 0, 0).
    pub origin: [i32; 3],
    /// Bit `n % 64` of word `n / 64` is set when voxel n is active.
    pub mask: [u64; 8],
    /// The values, `LEAF_VOXELS` of them.
    pub values: Vec<V>,
}

impl<V: Voxel> Leaf<V> {
    /// A leaf at `origin` with every voxel inactive.
    pub fn empty(origin: [i32; 3]) -> Leaf<V> {
        Leaf {
            origin,
            mask: [0; 8],
            values: vec![V::ZERO; LEAF_VOXELS],
        }
    }

    /// Sets voxel `n` to `value` and makes it active.
    pub fn set(&mut self, n: usize, value: V) {
        self.values[n] = value;
        self.mask[n / 64] |= 1 << (n % 64);
    }

    /// Active voxels.
    pub fn active(&self) -> u64 {
        self.mask.iter().map(|w| u64::from(w.count_ones())).sum()
    }
}

/// The map from index to world space: world = translation + voxel_size · ijk
/// (OpenVDB's `UniformScaleTranslateMap`; a voxel's value is at its centre).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Transform {
    /// The edge of a voxel in world units.
    pub voxel_size: f64,
    /// The world position of voxel (0, 0, 0).
    pub translation: [f64; 3],
}

/// A named grid: its class (`fog volume` for densities, OpenVDB's
/// `GRID_FOG_VOLUME`, or `unknown`) and its leaves.
#[derive(Clone, Debug)]
pub struct Grid<V> {
    /// The grid's name (`density`, `color`).
    pub name: String,
    /// OpenVDB's grid class metadata.
    pub class: &'static str,
    /// The leaves, any order; at most one per origin.
    pub leaves: Vec<Leaf<V>>,
}

/// A grid of any voxel type the writer knows.
#[derive(Clone, Debug)]
pub enum AnyGrid {
    /// Scalar floats.
    Float(Grid<f32>),
    /// Three floats a voxel (OpenVDB's `Vec3SGrid`).
    Vec3(Grid<[f32; 3]>),
}

/// Metadata values the writer stores.
#[derive(Clone, Debug)]
pub enum Meta {
    /// OpenVDB's `string`.
    String(String),
    /// OpenVDB's `int64`.
    Int64(i64),
}

/// The whole file: every grid shares the transform.
pub fn encode(file_meta: &[(&str, Meta)], transform: &Transform, grids: &[AnyGrid]) -> Vec<u8> {
    let mut out = Vec::new();
    out.extend_from_slice(&MAGIC.to_le_bytes());
    put_u32(&mut out, FILE_VERSION);
    // The library version that writes 224 files.
    put_u32(&mut out, 10);
    put_u32(&mut out, 0);
    // Grid offsets follow each descriptor.
    out.push(1);
    // A unique tag OpenVDB compares to detect a file that changed; fixed, so
    // that equal bakes are equal files.
    out.extend_from_slice(b"00000000-0000-0000-0000-000000000000");
    put_meta(&mut out, file_meta);
    put_u32(&mut out, grids.len() as u32);
    for grid in grids {
        match grid {
            AnyGrid::Float(g) => put_grid(&mut out, g, transform),
            AnyGrid::Vec3(g) => put_grid(&mut out, g, transform),
        }
    }
    out
}

fn put_u32(out: &mut Vec<u8>, v: u32) {
    out.extend_from_slice(&v.to_le_bytes());
}

fn put_string(out: &mut Vec<u8>, s: &str) {
    put_u32(out, s.len() as u32);
    out.extend_from_slice(s.as_bytes());
}

fn put_f64s(out: &mut Vec<u8>, v: [f64; 3]) {
    for c in v {
        out.extend_from_slice(&c.to_le_bytes());
    }
}

fn put_meta(out: &mut Vec<u8>, meta: &[(&str, Meta)]) {
    put_u32(out, meta.len() as u32);
    for (name, value) in meta {
        put_string(out, name);
        match value {
            Meta::String(s) => {
                put_string(out, "string");
                put_string(out, s);
            }
            Meta::Int64(v) => {
                put_string(out, "int64");
                put_u32(out, 8);
                out.extend_from_slice(&v.to_le_bytes());
            }
        }
    }
}

/// The origin of the node of `2^log2` voxels a side that holds `origin`.
fn node_origin(origin: [i32; 3], log2: u32) -> [i32; 3] {
    let mask = !((1i32 << log2) - 1);
    origin.map(|c| c & mask)
}

/// Offset of the child at `child` within the node at `parent`: x slowest.
fn child_offset(parent: [i32; 3], child: [i32; 3], node_log2: u32, child_log2: u32) -> usize {
    let d = |a: usize| ((child[a] - parent[a]) >> child_log2) as usize;
    let n = node_log2 - child_log2;
    (d(0) << (2 * n)) | (d(1) << n) | d(2)
}

/// A bit mask of `bits` bits, as u64 words.
fn mask_bytes(out: &mut Vec<u8>, set: impl Iterator<Item = usize>, bits: usize) {
    let mut words = vec![0u64; bits / 64];
    for n in set {
        words[n / 64] |= 1 << (n % 64);
    }
    for w in words {
        out.extend_from_slice(&w.to_le_bytes());
    }
}

/// The tree as nested sorted maps: upper node origin → lower node origin →
/// leaves, each level in OpenVDB's order (the root by origin x, y, z; each
/// internal node by child offset, which for children sorted by origin is the
/// same order).
type Tree<'a, V> = BTreeMap<[i32; 3], BTreeMap<[i32; 3], Vec<&'a Leaf<V>>>>;

fn put_grid<V: Voxel>(out: &mut Vec<u8>, grid: &Grid<V>, transform: &Transform) {
    let mut tree: Tree<V> = BTreeMap::new();
    for leaf in &grid.leaves {
        tree.entry(node_origin(leaf.origin, 12))
            .or_default()
            .entry(node_origin(leaf.origin, 7))
            .or_default()
            .push(leaf);
    }
    for lower in tree.values_mut() {
        for leaves in lower.values_mut() {
            leaves.sort_by_key(|l| l.origin);
        }
    }
    // Descriptor: unique name, type, no instance parent.
    put_string(out, &grid.name);
    put_string(out, V::TREE_TYPE);
    put_string(out, "");
    let offsets_at = out.len();
    out.extend_from_slice(&[0; 24]);
    let grid_pos = out.len();
    // No compression.
    put_u32(out, 0);
    put_meta(
        out,
        &[
            ("class", Meta::String(grid.class.into())),
            ("name", Meta::String(grid.name.clone())),
        ],
    );
    put_string(out, "UniformScaleTranslateMap");
    let h = transform.voxel_size;
    put_f64s(out, transform.translation);
    put_f64s(out, [h; 3]); // scale
    put_f64s(out, [h.abs(); 3]); // voxel size
    put_f64s(out, [1.0 / h; 3]); // inverse scale
    put_f64s(out, [1.0 / (h * h); 3]); // inverse scale squared
    put_f64s(out, [0.5 / h; 3]); // inverse of twice the scale
    // Topology: one buffer, the background, no root tiles.
    put_u32(out, 1);
    V::ZERO.put(out);
    put_u32(out, 0);
    put_u32(out, tree.len() as u32);
    for (upper, lower) in &tree {
        for c in upper {
            out.extend_from_slice(&c.to_le_bytes());
        }
        put_internal::<V>(out, *upper, 12, 7, lower.keys().copied());
        for (origin, leaves) in lower {
            put_internal::<V>(out, *origin, 7, 3, leaves.iter().map(|l| l.origin));
            for leaf in leaves {
                for w in leaf.mask {
                    out.extend_from_slice(&w.to_le_bytes());
                }
            }
        }
    }
    let block_pos = out.len();
    for leaves in tree.values().flat_map(BTreeMap::values) {
        for leaf in leaves {
            for w in leaf.mask {
                out.extend_from_slice(&w.to_le_bytes());
            }
            out.push(ALL_VALUES);
            for v in &leaf.values {
                v.put(out);
            }
        }
    }
    let end_pos = out.len();
    let mut offsets = Vec::with_capacity(24);
    for p in [grid_pos, block_pos, end_pos] {
        offsets.extend_from_slice(&(p as i64).to_le_bytes());
    }
    out[offsets_at..offsets_at + 24].copy_from_slice(&offsets);
}

/// An internal node's topology: child mask, value mask (no active tiles),
/// and its tile values (all zero: background) behind the all-values flag.
fn put_internal<V: Voxel>(
    out: &mut Vec<u8>,
    origin: [i32; 3],
    log2: u32,
    child_log2: u32,
    children: impl Iterator<Item = [i32; 3]>,
) {
    let bits = 1usize << (3 * (log2 - child_log2));
    mask_bytes(
        out,
        children.map(|c| child_offset(origin, c, log2, child_log2)),
        bits,
    );
    mask_bytes(out, std::iter::empty(), bits);
    out.push(ALL_VALUES);
    for _ in 0..bits {
        V::ZERO.put(out);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn child_offsets_run_x_slowest() {
        assert_eq!(child_offset([0; 3], [0, 0, 8], 7, 3), 1);
        assert_eq!(child_offset([0; 3], [0, 8, 0], 7, 3), 16);
        assert_eq!(child_offset([0; 3], [8, 0, 0], 7, 3), 256);
        assert_eq!(
            child_offset([-4096; 3], [-4096 + 128, -4096, -4096], 12, 7),
            1024
        );
        assert_eq!(node_origin([-8, 130, 4095], 7), [-128, 128, 3968]);
    }

    #[test]
    fn a_file_has_the_header_and_offsets_that_point_inside_it() {
        let mut leaf = Leaf::empty([8, 0, -8]);
        leaf.set(3, 0.5f32);
        let grid = AnyGrid::Float(Grid {
            name: "density".into(),
            class: "fog volume",
            leaves: vec![leaf],
        });
        let t = Transform {
            voxel_size: 0.25,
            translation: [1.0, 2.0, 3.0],
        };
        let bytes = encode(&[("creator", Meta::String("test".into()))], &t, &[grid]);
        assert_eq!(&bytes[..8], &MAGIC.to_le_bytes());
        assert_eq!(&bytes[8..12], &224u32.to_le_bytes());
        // The end offset of the only grid is the file's end.
        let tail = &bytes[bytes.len() - 2113..];
        assert_eq!(tail[64], ALL_VALUES);
        assert_eq!(&tail[65 + 12..65 + 16], &0.5f32.to_le_bytes());
        let find = |needle: &[u8]| bytes.windows(needle.len()).position(|w| w == needle);
        let type_at = find(b"Tree_float_5_4_3").expect("tree type written");
        let offsets = type_at + 16 + 4;
        let end = i64::from_le_bytes(bytes[offsets + 16..offsets + 24].try_into().expect("8"));
        assert_eq!(end as usize, bytes.len());
    }
}
