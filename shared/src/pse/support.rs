//! Where a density expression can be non-zero: a box found by reading the
//! register code once at load, so that the marcher skips empty space for
//! expressions as it does for the native DMFs.
//!
//! Each register gets a *support*: a box outside which its value is 0 for
//! certain, or "anywhere". The rules follow the operations: `D(x)` at the sample
//! point itself has the object's support; a product is 0 where either factor
//! is; a sum only where both are; `bias`, `gain`, `abs`, `sin`, `sqrt` and
//! `clamp(v, lo ≤ 0, hi ≥ 0)` keep 0 at 0; `a < b` is false where both are 0.
//! Control flow is followed forwards (jumps only go forwards): the branch after
//! `JumpIfZero(c)` runs only where `c` is non-zero, so everything it writes is 0
//! outside `c`'s support, and where paths meet the supports are joined.
//! Anything else (noise, `cos`, `exp`, a point moved before `D` is evaluated)
//! may be non-zero anywhere.
//!
//! A product is 0 where a factor is 0 only if the other factor is finite there
//! (`0 · ∞` is a NaN, and a NaN is not 0 to `!=` or to a branch), so every
//! register also carries a bound on its magnitude, `None` when it may be
//! infinite or NaN; the sample point is taken to lie within ±10³⁰ (march bounds
//! are far smaller).

use std::collections::BTreeMap;

use glam::Vec3;

use super::eval::{Fn1, Fn2, INPUTS, Op, Program, REG_D, REG_FRAME, REG_T, REG_X, Result3};
use crate::field::density::Density;
use crate::field::domain::Aabb;

/// Where a value can be non-zero: `None` anywhere, or inside a box and, when
/// known, a ball (an empty box: nowhere, the value is always 0).
type Support = Option<Region>;

/// A box, and a ball when one is known; the value is 0 outside either.
#[derive(Clone, Copy, Debug, PartialEq)]
struct Region {
    aabb: Aabb,
    ball: Option<(Vec3, f32)>,
}

const NOWHERE: Region = Region {
    aabb: (Vec3::INFINITY, Vec3::NEG_INFINITY),
    ball: None,
};

fn is_empty(r: &Region) -> bool {
    r.aabb.0.cmpgt(r.aabb.1).any()
}

/// The smallest ball holding both balls.
fn enclosing((c, r): (Vec3, f32), (d, q): (Vec3, f32)) -> (Vec3, f32) {
    let gap = (d - c).length();
    if gap + q <= r {
        (c, r)
    } else if gap + r <= q {
        (d, q)
    } else {
        let radius = (gap + r + q) * 0.5;
        // From c towards d, so that both balls touch the new one's surface;
        // a little more for rounding.
        let centre = c + (d - c) * ((radius - r) / gap);
        (centre, radius * (1.0 + 1e-6) + 1e-6)
    }
}

fn union(a: Support, b: Support) -> Support {
    let (a, b) = (a?, b?);
    if is_empty(&a) {
        return Some(b);
    }
    if is_empty(&b) {
        return Some(a);
    }
    Some(Region {
        aabb: (a.aabb.0.min(b.aabb.0), a.aabb.1.max(b.aabb.1)),
        ball: a.ball.zip(b.ball).map(|(x, y)| enclosing(x, y)),
    })
}

fn meet(a: Support, b: Support) -> Support {
    match (a, b) {
        (Some(a), Some(b)) => Some(Region {
            aabb: (a.aabb.0.max(b.aabb.0), a.aabb.1.min(b.aabb.1)),
            // Either ball holds the intersection: the smaller.
            ball: match (a.ball, b.ball) {
                (Some(x), Some(y)) => Some(if x.1 <= y.1 { x } else { y }),
                (x, y) => x.or(y),
            },
        }),
        (Some(a), None) | (None, Some(a)) => Some(a),
        (None, None) => None,
    }
}

/// What is known of the registers on one path through the code.
#[derive(Clone)]
struct State {
    /// The path is taken only for points inside this box.
    reach: Support,
    support: Vec<Support>,
    /// `Some(i)`: the register holds component i of the sample point x.
    point: Vec<Option<u8>>,
    /// The register holds this value at every point (a constant never overwritten).
    constant: Vec<Option<f32>>,
    /// A bound on the register's magnitude, `None`: it may be infinite or NaN.
    magnitude: Vec<Option<f64>>,
}

/// The magnitude bound of the sample point's coordinates.
const POINT_MAGNITUDE: f64 = 1e30;

/// `m` as a magnitude bound, if every f32 below it (rounded up) is finite.
fn finite(m: f64) -> Option<f64> {
    (m <= 1e37).then_some(m)
}

/// What two paths agree on.
fn agreed<T: PartialEq>(a: Vec<Option<T>>, b: Vec<Option<T>>) -> Vec<Option<T>> {
    a.into_iter()
        .zip(b)
        .map(|(a, b)| if a == b { a } else { None })
        .collect()
}

impl State {
    fn join(self, other: State) -> State {
        State {
            reach: union(self.reach, other.reach),
            support: self
                .support
                .into_iter()
                .zip(other.support)
                .map(|(a, b)| union(a, b))
                .collect(),
            point: agreed(self.point, other.point),
            constant: agreed(self.constant, other.constant),
            magnitude: self
                .magnitude
                .into_iter()
                .zip(other.magnitude)
                .map(|(a, b)| Some(a?.max(b?)))
                .collect(),
        }
    }
}

impl Program {
    /// A box outside which the (scalar) value of the program is 0 for certain,
    /// or `None` when it may be non-zero anywhere.
    pub fn support(&self) -> Option<Aabb> {
        self.region().map(|r| r.aabb)
    }

    /// A ball outside which the value is 0 for certain, when one is known
    /// (`D(x)` of a sphere or torus, and what keeps its zeros).
    pub fn support_ball(&self) -> Option<(Vec3, f32)> {
        self.region()
            .and_then(|r| if is_empty(&r) { None } else { r.ball })
    }

    fn region(&self) -> Option<Region> {
        let Result3::Scalar(result) = self.result else {
            return None;
        };
        let n = self.template.len();
        let mut entry = State {
            reach: None,
            support: vec![None; n],
            point: vec![None; n],
            constant: vec![None; n],
            magnitude: vec![None; n],
        };
        // Inputs are registers 0..INPUTS; the temporaries (0) and constants follow.
        for (r, &v) in self.template.iter().enumerate().skip(INPUTS) {
            entry.constant[r] = Some(v);
            entry.support[r] = if v == 0.0 { Some(NOWHERE) } else { None };
            entry.magnitude[r] = v.is_finite().then(|| f64::from(v.abs()));
        }
        for i in 0..3u8 {
            entry.point[usize::from(REG_X + i)] = Some(i);
            entry.magnitude[usize::from(REG_X + i)] = Some(POINT_MAGNITUDE);
        }
        // t and the frame are finite; d is in [0, 1].
        entry.magnitude[usize::from(REG_T)] = Some(1e10);
        entry.magnitude[usize::from(REG_FRAME)] = Some(1e10);
        entry.magnitude[usize::from(REG_D)] = Some(1.0);
        let mut incoming: BTreeMap<usize, State> = BTreeMap::new();
        let arrive = |at: usize, s: State, incoming: &mut BTreeMap<usize, State>| {
            let joined = match incoming.remove(&at) {
                Some(other) => other.join(s),
                None => s,
            };
            incoming.insert(at, joined);
        };
        let mut current = Some(entry);
        for (i, op) in self.ops.iter().enumerate() {
            if let Some(s) = incoming.remove(&i) {
                current = Some(match current {
                    Some(c) => c.join(s),
                    None => s,
                });
            }
            let Some(state) = current.as_mut() else {
                continue;
            };
            match *op {
                Op::Jump(target) => {
                    let s = current.take().expect("a reachable path");
                    arrive(usize::from(target), s, &mut incoming);
                }
                Op::JumpIfZero(c, target) => {
                    arrive(usize::from(target), state.clone(), &mut incoming);
                    state.reach = meet(state.reach, state.support[usize::from(c)]);
                }
                op => self.step(state, op),
            }
        }
        if let Some(s) = incoming.remove(&self.ops.len()) {
            current = Some(match current {
                Some(c) => c.join(s),
                None => s,
            });
        }
        let support = current?.support[usize::from(result)]?;
        // An empty box stays empty (the marcher then skips every sample).
        Some(support)
    }

    /// The effect of one straight-line operation on what is known.
    fn step(&self, s: &mut State, op: Op) {
        if let Op::Copy(d, a) = op {
            let d = usize::from(d);
            s.support[d] = meet(s.sup(a), s.reach);
            s.point[d] = s.point[usize::from(a)];
            s.constant[d] = s.konst(a);
            s.magnitude[d] = s.mag(a);
            return;
        }
        let (dests, support, magnitude) = match op {
            Op::F1(..) | Op::F2(..) => function_effect(s, op),
            Op::Density(..)
            | Op::Noise(..)
            | Op::Improved(..)
            | Op::Turbulence(..)
            | Op::Fbm(..)
            | Op::VNoise(..)
            | Op::DNoise(..)
            | Op::Project(..)
            | Op::Smoothstep(..)
            | Op::ColourMap(..) => self.field_effect(s, op),
            _ => arithmetic_effect(s, op),
        };
        // Only points inside `reach` run this operation: whatever it writes is 0
        // outside `reach` as far as any later reader on this path can tell.
        let support = meet(support, s.reach);
        for d in dests {
            let d = usize::from(d);
            s.support[d] = support;
            s.point[d] = None;
            s.constant[d] = None;
            s.magnitude[d] = magnitude;
        }
    }

    /// What the field's built-ins write: an object's density at the sample
    /// point keeps the object's support; noise, the projection and the rest
    /// may be non-zero anywhere.
    fn field_effect(&self, s: &State, op: Op) -> Effect {
        let unit = Some(1.0);
        match op {
            Op::Density(d, object, p) => {
                let at_x = (0..3u8).all(|i| s.point[usize::from(p[usize::from(i)])] == Some(i));
                let object = self.objects.get(usize::from(object));
                let support = if at_x {
                    object.and_then(|o| {
                        Some(Region {
                            aabb: o.support()?,
                            ball: o.support_ball(),
                        })
                    })
                } else {
                    None
                };
                (vec![d], support, s.mags(p).and(unit))
            }
            Op::Noise(d, p) | Op::Improved(d, p) => (vec![d], None, s.mags(p).and(Some(2.0))),
            Op::Turbulence(d, p, _) | Op::Fbm(d, p, _) => {
                (vec![d], None, s.mags(p).and(Some(64.0)))
            }
            Op::VNoise(d, p) => (d.to_vec(), None, s.mags(p).and(Some(2.0))),
            // Central differences of noise over 2⁻⁹.
            Op::DNoise(d, p) => (d.to_vec(), None, s.mags(p).and(Some(4096.0))),
            Op::Project(d, p) => {
                // Onto the inner surface: inside the surface's support.
                let reach = self
                    .surface
                    .as_ref()
                    .and_then(Density::support)
                    .map(|(lo, hi)| f64::from(lo.abs().max(hi.abs()).max_element()));
                let m = match &self.surface {
                    None => s.mags(p),
                    Some(_) => s.mags(p).and(reach),
                };
                (d.to_vec(), None, m)
            }
            Op::Smoothstep(d, ..) => (vec![d], None, None),
            Op::ColourMap(d, _) => (d.to_vec(), None, None),
            _ => unreachable!("{op:?} is not a built-in of the field"),
        }
    }
}

/// What an operation writes: the registers, their support and their
/// magnitude bound.
type Effect = (Vec<u8>, Support, Option<f64>);

impl State {
    /// The support of register `r`.
    fn sup(&self, r: u8) -> Support {
        self.support[usize::from(r)]
    }

    /// The constant register `r` holds, if any.
    fn konst(&self, r: u8) -> Option<f32> {
        self.constant[usize::from(r)]
    }

    /// The magnitude bound of register `r`.
    fn mag(&self, r: u8) -> Option<f64> {
        self.magnitude[usize::from(r)]
    }

    /// The magnitude bound of the vector in registers `p`.
    fn mags(&self, p: [u8; 3]) -> Option<f64> {
        Some(self.mag(p[0])?.max(self.mag(p[1])?).max(self.mag(p[2])?))
    }
}

/// What arithmetic, comparisons, bias, gain and clamp write.
fn arithmetic_effect(s: &State, op: Op) -> Effect {
    let (sup, konst, mag) = (|r| s.sup(r), |r| s.konst(r), |r| s.mag(r));
    let nonzero_constant = |r: u8| konst(r).is_some_and(|k| k != 0.0 && k.is_finite());
    let unit = Some(1.0);
    // Bias and gain keep 0 at 0, and [0, 1] within [0, 1] when `keeps_unit`.
    let shaped = |d: u8, a: u8, keeps_unit: bool| -> Effect {
        (
            vec![d],
            sup(a),
            if keeps_unit { mag(a).and(unit) } else { None },
        )
    };
    match op {
        Op::Add(d, a, b) | Op::Sub(d, a, b) => (
            vec![d],
            union(sup(a), sup(b)),
            finite(mag(a).zip(mag(b)).map_or(f64::INFINITY, |(a, b)| a + b)),
        ),
        // 0 · b = 0 only for a finite b.
        Op::Mul(d, a, b) => (
            vec![d],
            meet(
                if mag(b).is_some() { sup(a) } else { None },
                if mag(a).is_some() { sup(b) } else { None },
            ),
            finite(mag(a).zip(mag(b)).map_or(f64::INFINITY, |(a, b)| a * b)),
        ),
        Op::Div(d, a, b) | Op::Rem(d, a, b) => {
            if nonzero_constant(b) {
                let k = f64::from(konst(b).unwrap_or(1.0).abs());
                let m = match op {
                    Op::Div(..) => mag(a).and_then(|m| finite(m / k)),
                    _ => mag(a),
                };
                (vec![d], sup(a), m)
            } else {
                (vec![d], None, None)
            }
        }
        Op::Neg(d, a) => (vec![d], sup(a), mag(a)),
        // 0 < 0, 0 != 0, 0 && b and 0 || 0 are false; 0 <= 0, 0 == 0, !0 true.
        Op::Lt(d, a, b) | Op::Ne(d, a, b) | Op::Or(d, a, b) => {
            (vec![d], union(sup(a), sup(b)), unit)
        }
        Op::And(d, a, b) => (vec![d], meet(sup(a), sup(b)), unit),
        Op::Le(d, ..) | Op::Eq(d, ..) | Op::Not(d, _) => (vec![d], None, unit),
        Op::BiasK(d, a, bias) => shaped(d, a, bias.keeps_unit_interval()),
        Op::GainK(d, a, gain) => shaped(d, a, gain.keeps_unit_interval()),
        Op::Clamp(d, v, lo, hi) => {
            let keeps_zero =
                konst(lo).is_some_and(|l| l <= 0.0) && konst(hi).is_some_and(|h| h >= 0.0);
            (
                vec![d],
                if keeps_zero { sup(v) } else { None },
                mag(lo).zip(mag(hi)).map(|(a, b)| a.max(b)),
            )
        }
        _ => unreachable!("{op:?} is not arithmetic"),
    }
}

/// What the scalar functions of one and two arguments write.
fn function_effect(s: &State, op: Op) -> Effect {
    let (sup, konst, mag) = (|r| s.sup(r), |r| s.konst(r), |r| s.mag(r));
    let unit = Some(1.0);
    match op {
        Op::F1(f, d, a) => match f {
            Fn1::Abs => (vec![d], sup(a), mag(a)),
            Fn1::Floor => (vec![d], sup(a), mag(a).map(|m| m + 1.0)),
            Fn1::Fract | Fn1::Sin => (vec![d], sup(a), mag(a).and(unit)),
            Fn1::Sign => (vec![d], sup(a), unit),
            Fn1::Tan | Fn1::Sqrt => (vec![d], sup(a), None),
            Fn1::Cos => (vec![d], None, mag(a).and(unit)),
            Fn1::Exp | Fn1::Log => (vec![d], None, None),
        },
        Op::F2(f, d, a, b) => match f {
            Fn2::Min | Fn2::Max => (
                vec![d],
                union(sup(a), sup(b)),
                mag(a).zip(mag(b)).map(|(a, b)| a.max(b)),
            ),
            // bias_b(0) = gain_g(0) = 0: the second argument is t.
            Fn2::Bias | Fn2::Gain => {
                let unit_b = konst(a).is_some_and(|b| b > 0.0 && b < 1.0);
                (
                    vec![d],
                    sup(b),
                    if unit_b { mag(b).and(unit) } else { None },
                )
            }
            Fn2::Step => (vec![d], None, unit),
            Fn2::Atan2 => (vec![d], None, mag(a).and(mag(b)).and(Some(4.0))),
            Fn2::Pow => (vec![d], None, None),
        },
        _ => unreachable!("{op:?} is not a scalar function"),
    }
}

#[cfg(test)]
mod tests {
    use std::collections::BTreeMap;

    use glam::Vec3;

    use crate::desc::ObjectDesc;
    use crate::field::density::Density;
    use crate::field::domain::Aabb;
    use crate::pse::{Context, Kind, compile_expression, parse_functions};

    fn object(ron_text: &str) -> Density {
        let desc: ObjectDesc = ron::Options::default()
            .with_default_extension(ron::extensions::Extensions::UNWRAP_VARIANT_NEWTYPES)
            .from_str(ron_text)
            .expect("an object");
        Density::build(&desc, 0.01)
    }

    fn support(src: &str) -> Option<Aabb> {
        let knobs = BTreeMap::from([("curl".to_string(), 0.0)]);
        let functions = parse_functions("fn bump(p, d) { d * noise(p) }").unwrap();
        let objects = vec![
            (
                "D".to_string(),
                object("Sphere(centre: (1, 0, 0), radius: 1, softness: 0.5)"),
            ),
            (
                "ball".to_string(),
                object("Sphere(centre: (-2, 0, 0), radius: 0.5, softness: 0)"),
            ),
        ];
        let ctx = Context {
            knobs: &knobs,
            functions: &functions,
            objects: &objects,
            surface: None,
            colour_map: None,
        };
        compile_expression(src, Kind::Density, &ctx)
            .expect("compiles")
            .support()
    }

    const D: Aabb = (Vec3::new(-0.25, -1.25, -1.25), Vec3::new(2.25, 1.25, 1.25));
    const BALL: Aabb = (Vec3::new(-2.5, -0.5, -0.5), Vec3::new(-1.5, 0.5, 0.5));

    #[test]
    fn products_and_guards_keep_the_objects_support() {
        assert_eq!(support("D(x)"), Some(D));
        assert_eq!(
            support("gain(0.9, bias(0.3, 0.5 + 0.5 * noise(x))) * D(x)"),
            Some(D)
        );
        assert_eq!(
            support("let d = D(x); if d > 0 { bump(x * 4, d) } else { 0 }"),
            Some(D)
        );
        assert_eq!(
            support("let d = D(x); if d > 0 { 1 - noise(x) } else { 0 }"),
            Some(D)
        );
        assert_eq!(support("clamp(D(x) * 2, 0, 1)"), Some(D));
        // A knob known at load removes the branch not taken.
        assert_eq!(
            support("let p = if curl > 0 { x + vnoise(x) } else { x }; D(p)"),
            Some(D)
        );
    }

    #[test]
    fn sums_join_the_supports() {
        let hull = (D.0.min(BALL.0), D.1.max(BALL.1));
        assert_eq!(support("D(x) + ball(x)"), Some(hull));
        assert_eq!(support("max(D(x), ball(x))"), Some(hull));
        assert_eq!(
            support("if D(x) > 0 { D(x) } else { ball(x) * noise(x) }"),
            Some(hull)
        );
        // A product lies inside either factor's support.
        let (lo, hi) = support("D(x) * ball(x)").expect("bounded");
        let inside = |b: Aabb| lo.cmpge(b.0).all() && hi.cmple(b.1).all();
        assert!(inside(D) || inside(BALL), "{lo} {hi}");
    }

    #[test]
    fn balls_follow_the_boxes() {
        let ball = |src: &str| {
            let knobs = BTreeMap::new();
            let objects = vec![
                (
                    "D".to_string(),
                    object("Sphere(centre: (1, 0, 0), radius: 1, softness: 0.5)"),
                ),
                (
                    "ball".to_string(),
                    object("Sphere(centre: (-2, 0, 0), radius: 0.5, softness: 0)"),
                ),
            ];
            let ctx = Context {
                knobs: &knobs,
                functions: &[],
                objects: &objects,
                surface: None,
                colour_map: None,
            };
            compile_expression(src, Kind::Density, &ctx)
                .unwrap()
                .support_ball()
        };
        let d = Some((Vec3::new(1.0, 0.0, 0.0), 1.25));
        assert_eq!(ball("D(x)"), d);
        assert_eq!(
            ball("let d = D(x); if d > 0 { d * noise(x) } else { 0 }"),
            d
        );
        assert_eq!(
            ball("D(x) * ball(x)"),
            Some((Vec3::new(-2.0, 0.0, 0.0), 0.5))
        );
        // Both spheres inside the enclosing ball, from x = -2.5 to 2.25.
        let (c, r) = ball("D(x) + ball(x)").unwrap();
        assert!(
            (c.x - (-0.125)).abs() < 1e-5 && (r - 2.375).abs() < 1e-4,
            "{c} {r}"
        );
        assert_eq!(ball("noise(x)"), None);
    }

    #[test]
    fn anything_else_may_be_non_zero_anywhere() {
        assert_eq!(support("noise(x)"), None);
        assert_eq!(support("D(x) + 0.1"), None);
        assert_eq!(support("D(x + [0.5, 0, 0])"), None);
        assert_eq!(support("cos(D(x))"), None);
        assert_eq!(support("if D(x) > 0 { 1 } else { 0.5 }"), None);
        assert_eq!(support("if D(x) <= 0 { 1 } else { D(x) }"), None);
    }
}
