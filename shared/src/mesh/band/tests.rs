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

/// The field as the straightforward build makes it: [`Mesh::closest`] at
/// every slot's centre, every block's centre and every sample of a near
/// block, on one thread.
fn reference(mesh: &Mesh, spec: &BandSpec) -> Band {
    let grid = Grid::new(mesh, spec);
    let half = grid.side * 0.5 * 3f32.sqrt();
    let mut slots: Vec<u32> = (0..grid.dims.iter().product())
        .map(|i| {
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
        })
        .collect();
    let mut samples = Vec::new();
    let mut bricks = 0;
    for (i, slot) in slots.iter_mut().enumerate() {
        if *slot == 0 {
            samples.extend(reference_brick(&grid, mesh, i));
            *slot = bricks;
            bricks += 1;
        }
    }
    Band {
        key: Band::key(mesh, spec),
        origin: grid.origin,
        inv_voxel: 1.0 / spec.voxel,
        dims: grid.dims,
        slots,
        samples,
    }
}

/// The samples of the brick in `slot`: [`Mesh::closest`] at each block's
/// centre, and at each sample of a near block.
fn reference_brick(grid: &Grid, mesh: &Mesh, slot: usize) -> Vec<[f32; 4]> {
    const BLOCKS: usize = BRICK / 2;
    let base = grid.slot_origin(slot);
    let lattice =
        |x: usize, y: usize, z: usize| base + Vec3::new(x as f32, y as f32, z as f32) * grid.voxel;
    let half = grid.voxel * 3f32.sqrt();
    let mut far = [0i8; BLOCKS * BLOCKS * BLOCKS];
    for (k, f) in far.iter_mut().enumerate() {
        let (x, y, z) = (k % BLOCKS, k / BLOCKS % BLOCKS, k / (BLOCKS * BLOCKS));
        let d = mesh
            .closest(lattice(2 * x + 1, 2 * y + 1, 2 * z + 1))
            .distance;
        if d.abs() - half > grid.reach {
            *f = if d < 0.0 { -1 } else { 1 };
        }
    }
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

/// The build's field against the straightforward one: the same slots and
/// the same bits in every sample, on every instruction-set path.
fn assert_as_reference(name: &str, mesh: &Mesh, spec: &BandSpec) {
    let want = reference(mesh, spec);
    let got = Band::build_on(mesh, spec, 2).unwrap();
    assert_eq!(got.slots, want.slots, "{name}: slots");
    let first = got
        .samples
        .iter()
        .zip(&want.samples)
        .position(|(a, b)| a.map(f32::to_bits) != b.map(f32::to_bits));
    if let Some(i) = first {
        panic!(
            "{name}: sample {i} of {} is {:?}, not {:?}",
            want.samples.len(),
            got.samples[i],
            want.samples[i]
        );
    }
    assert_eq!(got.digest(), want.digest(), "{name}");
    eprintln!(
        "{name}: {} bricks, digest {:016x}",
        want.bricks(),
        want.digest()
    );
}

#[test]
fn the_build_gives_the_straightforward_field_on_spot() {
    assert_as_reference("spot", &spot(), &spec(0.07));
}

#[test]
fn the_build_gives_the_straightforward_field_on_open_meshes() {
    let open = Mesh::from_obj(
        "open-cube.obj",
        crate::mesh::tests::open_cube_obj(0.5).as_bytes(),
        Default::default(),
    )
    .unwrap();
    assert!(!open.is_closed());
    assert_as_reference("open cube", &open, &spec(0.1));
    let teddy = crate::mesh::tests::teddy();
    assert!(!teddy.is_closed());
    assert_as_reference("teddy", &teddy, &spec(0.05));
}

#[test]
fn the_build_gives_the_straightforward_field_on_a_cube_and_an_icosphere() {
    let cube = Mesh::from_obj(
        "cube.obj",
        crate::mesh::tests::cube_obj(0.5).as_bytes(),
        Default::default(),
    )
    .unwrap();
    assert_as_reference("cube", &cube, &spec(0.1));
    assert_as_reference("icosphere", &icosphere(), &spec(0.1));
}
