//! Known answers: a cube and an icosphere against their exact distances, the
//! tree against a search of every triangle on Spot, and every refusal.

use std::sync::Arc;

use glam::Vec3;

use super::*;
use crate::math::random::SplitMix64;

mod teddy;

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

/// A cube of half size `h` about `centre` whose faces name their corners
/// from the end (`f -8 -6 -5`), so that several can follow one another in
/// one file, each its own object.
pub(crate) fn relative_cube_obj(name: &str, centre: Vec3, h: f32) -> String {
    let mut s = format!("o {name}\n");
    for i in 0..8 {
        let c = |bit: i32| if i & bit != 0 { h } else { -h };
        let p = centre + Vec3::new(c(1), c(2), c(4));
        s += &format!("v {} {} {}\n", p.x, p.y, p.z);
    }
    for l in cube_obj(h).lines().filter(|l| l.starts_with("f ")) {
        let f: Vec<String> = l[2..]
            .split(' ')
            .map(|i| (i.parse::<i32>().unwrap() - 9).to_string())
            .collect();
        s += &format!("f {}\n", f.join(" "));
    }
    s
}

/// `cube_obj(h)` without its top (y = +h): an open box.
pub(crate) fn open_cube_obj(h: f32) -> String {
    cube_obj(h).replace("f 3 7 8\nf 3 8 4\n", "")
}

/// A cube of half size `h` written as an exporter writes it: quads with
/// `v/vt/vn` corners, texture coordinates, normals, a material, smoothing.
pub(crate) fn quad_cube_obj(h: f32) -> String {
    let corners: String = cube_obj(h)
        .lines()
        .filter(|l| l.starts_with("v "))
        .map(|l| format!("{l}\n"))
        .collect();
    let mut s = format!(
        "# exported\nmtllib cube.mtl\no Cube\n{corners}vt 0 0\nvt 1 0\nvt 1 1\nvn 0 0 1\nusemtl skin\ns 1\n"
    );
    for f in [
        [1, 3, 4, 2],
        [5, 6, 8, 7],
        [1, 2, 6, 5],
        [3, 7, 8, 4],
        [1, 5, 7, 3],
        [2, 4, 8, 6],
    ] {
        s += &format!("f {}/1/1 {}/2/1 {}//1 {}/3\n", f[0], f[1], f[2], f[3]);
    }
    s
}

/// A hexagonal prism of radius `r` and half height `h` whose caps are
/// hexagons (6-gons) and whose sides are quads.
pub(crate) fn hexagonal_prism_obj(r: f32, h: f32) -> String {
    let mut s = String::new();
    for y in [-h, h] {
        for k in 0..6 {
            let a = k as f32 * std::f32::consts::FRAC_PI_3;
            s += &format!("v {} {} {}\n", r * a.cos(), y, r * a.sin());
        }
    }
    // Bottom seen from below, top from above: counter-clockwise outward.
    s += "f 1 2 3 4 5 6\nf 12 11 10 9 8 7\n";
    for k in 0..6 {
        let (a, b) = (k + 1, (k + 1) % 6 + 1);
        s += &format!("f {} {} {} {}\n", b, a, a + 6, b + 6);
    }
    s
}

/// Spot (Keenan Crane's cow), a closed mesh of 5,856 triangles.
pub(crate) fn spot() -> Mesh {
    let bytes = std::fs::read(concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/../scenes/mesh/meshes/spot.obj"
    ))
    .unwrap();
    Mesh::from_obj("spot.obj", &bytes, MeshLimits::default()).unwrap()
}

/// Teddy (scenes/mesh/meshes/teddy.obj, written by [`teddy::teddy_obj`]).
pub(crate) fn teddy() -> Mesh {
    let bytes = std::fs::read(TEDDY_PATH).unwrap();
    Mesh::from_obj("teddy.obj", &bytes, MeshLimits::default()).unwrap()
}

const TEDDY_PATH: &str = concat!(
    env!("CARGO_MANIFEST_DIR"),
    "/../scenes/mesh/meshes/teddy.obj"
);

/// Inside the box of half size `h` about `centre`, at least `margin` from
/// its faces (negative `margin`: outside by at least -margin).
fn in_box(p: Vec3, centre: Vec3, h: f32, margin: f32) -> bool {
    box_distance(p - centre, h) < -margin
}

/// The far field's largest error against the exact sum, in winding number
/// units, at β = 2 (Spot: 0.012 at worst over 2,000 points, 4·10⁻⁴ on
/// average): the bound the tests hold the tree to.
const WINDING_TOLERANCE: f32 = 0.02;

/// The bound on the mean error over many points.
const WINDING_MEAN_TOLERANCE: f32 = 1e-3;

#[test]
fn the_winding_number_is_one_inside_and_zero_outside_a_closed_mesh() {
    let r = 0.8;
    let mesh = load(&icosphere_obj(Vec3::ZERO, r, 3)).unwrap();
    let (mut inside, mut outside) = (0, 0);
    for p in points(4000, 1.5, 7) {
        let w = mesh.winding_number(p);
        if p.length() < 0.7 {
            assert!((w - 1.0).abs() < WINDING_TOLERANCE, "{p}: {w}");
            inside += 1;
        } else if p.length() > 0.85 {
            assert!(w.abs() < WINDING_TOLERANCE, "{p}: {w}");
            outside += 1;
        }
    }
    assert!(inside > 200 && outside > 3000, "{inside} {outside}");
}

#[test]
fn the_tree_agrees_with_the_exact_sum() {
    for mesh in [spot(), teddy(), load(&open_cube_obj(0.5)).unwrap()] {
        let corners: Vec<[Vec3; 3]> = mesh.triangles.iter().map(|t| t.v).collect();
        let (mut worst, mut sum) = (0f32, 0.0);
        let n = 2000;
        for p in points(n, 1.5, 8) {
            let exact = winding::WindingTree::exact(&corners, p);
            let exact = if mesh.flipped { -exact } else { exact };
            let error = (mesh.winding_number(p) - exact).abs();
            worst = worst.max(error);
            sum += error;
        }
        let mean = sum / n as f32;
        assert!(
            worst < WINDING_TOLERANCE && mean < WINDING_MEAN_TOLERANCE,
            "{mesh:?}: {worst} {mean}"
        );
    }
}

#[test]
fn the_winding_sign_agrees_with_the_pseudo_normal_on_spot() {
    let mesh = spot();
    assert!(mesh.is_closed() && mesh.warnings().is_empty(), "{mesh:?}");
    let mut checked = 0;
    for p in points(6000, 1.2, 9) {
        let d = mesh.signed_distance(p);
        assert_eq!(mesh.is_inside(p), d < 0.0, "{p}: {d}");
        if d.abs() > 0.01 {
            assert_eq!(mesh.winding_number(p) >= 0.5, d < 0.0, "{p}: {d}");
            checked += 1;
        }
    }
    assert!(checked > 5000, "{checked}");
}

#[test]
fn an_open_cube_is_inside_below_its_missing_top() {
    let h = 0.5;
    let mesh = load(&open_cube_obj(h)).unwrap();
    assert!(!mesh.is_closed());
    assert_eq!(
        mesh.warnings(),
        [
            "the mesh is open: 4 edges belong to one triangle only; inside and outside come from the generalized winding number"
        ]
    );
    let (mut inside, mut outside) = (0, 0);
    for p in points(4000, 1.0, 10) {
        let d = mesh.signed_distance(p);
        if in_box(p, Vec3::ZERO, h, 0.01) && p.y < 0.2 {
            assert!(d < 0.0 && mesh.is_inside(p), "{p}: {d}");
            // The nearest of the four walls and the floor.
            let walls = (h - p.x.abs()).min(h - p.z.abs()).min(p.y + h);
            assert!((d + walls).abs() < 1e-5, "{p}: {d} vs {walls}");
            inside += 1;
        } else if !in_box(p, Vec3::ZERO, h, -0.01) {
            assert!(d > 0.0 && !mesh.is_inside(p), "{p}: {d}");
            outside += 1;
        }
    }
    assert!(inside > 100 && outside > 1000, "{inside} {outside}");
}

#[test]
fn overlapping_parts_make_their_union() {
    let (a, b, h) = (Vec3::ZERO, Vec3::new(0.4, 0.3, 0.0), 0.5);
    let text = relative_cube_obj("A", a, h) + &relative_cube_obj("B", b, h);
    let mesh = load(&text).unwrap();
    assert_eq!(
        (
            mesh.triangle_count(),
            mesh.vertex_count(),
            mesh.part_count()
        ),
        (24, 16, 2)
    );
    // Closed, but one part crosses the other: the pseudo-normal of the
    // closest face no longer gives the union's sign.
    assert!(mesh.warnings().is_empty() && !mesh.is_closed(), "{mesh:?}");
    let (mut inside, mut outside) = (0, 0);
    for p in points(4000, 1.2, 11) {
        let d = mesh.signed_distance(p);
        if in_box(p, a, h, 0.01) || in_box(p, b, h, 0.01) {
            assert!(d < 0.0 && mesh.is_inside(p), "{p}: {d}");
            inside += 1;
        } else if !in_box(p, a, h, -0.01) && !in_box(p, b, h, -0.01) {
            assert!(d > 0.0 && !mesh.is_inside(p), "{p}: {d}");
            outside += 1;
        }
    }
    assert!(inside > 300 && outside > 1000, "{inside} {outside}");
}

#[test]
fn quads_n_gons_and_objects_are_fanned_in_file_order() {
    // Quads with every corner form, and what the loader skips.
    let quads = load(&quad_cube_obj(0.5)).unwrap();
    let triangles = load(&cube_obj(0.5)).unwrap();
    assert_eq!(quads.triangles, triangles.triangles);
    assert!(quads.is_closed() && quads.warnings().is_empty());
    // Hexagons: four triangles each.
    let prism = load(&hexagonal_prism_obj(0.5, 0.3)).unwrap();
    assert_eq!(
        (prism.triangle_count(), prism.vertex_count()),
        (2 * 4 + 6 * 2, 12)
    );
    assert!(prism.is_closed() && prism.warnings().is_empty());
    assert!(prism.signed_distance(Vec3::ZERO) < -0.29);
    assert!((prism.signed_distance(Vec3::new(0.0, 0.5, 0.0)) - 0.2).abs() < 1e-6);
    // Two objects apart, named from the end: one closed mesh of two parts.
    let (a, b) = (Vec3::new(-1.0, 0.0, 0.0), Vec3::new(1.0, 0.0, 0.0));
    let two = load(&(relative_cube_obj("A", a, 0.5) + &relative_cube_obj("B", b, 0.5))).unwrap();
    assert_eq!(
        (two.triangle_count(), two.vertex_count(), two.part_count()),
        (24, 16, 2)
    );
    assert!(two.is_closed() && two.warnings().is_empty());
    for p in points(2000, 2.0, 12) {
        let want = box_distance(p - a, 0.5).min(box_distance(p - b, 0.5));
        assert!((two.signed_distance(p) - want).abs() < 1e-5, "{p}");
    }
}

#[test]
fn the_teddy_file_is_what_its_helper_writes() {
    let text = teddy::teddy_obj();
    if std::env::var_os("HYPERTEXTURE_BLESS").is_some_and(|v| v == "1") {
        std::fs::write(TEDDY_PATH, &text).unwrap();
    }
    let stored = std::fs::read_to_string(TEDDY_PATH).unwrap();
    assert!(
        stored == text,
        "{TEDDY_PATH} differs from teddy_obj(): run HYPERTEXTURE_BLESS=1 cargo test -p hypertexture --lib mesh::tests::the_teddy"
    );
}

#[test]
fn teddy_loads_open_and_overlapping_with_an_inside() {
    let mesh = teddy();
    // Seven objects, none welded to another.
    assert_eq!(mesh.part_count(), 7);
    assert_eq!(
        mesh.warnings(),
        [format!(
            "the mesh is open: {} edges belong to one triangle only; inside and outside come from the generalized winding number",
            2 * teddy::EYE_SEGMENTS
        )]
    );
    assert!(!mesh.is_closed());
    // The head's middle, an ear, the nose tip and an eye's bulge are inside;
    // beyond them is outside.
    for p in [
        Vec3::ZERO,
        Vec3::new(0.36, 0.44, -0.04),
        Vec3::new(0.0, -0.04, 0.62),
    ] {
        assert!(mesh.is_inside(p) && mesh.signed_distance(p) < 0.0, "{p}");
    }
    for p in [
        Vec3::new(0.0, 3.0, 0.0),
        Vec3::new(0.0, 0.5, 0.0),
        Vec3::new(0.0, -0.04, 0.7),
        Vec3::new(0.6, 0.0, 0.0),
    ] {
        assert!(!mesh.is_inside(p) && mesh.signed_distance(p) > 0.0, "{p}");
    }
    // Between an eye's open half-sphere and the head it is set into: only
    // the winding number of the eye's faces makes that inside.
    for side in [-1.0, 1.0] {
        let (on_head, outward) = teddy::eye_axis(side);
        let bulge = on_head + outward * 0.03;
        assert!(mesh.is_inside(bulge), "{bulge}");
        assert!(!mesh.is_inside(on_head + outward * 0.07), "{bulge}");
    }
    // The same bits on a second load.
    let again = teddy();
    for p in points(300, 0.8, 13) {
        assert_eq!(mesh.closest(p), again.closest(p));
        assert_eq!(
            mesh.winding_number(p).to_bits(),
            again.winding_number(p).to_bits()
        );
    }
}

#[test]
fn bad_meshes_are_refused_and_imperfect_ones_warned_about() {
    let cube = cube_obj(0.5);
    let message = |text: &str| load(text).unwrap_err().to_string();
    let warnings = |text: &str| load(text).unwrap().warnings().join("\n");
    // Open: the last face left out.
    let open: String = cube
        .lines()
        .take(cube.lines().count() - 1)
        .map(|l| format!("{l}\n"))
        .collect();
    let w = warnings(&open);
    assert!(
        w.starts_with("the mesh is open: 3 edges belong to one triangle only"),
        "{w}"
    );
    // Non-manifold: one face twice.
    let w = warnings(&format!("{cube}f 1 3 4\n"));
    assert!(
        w.contains("not manifold: 3 edges belong to more than two triangles"),
        "{w}"
    );
    // Two faces wound against the rest.
    let w = warnings(&cube.replacen("f 1 3 4\nf 1 4 2", "f 1 4 3\nf 1 2 4", 1));
    assert!(
        w.contains("not consistently oriented: along 4 edges"),
        "{w}"
    );
    // A degenerate triangle is left out.
    let w = warnings(&format!("{cube}v 1.5 -0.5 -0.5\nf 1 2 9\n"));
    assert!(
        w.starts_with("1 triangles have no area and are left out"),
        "{w}"
    );
    let m = message("v 0 0 0\nv 1 0 0\nv 2 0 0\nf 1 2 3\nf 1 3 2\n");
    assert!(m.contains("none of the 2 triangles has an area"), "{m}");
    // A face naming a vertex that is not there, or vertex 0, or before the
    // first, or too few corners.
    let m = message("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 9\n");
    assert_eq!(
        m,
        "test.obj: a face names vertex 9 but the file has 3 vertices"
    );
    let m = message("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 0 1 2\n");
    assert!(
        m.starts_with("test.obj: line 4: a face names vertex 0"),
        "{m}"
    );
    let m = message("v 0 0 0\nv 1 0 0\nv 0 1 0\nf -1 -2 -4\n");
    assert!(
        m.starts_with("test.obj: line 4: a face names vertex -4, before the first"),
        "{m}"
    );
    let m = message("v 0 0 0\nv 1 0 0\nf 1 2\n");
    assert!(
        m.starts_with("test.obj: line 3: a face needs three corners or more"),
        "{m}"
    );
    let m = message("v 0 0 0\nv 1 0 x\n");
    assert!(
        m.starts_with("test.obj: line 2: the coordinate `x` is not a number"),
        "{m}"
    );
    let m = message("v 0 0 0\nv 1 0\n");
    assert!(
        m.contains("line 2: a vertex needs three coordinates"),
        "{m}"
    );
    let m = message("v 0 0 inf\n");
    assert!(m.contains("line 1: a vertex is not finite"), "{m}");
    let m = message("v 0 0 0\nf x/1 1 1\n");
    assert!(m.contains("line 2: "), "{m}");
    // No faces, not an OBJ.
    assert!(message("v 0 0 0\n").contains("no triangles"));
    let m = message("\u{0}\u{1}garbage");
    assert!(
        m.starts_with("test.obj: line 1: `\\0\\u{1}garbage` is not an OBJ statement"),
        "{m}"
    );
    let m = message("v 0 0 0\n\u{ff}\n");
    assert!(m.starts_with("test.obj: line 2: "), "{m}");
    let m = Mesh::from_obj("b.obj", b"v 0 0 0\n\xff\xfe\n", MeshLimits::default())
        .unwrap_err()
        .to_string();
    assert_eq!(m, "b.obj: line 2: not text (OBJ is a text format)");
    // Over the cap.
    let e = Mesh::from_obj("big.obj", cube.as_bytes(), MeshLimits { max_triangles: 11 })
        .unwrap_err()
        .to_string();
    assert!(e.starts_with("big.obj: more than 11 triangles"), "{e}");
}
