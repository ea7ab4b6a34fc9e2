//! Wavefront OBJ text read into welded positions and triangles.
//!
//! Read: `v x y z` (a fourth coordinate or a colour after it is ignored) and
//! `f` with three or more corners, each `v`, `v/vt`, `v//vn` or `v/vt/vn`,
//! its position index counted from 1, or from the end of the positions read
//! so far when negative. A polygon is fanned into triangles from its first
//! corner, in file order. Objects and groups (`o`, `g`) all join one mesh.
//! Statements that do not shape a density (`vt`, `vn`, `vp`, `usemtl`,
//! `mtllib`, `s`, `l`, `p` and the rest of the format's keywords) are
//! skipped.
//!
//! Positions with the same coordinates are welded into one vertex (−0 and +0
//! are one), numbered in the order faces first name them; positions no face
//! names are dropped. Nothing here hashes with random state: the same text
//! gives the same vertices and triangles in the same order.

use glam::Vec3;

/// The mesh an OBJ file describes.
#[derive(Debug)]
pub(super) struct Obj {
    /// Welded positions, in the order faces first name them.
    pub(super) positions: Vec<Vec3>,
    /// Triangles as indices into `positions`, in file order.
    pub(super) faces: Vec<[u32; 3]>,
}

/// Reads `bytes` as OBJ text. The error names the line (from 1) and what is
/// wrong with it.
pub(super) fn read(bytes: &[u8], max_triangles: usize) -> Result<Obj, String> {
    let mut raw: Vec<Vec3> = Vec::new();
    // Triangles as indices into `raw`, checked against it at the end (a
    // face may name a position written after it).
    let mut corners: Vec<[u32; 3]> = Vec::new();
    let mut polygon: Vec<u32> = Vec::new();
    for (n, line) in bytes.split(|&b| b == b'\n').enumerate() {
        let at = |message: String| format!("line {}: {message}", n + 1);
        let line =
            std::str::from_utf8(line).map_err(|_| at("not text (OBJ is a text format)".into()))?;
        let line = line.split('#').next().unwrap_or("");
        let mut words = line.split_ascii_whitespace();
        let Some(keyword) = words.next() else {
            continue;
        };
        match keyword {
            "v" => raw.push(vertex(&mut words).map_err(at)?),
            "f" => {
                polygon.clear();
                for word in words {
                    polygon.push(corner(word, raw.len()).map_err(at)?);
                }
                if polygon.len() < 3 {
                    return Err(at(format!(
                        "a face needs three corners or more, not {}",
                        polygon.len()
                    )));
                }
                for k in 1..polygon.len() - 1 {
                    corners.push([polygon[0], polygon[k], polygon[k + 1]]);
                }
                if corners.len() > max_triangles {
                    return Err(format!(
                        "more than {max_triangles} triangles, the most a mesh may have here"
                    ));
                }
            }
            _ if keyword
                .bytes()
                .all(|b| b.is_ascii_alphabetic() || b == b'_') => {}
            _ => {
                return Err(at(format!(
                    "`{}` is not an OBJ statement",
                    keyword.escape_debug()
                )));
            }
        }
    }
    if corners.is_empty() {
        return Err("no triangles: a mesh needs faces (`f` lines)".into());
    }
    if let Some(&i) = corners.iter().flatten().find(|&&i| i as usize >= raw.len()) {
        return Err(format!(
            "a face names vertex {} but the file has {} vertices",
            i as u64 + 1,
            raw.len()
        ));
    }
    let (positions, faces) = weld(&raw, &corners);
    Ok(Obj { positions, faces })
}

/// The position of a `v` statement: three finite numbers.
fn vertex<'a>(words: &mut impl Iterator<Item = &'a str>) -> Result<Vec3, String> {
    let mut xyz = [0f32; 3];
    for c in &mut xyz {
        let word = words
            .next()
            .ok_or("a vertex needs three coordinates (`v x y z`)")?;
        *c = word
            .parse()
            .map_err(|_| format!("the coordinate `{}` is not a number", word.escape_debug()))?;
    }
    let v = Vec3::from_array(xyz);
    if !v.is_finite() {
        return Err(format!("a vertex is not finite ({v})"));
    }
    Ok(v)
}

/// The 0-based position index of one corner of a face (`v`, `v/vt`,
/// `v//vn`, `v/vt/vn`), `count` positions having been read before it.
fn corner(word: &str, count: usize) -> Result<u32, String> {
    let index = word.split('/').next().unwrap_or("");
    let bad = || {
        format!(
            "the face corner `{}` does not start with a vertex number",
            word.escape_debug()
        )
    };
    let i: i64 = index.parse().map_err(|_| bad())?;
    let resolved = match i {
        0 => return Err("a face names vertex 0 (vertices are counted from 1)".into()),
        i if i > 0 => i - 1,
        i => {
            let from_end = count as i64 + i;
            if from_end < 0 {
                return Err(format!(
                    "a face names vertex {i}, before the first of the {count} vertices read so far"
                ));
            }
            from_end
        }
    };
    u32::try_from(resolved).map_err(|_| format!("a face names vertex {i}, beyond any mesh"))
}

/// Welds equal positions: the positions the faces name, each once, in the
/// order faces first name them, and the faces renumbered.
fn weld(raw: &[Vec3], corners: &[[u32; 3]]) -> (Vec<Vec3>, Vec<[u32; 3]>) {
    // -0 and +0 are one position.
    let key = |i: u32| (raw[i as usize] + Vec3::ZERO).to_array().map(f32::to_bits);
    // Every raw position with its group: the first raw index of its key.
    let mut sorted: Vec<u32> = (0..raw.len() as u32).collect();
    sorted.sort_unstable_by_key(|&i| (key(i), i));
    let mut group = vec![0u32; raw.len()];
    for pair in sorted.chunk_by(|&a, &b| key(a) == key(b)) {
        for &i in pair {
            group[i as usize] = pair[0];
        }
    }
    let mut welded = vec![u32::MAX; raw.len()];
    let mut positions = Vec::new();
    let faces = corners
        .iter()
        .map(|f| {
            f.map(|i| {
                let g = group[i as usize] as usize;
                if welded[g] == u32::MAX {
                    welded[g] = positions.len() as u32;
                    positions.push(raw[i as usize]);
                }
                welded[g]
            })
        })
        .collect();
    (positions, faces)
}
