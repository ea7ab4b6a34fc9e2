//! The harness the cargo-fuzz target (`fuzz/`) and the stable garbage test share:
//! compile arbitrary text in a context with knobs, functions and soft objects,
//! and run whatever compiles. It must never panic or hang.

use std::collections::BTreeMap;

use glam::Vec3;

use super::eval::Inputs;
use super::{Context, Kind, compile_expression, parse_functions};
use crate::desc::{ObjectDesc, SphereDesc, V3};
use crate::field::curve::Curve;
use crate::field::density::Density;
use crate::field::domain::{Field, Points};
use crate::field::noise::Noise;
use crate::math::simd::Isa;
use crate::math::simd::{LANES, Lanes};

/// Parses `functions`, compiles `expression` as every kind of expression, and
/// evaluates each program that compiles at a few points (finite and not).
pub fn compile_and_run(functions: &str, expression: &str) {
    let Ok(functions) = parse_functions(functions) else {
        return;
    };
    let knobs = BTreeMap::from([("k".to_string(), 0.5), ("freq".to_string(), 4.0)]);
    let sphere = Density::build(
        &ObjectDesc::Sphere(SphereDesc {
            centre: V3(Vec3::ZERO),
            radius: 0.8,
            softness: 0.4,
        }),
        0.05,
    );
    let objects = vec![
        ("D".to_string(), sphere.clone()),
        ("ball".to_string(), sphere.clone()),
    ];
    let map = Curve::new(
        crate::desc::Interpolation::Spline,
        [
            (0.0, [0.0, 0.0, 0.0]),
            (0.5, [1.0, 0.5, 0.0]),
            (1.0, [1.0, 1.0, 1.0]),
        ],
    );
    let ctx = Context {
        knobs: &knobs,
        functions: &functions,
        objects: &objects,
        surface: Some(&sphere),
        colour_map: Some(&map),
    };
    let noise = Noise::default();
    let field = Field {
        noise: &noise,
        offset: Vec3::ZERO,
        frame: 7,
        time: 7.0,
        frame_rate: 24.0,
        pose: None,
        support: None,
    };
    for kind in [Kind::Density, Kind::Colour, Kind::Normal, Kind::Probe] {
        if let Ok(program) = compile_expression(expression, kind, &ctx) {
            for x in [
                Vec3::ZERO,
                Vec3::new(0.3, -0.7, 0.2),
                Vec3::splat(f32::NAN),
                Vec3::splat(f32::INFINITY),
                Vec3::splat(-3.0e38),
            ] {
                let _ = program.eval(Inputs { x, d: 0.5 }, &field);
            }
            lanes_agree(&program, &field);
            if kind == Kind::Density {
                support_holds(&program, &field);
            }
        }
    }
}

/// Points of the sample grid the checks use: inside the sphere, in its soft
/// shell, outside it.
const POINTS: [Vec3; 8] = [
    Vec3::new(0.0, 0.0, 0.0),
    Vec3::new(0.3, -0.7, 0.2),
    Vec3::new(0.9, 0.1, 0.0),
    Vec3::new(-0.5, 0.5, -0.6),
    Vec3::new(3.0, 0.0, 0.0),
    Vec3::new(0.0, -1.5, 0.2),
    Vec3::new(1.2, 1.2, 1.2),
    Vec3::new(-2.0, 0.25, 7.0),
];

/// The lane register code gives each lane the bits of the point alone (lanes
/// take different branches here), on every instruction set.
fn lanes_agree(program: &super::Program, field: &Field) {
    let mut points = Points::default();
    for l in 0..LANES {
        points.set(l, POINTS[l % POINTS.len()]);
    }
    let d: Lanes = std::array::from_fn(|l| l as f32 / 7.0);
    let alone: Vec<[f32; 3]> = (0..LANES)
        .map(|l| {
            program.eval(
                Inputs {
                    x: POINTS[l % POINTS.len()],
                    d: d[l],
                },
                field,
            )
        })
        .collect();
    for isa in Isa::available() {
        let lanes = program.eval_lanes(&points, &d, field, isa);
        for (l, one) in alone.iter().enumerate() {
            for c in 0..3 {
                let (a, b) = (lanes[c][l], one[c]);
                assert!(
                    a.to_bits() == b.to_bits() || (a.is_nan() && b.is_nan()),
                    "lane {l} on {isa:?}: {a} vs {b} alone"
                );
            }
        }
    }
}

/// Outside the box [`super::Program::support`] finds, and outside its ball,
/// the density is 0.
fn support_holds(program: &super::Program, field: &Field) {
    let Some((lo, hi)) = program.support() else {
        return;
    };
    let ball = program.support_ball();
    for x in POINTS {
        let outside_ball = ball.is_some_and(|(c, r)| (x - c).length() > r);
        if x.cmplt(lo).any() || x.cmpgt(hi).any() || outside_ball {
            let f = crate::field::shaping::clamp01(program.eval_scalar(x, 0.0, field));
            assert!(f == 0.0, "{f} at {x}, outside the support {lo} {hi}");
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::math::random::SplitMix64;

    /// Pieces that make near-valid programs, so that random strings reach deep
    /// into the parser and the compiler rather than failing on the first byte.
    const PIECES: [&str; 48] = [
        "x",
        "t",
        "d",
        "k",
        "freq",
        "frame",
        "pi",
        "1",
        "0.5",
        "-",
        "+",
        "*",
        "/",
        "%",
        "<",
        "<=",
        "==",
        "!=",
        "&&",
        "||",
        "!",
        "(",
        ")",
        "[",
        "]",
        "{",
        "}",
        ",",
        ";",
        "=",
        ".x",
        ".z",
        "let a = ",
        "a",
        "if ",
        " else ",
        "noise(",
        "vnoise(",
        "dnoise(",
        "turbulence(",
        "bias(",
        "gain(",
        "D(",
        "ball(",
        "project(",
        "colour_map(",
        "f(",
        "fn f(a) { ",
    ];

    fn random_text(r: &mut SplitMix64) -> String {
        let mut s = String::new();
        let n = r.below(40);
        for _ in 0..n {
            match r.below(8) {
                0 => {
                    // A raw byte, possibly not ASCII.
                    let c = char::from_u32(r.below(0x3000)).unwrap_or('?');
                    s.push(c);
                }
                1 => s.push(' '),
                _ => s.push_str(PIECES[r.below(PIECES.len() as u32) as usize]),
            }
        }
        s
    }

    #[test]
    fn never_panics_on_garbage() {
        let mut r = SplitMix64::new(1985);
        let mut compiled = 0;
        for _ in 0..20_000 {
            let functions = if r.below(4) == 0 {
                random_text(&mut r)
            } else {
                "fn f(a) { a * 2 }".to_string()
            };
            let expression = random_text(&mut r);
            compile_and_run(&functions, &expression);
            let knobs = BTreeMap::new();
            let ctx = Context {
                knobs: &knobs,
                functions: &[],
                objects: &[],
                surface: None,
                colour_map: None,
            };
            compiled += usize::from(compile_expression(&expression, Kind::Probe, &ctx).is_ok());
        }
        // Some random texts are valid programs: the test reaches the evaluator.
        assert!(compiled > 50, "only {compiled} random texts compiled");
    }

    #[test]
    fn never_panics_on_mutated_programs() {
        let seeds = [
            "let s = noise(freq * project(x)); gain(0.9, bias(0.3, s)) * D(x)",
            "if d > 0.5 { colour_map(turbulence(x * 4, 5)) } else { [1, 0, 0] }",
            "let v = dnoise(x); normalize(cross(v, [0, 1, 0])) * 0.2",
        ];
        let mut r = SplitMix64::new(2002);
        for _ in 0..5_000 {
            let mut bytes = seeds[r.below(3) as usize].as_bytes().to_vec();
            for _ in 0..1 + r.below(4) {
                let i = r.below(bytes.len() as u32) as usize;
                match r.below(3) {
                    0 => bytes[i] = r.below(128) as u8,
                    1 => {
                        bytes.remove(i);
                    }
                    _ => bytes.insert(i, b"()[]{},;.+-*/"[r.below(13) as usize]),
                }
            }
            compile_and_run("fn f(a) { a }", &String::from_utf8_lossy(&bytes));
        }
    }
}
