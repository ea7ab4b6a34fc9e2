//! Every DMF on every path: the lanes of SSE4.1, AVX2 and AVX-512 give the scalar
//! bits (of f and of the object's own D), and the dual path the scalar value
//! with a finite gradient.

use std::collections::BTreeSet;

use glam::Vec3;

use super::{Dmf, Modulation, Warp};
use crate::desc::{DmfDesc, HardCore, ObjectDesc};
use crate::field::density::{Density, Hypertexture};
use crate::field::domain::{Field, Points};
use crate::field::noise::Noise;
use crate::math::dual::DualPoint;
use crate::math::random::SplitMix64;
use crate::math::simd::{Isa, LANES};

/// The registered DMF a description builds, by name. The match has no
/// wildcard: a DMF registered without a case below does not compile.
fn registered(dmf: &Dmf) -> &'static str {
    match dmf {
        Dmf::Warp(Warp::NoisyRadius(_)) => "NoisyRadius",
        Dmf::Warp(Warp::FractalRadius(_)) => "FractalRadius",
        Dmf::Warp(Warp::Dripping(_)) => "Dripping",
        Dmf::Warp(Warp::TurbulentRadius(_)) => "TurbulentRadius",
        Dmf::Value(Modulation::Bias(_)) => "Bias",
        Dmf::Value(Modulation::Gain(_)) => "Gain",
        Dmf::Value(Modulation::Fur(_)) => "Fur",
    }
}

/// Every registered DMF, as a scene writes it.
const EVERY_DMF: usize = 7;

/// (object, DMFs): each DMF alone, on the objects whose code paths differ
/// (the fur projects onto a sphere, a box or a torus), and chained.
const CASES: &[(&str, &str)] = &[
    (
        "Sphere(radius: 0.9, softness: 0.6)",
        "NoisyRadius(frequency: 3.0, amplitude: 0.4)",
    ),
    (
        "Sphere(radius: 0.9, softness: 0.6)",
        "FractalRadius(frequency: 2.0, octaves: 6, amplitude: 0.5)",
    ),
    (
        "Sphere(radius: 0.9, softness: 0.6)",
        "Dripping(frequency: 5.0, amplitude: 0.9, stretch: 0.1)",
    ),
    (
        "Sphere(radius: 0.9, softness: 0.6)",
        "TurbulentRadius(frequency: 2.0, amplitude: 1.0, octaves: 5)",
    ),
    ("Sphere(radius: 0.9, softness: 0.6)", "Bias(0.3)"),
    ("Sphere(radius: 0.9, softness: 0.6)", "Gain(0.8)"),
    ("Sphere(radius: 0.9, softness: 0.6)", "Fur(frequency: 30.0)"),
    (
        "Sphere(radius: 0.9, softness: 0.6)",
        "Fur(frequency: 30.0, bias: 0.3, gain: 0.9, curliness: 0.9)",
    ),
    (
        "Box(half_size: (0.6, 0.5, 0.7), softness: 0.4)",
        "Fur(frequency: 20.0, curliness: 0.5)",
    ),
    (
        "Torus(major_radius: 0.8, minor_radius: 0.3, softness: 0.3)",
        "Fur(frequency: 25.0, curliness: 0.7)",
    ),
    // An icosphere of radius 0.6 (the mesh tests' generator).
    (
        "Mesh(path: \"icosphere.obj\", softness: 0.4)",
        "Fur(frequency: 25.0, curliness: 0.7)",
    ),
    (
        "Mesh(path: \"icosphere.obj\", softness: 0.4, centre: (0.1, 0.0, 0.0), scale: 1.2)",
        "NoisyRadius(frequency: 2.0, amplitude: 0.2), Bias(0.6), Fur(frequency: 12.0)",
    ),
    // The exact closest-triangle search instead of the distance field.
    (
        "Mesh(path: \"icosphere.obj\", softness: 0.4, sdf: Exact)",
        "Fur(frequency: 25.0, curliness: 0.7)",
    ),
    (
        "Sphere(radius: 0.9, softness: 0.6)",
        "NoisyRadius(frequency: 2.0, amplitude: 0.2), TurbulentRadius(frequency: 3.0, amplitude: 0.3, octaves: 3), Bias(0.6), Gain(0.3), Fur(frequency: 12.0, curliness: 0.4)",
    ),
];

fn case(object: &str, dmfs: &str, hard_core: HardCore) -> (Density, Vec<DmfDesc>) {
    let step = 0.01;
    // The scene parser's extensions: `Sphere(radius: …)` for `Sphere(Sphere(…))`.
    let ron = ron::Options::default()
        .with_default_extension(ron::extensions::Extensions::UNWRAP_VARIANT_NEWTYPES);
    let mut object: ObjectDesc = ron.from_str(object).expect("a valid object");
    object.for_each_mesh_mut(&mut |m| {
        let obj = crate::mesh::icosphere_obj(glam::Vec3::ZERO, 0.6, 2);
        let mesh = crate::mesh::Mesh::from_obj(&m.path, obj.as_bytes(), Default::default());
        m.mesh = Some(std::sync::Arc::new(
            mesh.expect("the icosphere is a closed mesh"),
        ));
        // Its distance field, as a scene attaches it (`sdf: Field`, the default).
        m.field = m.field_spec(0.0).map(|spec| {
            let mesh = m.mesh.as_ref().expect("attached");
            crate::mesh::Band::shared(mesh, &spec).expect("a small field")
        });
    });
    let dmfs: Vec<DmfDesc> = ron.from_str(&format!("[{dmfs}]")).expect("valid DMFs");
    let h =
        Hypertexture::build(Density::build(&object, step), &dmfs, step).with_hard_core(hard_core);
    (Density::Hypertexture(Box::new(h)), dmfs)
}

fn field(noise: &Noise) -> Field<'_> {
    Field {
        noise,
        offset: Vec3::new(0.0, 0.06, 0.0),
        frame: 3,
        time: 3.0,
        frame_rate: 24.0,
        pose: None,
        support: None,
    }
}

#[test]
fn the_hard_region_is_solid_unless_shaped() {
    let noise = Noise::new(1989);
    let field = field(&noise);
    let sphere = "Sphere(radius: 0.9, softness: 0.6)";
    let fur = "Fur(frequency: 30.0, bias: 0.3, gain: 0.9)";
    let (solid, _) = case(sphere, fur, HardCore::Solid);
    let (shaped, _) = case(sphere, fur, HardCore::Shaped);
    let (object, _) = case(sphere, "", HardCore::Solid);
    let mut r = SplitMix64::new(1);
    let (mut core, mut shaped_below_1, mut soft) = (0, 0, 0);
    for _ in 0..2000 {
        let p = (Vec3::new(r.next_f32(), r.next_f32(), r.next_f32()) * 2.0 - 1.0) * 1.2;
        let d = object.eval(p, &field);
        let (f, g) = (solid.eval(p, &field), shaped.eval(p, &field));
        if d == 1.0 {
            core += 1;
            assert_eq!(f, 1.0, "solid at {p}");
            assert_eq!(solid.eval_dual(&DualPoint::at(p), &field, 0.01).v, 1.0);
            shaped_below_1 += usize::from(g < 1.0);
        } else {
            // The soft region and outside: the same DMFs either way.
            assert_eq!(f.to_bits(), g.to_bits(), "soft at {p}");
            soft += usize::from(d > 0.0 && f < d);
        }
        assert_eq!(solid.eval_object(p, &field).to_bits(), d.to_bits());
    }
    assert!(core > 100 && soft > 100, "{core} core, {soft} soft points");
    // The literal formula f = fur(x)·D leaves most of the core below 1.
    assert!(shaped_below_1 > core / 2, "{shaped_below_1} of {core}");
}

#[test]
fn every_dmf_gives_the_same_bits_on_every_path() {
    let noise = Noise::new(1989);
    let field = field(&noise);
    let isas = Isa::available();
    assert!(isas.contains(&Isa::Scalar));
    let mut seen = BTreeSet::new();
    let modes = [HardCore::Solid, HardCore::Shaped];
    for (&(object, dmfs), hard_core) in CASES.iter().flat_map(|c| modes.map(|m| (c, m))) {
        let (density, descs) = case(object, dmfs, hard_core);
        for d in &descs {
            seen.insert(registered(&Dmf::build(d, 0.01)));
        }
        let mut r = SplitMix64::new(18);
        let mut non_zero = 0;
        for _ in 0..1000 / LANES {
            let mut points = Points::default();
            for l in 0..LANES {
                let p = Vec3::new(r.next_f32(), r.next_f32(), r.next_f32()) * 3.0 - 1.5;
                points.set(l, p);
            }
            let scalar: [f32; LANES] = std::array::from_fn(|l| density.eval(points.get(l), &field));
            non_zero += scalar.iter().filter(|&&v| v > 0.0).count();
            for &isa in &isas {
                let lanes = density.eval_lanes(&points, &field, isa);
                assert_eq!(
                    lanes.map(f32::to_bits),
                    scalar.map(f32::to_bits),
                    "{dmfs} on {object} ({hard_core:?}), {isa:?} at {points:?}"
                );
                // The object's own D, which gives a hard region its normal.
                let own: [f32; LANES] =
                    std::array::from_fn(|l| density.eval_object(points.get(l), &field));
                assert_eq!(
                    density
                        .eval_object_lanes(&points, &field, isa)
                        .map(f32::to_bits),
                    own.map(f32::to_bits),
                    "D of {object} under {dmfs}, {isa:?} at {points:?}"
                );
            }
            for (l, &v) in scalar.iter().enumerate() {
                let p = points.get(l);
                let dual = density.eval_dual(&DualPoint::at(p), &field, 0.01);
                assert!(
                    (dual.v - v).abs() <= 1e-5,
                    "{dmfs} on {object}, dual {} against {v} at {p}",
                    dual.v
                );
                assert!(
                    dual.d.is_finite(),
                    "{dmfs} on {object}: gradient {} at {p}",
                    dual.d
                );
            }
        }
        assert!(
            non_zero > 50,
            "{dmfs} on {object}: only {non_zero} points inside"
        );
    }
    assert_eq!(seen.len(), EVERY_DMF, "DMFs tested: {seen:?}");
}

/// The radial warps summing octaves stop at the lanes whose D is settled
/// (`WarpDmf::apply_lanes`). Lanes along a ray, like the marcher's,
/// settle a register at a time: from outside the shell to the hard region
/// they still give the scalar bits on every path.
#[test]
fn warps_that_settle_give_the_same_bits_along_rays() {
    let noise = Noise::new(1989);
    let field = field(&noise);
    let cases = [
        (
            "Sphere(radius: 1.0, softness: 0.2)",
            "FractalRadius(frequency: 2.0, octaves: 8)",
        ),
        (
            "Sphere(radius: 1.2, softness: 0.15, centre: (0.1, 0.0, 0.0))",
            "FractalRadius(frequency: 2.5, octaves: 8, amplitude: 1.6, centre: (0.1, 0.0, 0.0))",
        ),
        (
            "Sphere(radius: 0.9, softness: 1.2)",
            "TurbulentRadius(frequency: 2.0, amplitude: 1.0, octaves: 7)",
        ),
        (
            "Sphere(radius: 0.9, softness: 0.4)",
            "TurbulentRadius(frequency: 2.0, amplitude: 0.3, octaves: 6)",
        ),
        // The most octaves a scene may ask for, none clamped at this step.
        (
            "Sphere(radius: 0.9, softness: 0.4)",
            "TurbulentRadius(frequency: 0.002, amplitude: 2.0, octaves: 16)",
        ),
        (
            "Sphere(radius: 0.9, softness: 0.4)",
            "FractalRadius(frequency: 0.002, octaves: 16, amplitude: 0.01)",
        ),
    ];
    let mut r = SplitMix64::new(41);
    let mut unit = || Vec3::new(r.next_f32(), r.next_f32(), r.next_f32()) * 2.0 - 1.0;
    for (object, dmfs) in cases {
        for hard_core in [HardCore::Solid, HardCore::Shaped] {
            let (density, _) = case(object, dmfs, hard_core);
            let (mut zero, mut one, mut soft) = (0, 0, 0);
            for _ in 0..300 {
                // 16 samples 0.02 apart on a ray from outside towards the centre.
                let from = unit().normalize_or(Vec3::X) * 2.2;
                let dir = (unit() * 0.3 - from).normalize_or(Vec3::X);
                let start = 0.02 * LANES as f32 * (unit().x + 1.0) * 4.0;
                let mut points = Points::default();
                for l in 0..LANES {
                    points.set(l, from + dir * (start + 0.02 * l as f32));
                }
                let scalar: [f32; LANES] =
                    std::array::from_fn(|l| density.eval(points.get(l), &field));
                for v in scalar {
                    zero += usize::from(v == 0.0);
                    one += usize::from(v == 1.0);
                    soft += usize::from(v > 0.0 && v < 1.0);
                }
                for isa in Isa::available() {
                    let lanes = density.eval_lanes(&points, &field, isa);
                    assert_eq!(
                        lanes.map(f32::to_bits),
                        scalar.map(f32::to_bits),
                        "{dmfs} on {object} ({hard_core:?}), {isa:?} at {points:?}"
                    );
                }
            }
            assert!(
                zero > 200 && one > 200 && soft > 200,
                "{dmfs} on {object}: {zero} at 0, {one} at 1, {soft} between"
            );
        }
    }
}
