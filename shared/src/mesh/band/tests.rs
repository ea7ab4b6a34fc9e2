//! The field against the exact distance: its error over the soft region,
//! its classes outside the band, its determinism and its limits.

use super::*;
use crate::math::random::SplitMix64;
use crate::mesh::icosphere_obj;

fn spot() -> Mesh {
    let bytes = std::fs::read(concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/../scenes/mesh/meshes/spot.obj"
    ))
    .unwrap();
    Mesh::from_obj("spot.obj", &bytes, Default::default()).unwrap()
}

fn icosphere() -> Mesh {
    let obj = icosphere_obj(Vec3::new(0.1, 0.0, -0.2), 0.5, 4);
    Mesh::from_obj("icosphere.obj", obj.as_bytes(), Default::default()).unwrap()
}

/// The field of softness `s` with the scenes' default voxel.
fn spec(s: f32) -> BandSpec {
    let voxel = s / crate::desc::FIELD_VOXELS_PER_SOFTNESS;
    BandSpec {
        voxel,
        outer: s,
        inner: 2.0 * voxel,
        max_bytes: DEFAULT_MAX_FIELD_BYTES,
    }
}

/// Random points of the mesh's box grown by `s`.
fn points(mesh: &Mesh, s: f32, n: usize, seed: u64) -> Vec<Vec3> {
    let (lo, hi) = mesh.bounds();
    let (lo, hi) = (lo - Vec3::splat(s), hi + Vec3::splat(s));
    let mut r = SplitMix64::new(seed);
    (0..n)
        .map(|_| lo + Vec3::new(r.next_f32(), r.next_f32(), r.next_f32()) * (hi - lo))
        .collect()
}

#[test]
fn a_field_on_an_icosphere_is_close_to_the_exact_distance() {
    let (mesh, s) = (icosphere(), 0.1);
    let band = Band::build(&mesh, &spec(s)).unwrap();
    let e = band.error(&mesh, s, 8000, 3);
    eprintln!("icosphere: {e:?}");
    assert_eq!((e.points, e.missed), (8000, 0), "{e:?}");
    assert!(e.distance[0] < 0.01 && e.distance[1] < 0.003, "{e:?}");
    assert!(e.point[0] < 0.06 && e.point[1] < 0.015, "{e:?}");
}

#[test]
fn a_field_on_spot_is_close_to_the_exact_distance() {
    let (mesh, s) = (spot(), 0.07);
    let band = Band::build(&mesh, &spec(s)).unwrap();
    let e = band.error(&mesh, s, 8000, 3);
    eprintln!("spot: {e:?}");
    assert_eq!((e.points, e.missed), (8000, 0), "{e:?}");
    // The distance is smooth but at the creases; the closest point jumps
    // across the medial axis (between a leg and the belly, say), where a
    // cell's corners see different parts of the surface.
    assert!(e.distance[0] < 0.12 && e.distance[1] < 0.008, "{e:?}");
    assert!(e.point[0] < 2.5 && e.point[1] < 0.06, "{e:?}");
}

#[test]
fn outside_the_band_the_class_is_the_exact_one() {
    let (mesh, s) = (spot(), 0.07);
    let band = Band::build(&mesh, &spec(s)).unwrap();
    let (mut outside, mut inside) = (0, 0);
    for x in points(&mesh, 0.3, 20_000, 4) {
        let d = mesh.signed_distance(x);
        match band.sample(x) {
            Sample::Outside => {
                assert!(d >= s, "{x}: outside the band at {d}");
                outside += 1;
            }
            Sample::Inside => {
                assert!(d < 0.0, "{x}: inside the mesh at {d}");
                inside += 1;
            }
            Sample::Near { .. } => {}
        }
    }
    assert!(
        outside > 1000 && inside > 100,
        "{outside} outside, {inside} inside"
    );
}

#[test]
fn the_build_gives_the_same_bits_on_any_number_of_threads() {
    let (mesh, s) = (icosphere(), 0.1);
    let one = Band::build_on(&mesh, &spec(s), 1).unwrap();
    for threads in [2, 3, 8] {
        let many = Band::build_on(&mesh, &spec(s), threads).unwrap();
        assert_eq!(one.slots, many.slots);
        let bits = |b: &Band| {
            b.samples
                .iter()
                .flatten()
                .map(|v| v.to_bits())
                .collect::<Vec<_>>()
        };
        assert_eq!(bits(&one), bits(&many), "{threads} threads");
    }
}

#[test]
fn one_field_is_shared_per_mesh_and_resolution() {
    let mesh = icosphere();
    let a = Band::shared(&mesh, &spec(0.1)).unwrap();
    let b = Band::shared(&mesh, &spec(0.1)).unwrap();
    assert!(Arc::ptr_eq(&a, &b));
    let c = Band::shared(&mesh, &spec(0.2)).unwrap();
    assert!(!Arc::ptr_eq(&a, &c));
    assert_ne!(a.band_key(), c.band_key());
}

#[test]
fn a_field_over_the_cap_is_refused_with_its_size() {
    let mesh = icosphere();
    let mut small = spec(0.1);
    small.max_bytes = 1 << 20;
    small.voxel = 0.002;
    let e = Band::build(&mesh, &small).unwrap_err();
    assert!(e.contains("MiB, more than the 1 MiB allowed"), "{e}");
    small.voxel = -1.0;
    let e = Band::build(&mesh, &small).unwrap_err();
    assert!(e.contains("not a positive length"), "{e}");
}
