//! Known answers: a cube and an icosphere against their exact distances, the
//! tree against a search of every triangle on Spot, and every refusal.

use std::sync::Arc;

use glam::Vec3;

use super::*;
use crate::math::random::SplitMix64;

/// An axis-aligned cube of half size `h` about the origin, faces outward.
pub(crate) fn cube_obj(h: f32) -> String {
    let mut s = String::new();
    for i in 0..8 {
        let c = |bit: i32| if i & bit != 0 { h } else { -h };
        s += &format!("v {} {} {}\n", c(1), c(2), c(4));
    }
    // Each face counter-clockwise seen from outside (1-based vertex numbers).
    for f in [
        [1, 3, 4, 2], // z = -h
        [5, 6, 8, 7], // z = +h
        [1, 2, 6, 5], // y = -h
        [3, 7, 8, 4], // y = +h
        [1, 5, 7, 3], // x = -h
        [2, 4, 8, 6], // x = +h
    ] {
        s += &format!(
            "f {} {} {}\nf {} {} {}\n",
            f[0], f[1], f[2], f[0], f[2], f[3]
        );
    }
    s
}

fn load(text: &str) -> Result<Mesh, MeshError> {
    Mesh::from_obj("test.obj", text.as_bytes(), MeshLimits::default())
}

/// The exact signed distance to a box of half size `h` about the origin.
fn box_distance(p: Vec3, h: f32) -> f32 {
    let q = p.abs() - Vec3::splat(h);
    q.max(Vec3::ZERO).length() + q.max_element().min(0.0)
}

fn points(n: usize, extent: f32, seed: u64) -> Vec<Vec3> {
    let mut rng = SplitMix64::new(seed);
    (0..n)
        .map(|_| {
            Vec3::new(rng.next_f32(), rng.next_f32(), rng.next_f32()) * (2.0 * extent)
                - Vec3::splat(extent)
        })
        .collect()
}

#[test]
fn a_cube_has_the_exact_distance_of_a_box() {
    let mesh = load(&cube_obj(0.5)).unwrap();
    assert_eq!((mesh.triangle_count(), mesh.vertex_count()), (12, 8));
    for p in points(4000, 1.2, 1) {
        let (got, want) = (mesh.signed_distance(p), box_distance(p, 0.5));
        assert!((got - want).abs() < 1e-5, "{p}: {got} vs {want}");
    }
}

#[test]
fn an_icosphere_is_a_sphere_within_its_chord_error() {
    let r = 0.8;
    let mesh = load(&icosphere_obj(Vec3::ZERO, r, 3)).unwrap();
    assert_eq!(mesh.triangle_count(), 20 * 64);
    // The flat faces lie inside the sphere by at most r(1 - cos θ), θ the
    // largest angle from a face's centre to its corners (under 0.1 rad here: the
    // icosahedron's 1.11 rad edges halved three times, over √3).
    let sag = r * (1.0 - 0.1f32.cos());
    for p in points(4000, 1.5, 2) {
        let (got, want) = (mesh.signed_distance(p), p.length() - r);
        assert!(
            got >= want - 1e-5 && got <= want + sag,
            "{p}: {got} vs {want}"
        );
    }
}

#[test]
fn a_mesh_cube_is_solid_where_the_box_primitive_is() {
    // The box primitive's inner box (half size h - s/2) is the mesh cube;
    // outside it the mesh's density is the paper's falloff of the distance
    // to the cube, and it vanishes wherever the box primitive does.
    let (h, s) = (0.5, 0.2);
    let mesh = Arc::new(load(&cube_obj(h - s / 2.0)).unwrap());
    let soft = crate::field::soft::SoftMesh::new(mesh, Vec3::ZERO, 1.0, s);
    let boxed = crate::field::soft::SoftBox {
        centre: Vec3::ZERO,
        falloff: [crate::field::soft::Falloff::new(h, s); 3],
    };
    let falloff = crate::field::soft::Falloff::new(s / 2.0, s);
    for p in points(4000, 0.8, 3) {
        let d = box_distance(p, h - s / 2.0);
        let want = if d <= 0.0 {
            1.0
        } else {
            falloff.density(d * d)
        };
        let got = soft.density(p);
        assert!((got - want).abs() < 1e-4, "{p}: {got} vs {want}");
        assert_eq!(got == 1.0, boxed.density(p) == 1.0, "{p}");
        if boxed.density(p) == 0.0 {
            assert_eq!(got, 0.0, "{p}");
        }
    }
}

#[test]
fn projection_lands_on_the_surface() {
    let mesh = Arc::new(load(&cube_obj(0.5)).unwrap());
    let soft = crate::field::soft::SoftMesh::new(mesh, Vec3::new(1.0, 0.0, 0.0), 2.0, 0.1);
    for p in points(500, 2.5, 4) {
        let q = soft.project(p);
        let local = (q - Vec3::new(1.0, 0.0, 0.0)) / 2.0;
        assert!(box_distance(local, 0.5).abs() < 1e-5, "{p} → {q}");
    }
}

#[test]
fn the_tree_finds_what_a_search_of_every_triangle_finds() {
    let bytes = std::fs::read(concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/../scenes/mesh/meshes/spot.obj"
    ))
    .unwrap();
    let mesh = Mesh::from_obj("spot.obj", &bytes, MeshLimits::default()).unwrap();
    assert_eq!((mesh.triangle_count(), mesh.vertex_count()), (5856, 2930));
    for p in points(300, 1.2, 5) {
        let brute = mesh
            .triangles
            .iter()
            .map(|t| (p - closest_on_triangle(p, t.v).0).length_squared())
            .fold(f32::INFINITY, f32::min);
        assert_eq!(mesh.signed_distance(p).abs(), brute.sqrt(), "{p}");
    }
    // Far from the cow is outside; its belly's centre is inside.
    assert!(mesh.signed_distance(Vec3::new(0.0, 3.0, 0.0)) > 0.0);
    assert!(mesh.signed_distance(Vec3::new(0.0, 0.0, 0.2)) < 0.0);
    // Loading twice gives the same bits.
    let again = Mesh::from_obj("spot.obj", &bytes, MeshLimits::default()).unwrap();
    for p in points(300, 1.2, 6) {
        assert_eq!(mesh.closest(p), again.closest(p));
    }
}

#[test]
fn an_inside_out_mesh_is_turned_round() {
    let flipped: String = cube_obj(0.5)
        .lines()
        .map(|l| match l.strip_prefix("f ") {
            Some(f) => {
                let v: Vec<&str> = f.split(' ').collect();
                format!("f {} {} {}\n", v[0], v[2], v[1])
            }
            None => format!("{l}\n"),
        })
        .collect();
    let mesh = load(&flipped).unwrap();
    assert!(mesh.signed_distance(Vec3::ZERO) < 0.0);
    assert!(mesh.signed_distance(Vec3::splat(2.0)) > 0.0);
}

#[test]
fn bad_meshes_are_refused_with_the_path_and_the_reason() {
    let cube = cube_obj(0.5);
    let message = |text: &str| load(text).unwrap_err().to_string();
    // Open: the last face left out.
    let open: String = cube
        .lines()
        .take(cube.lines().count() - 1)
        .map(|l| format!("{l}\n"))
        .collect();
    let m = message(&open);
    assert!(m.starts_with("test.obj: the mesh is open"), "{m}");
    // Non-manifold: one face twice.
    let m = message(&format!("{cube}f 1 3 4\n"));
    assert!(
        m.contains("not manifold") || m.contains("run along it the same way"),
        "{m}"
    );
    // Two faces wound against the rest.
    let m = message(&cube.replacen("f 1 3 4\nf 1 4 2", "f 1 4 3\nf 1 2 4", 1));
    assert!(m.contains("not consistently oriented"), "{m}");
    // Degenerate.
    let m = message("v 0 0 0\nv 1 0 0\nv 2 0 0\nf 1 2 3\nf 1 3 2\n");
    assert!(m.contains("has no area"), "{m}");
    // A face naming a vertex that is not there.
    let m = message("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 9\n");
    assert!(m.starts_with("test.obj: "), "{m}");
    // No faces, not an OBJ.
    assert!(message("v 0 0 0\n").contains("no triangles"));
    assert!(message("\u{0}\u{1}garbage").starts_with("test.obj: "));
    // Over the cap.
    let e = Mesh::from_obj("big.obj", cube.as_bytes(), MeshLimits { max_triangles: 11 })
        .unwrap_err()
        .to_string();
    assert!(e.starts_with("big.obj: more than 11 triangles"), "{e}");
}
