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
//! The analysis assumes no operation overflows to infinity (`0 · ∞` would be a
//! NaN, not 0); a NaN density is clamped to 0 anyway.

use std::collections::BTreeMap;

use glam::Vec3;

use super::eval::{Fn1, Fn2, Op, Program, REG_X, Result3};
use crate::density::Aabb;

/// Where a value can be non-zero: `None` anywhere, or inside a box (an empty
/// box: nowhere, the value is always 0).
type Support = Option<Aabb>;

const NOWHERE: Aabb = (Vec3::INFINITY, Vec3::NEG_INFINITY);

fn union(a: Support, b: Support) -> Support {
    Some((a?.0.min(b?.0), a?.1.max(b?.1)))
}

fn meet(a: Support, b: Support) -> Support {
    match (a, b) {
        (Some(a), Some(b)) => Some((a.0.max(b.0), a.1.min(b.1))),
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
        }
    }
}

impl Program {
    /// A box outside which the (scalar) value of the program is 0 for certain,
    /// or `None` when it may be non-zero anywhere.
    pub fn support(&self) -> Option<Aabb> {
        let Result3::Scalar(result) = self.result else {
            return None;
        };
        let n = self.template.len();
        let mut entry = State {
            reach: None,
            support: vec![None; n],
            point: vec![None; n],
            constant: vec![None; n],
        };
        // Inputs are registers 0..INPUTS; the constants follow them.
        for (r, &v) in self.template.iter().enumerate().skip(super::eval::INPUTS) {
            entry.constant[r] = Some(v);
            entry.support[r] = if v == 0.0 { Some(NOWHERE) } else { None };
        }
        for i in 0..3u8 {
            entry.point[usize::from(REG_X + i)] = Some(i);
        }
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
        let sup = |r: u8| s.support[usize::from(r)];
        let konst = |r: u8| s.constant[usize::from(r)];
        let same = |r: u8| sup(r);
        let (dests, support): (Vec<u8>, Support) = match op {
            Op::Copy(d, a) => {
                let (p, k, v) = (s.point[usize::from(a)], konst(a), meet(sup(a), s.reach));
                let d = usize::from(d);
                s.support[d] = v;
                s.point[d] = p;
                s.constant[d] = k;
                return;
            }
            Op::Add(d, a, b) | Op::Sub(d, a, b) => (vec![d], union(sup(a), sup(b))),
            Op::Mul(d, a, b) | Op::And(d, a, b) => (vec![d], meet(sup(a), sup(b))),
            Op::Div(d, a, b) | Op::Rem(d, a, b) => {
                let divisor_nonzero = konst(b).is_some_and(|k| k != 0.0);
                (vec![d], if divisor_nonzero { same(a) } else { None })
            }
            Op::Neg(d, a) => (vec![d], same(a)),
            // 0 < 0 and 0 != 0 are false; 0 <= 0, 0 == 0 and !0 are true.
            Op::Lt(d, a, b) | Op::Ne(d, a, b) | Op::Or(d, a, b) => (vec![d], union(sup(a), sup(b))),
            Op::Le(d, ..) | Op::Eq(d, ..) | Op::Not(d, _) => (vec![d], None),
            Op::F1(f, d, a) => match f {
                Fn1::Abs
                | Fn1::Floor
                | Fn1::Fract
                | Fn1::Sin
                | Fn1::Tan
                | Fn1::Sqrt
                | Fn1::Sign => (vec![d], same(a)),
                Fn1::Cos | Fn1::Exp | Fn1::Log => (vec![d], None),
            },
            Op::F2(f, d, a, b) => match f {
                Fn2::Min | Fn2::Max => (vec![d], union(sup(a), sup(b))),
                // bias_b(0) = gain_g(0) = 0: the second argument is t.
                Fn2::Bias | Fn2::Gain => (vec![d], same(b)),
                Fn2::Pow | Fn2::Atan2 | Fn2::Step => (vec![d], None),
            },
            Op::BiasK(d, a, _) | Op::GainK(d, a, _) => (vec![d], same(a)),
            Op::Clamp(d, v, lo, hi) => {
                let keeps_zero =
                    konst(lo).is_some_and(|l| l <= 0.0) && konst(hi).is_some_and(|h| h >= 0.0);
                (vec![d], if keeps_zero { same(v) } else { None })
            }
            Op::Density(d, object, p) => {
                let at_x = (0..3u8).all(|i| s.point[usize::from(p[usize::from(i)])] == Some(i));
                let support = if at_x {
                    self.objects[usize::from(object)].support()
                } else {
                    None
                };
                (vec![d], support)
            }
            Op::Smoothstep(d, ..)
            | Op::Noise(d, _)
            | Op::Turbulence(d, ..)
            | Op::Fbm(d, ..)
            | Op::Improved(d, _) => (vec![d], None),
            Op::VNoise(d, _) | Op::DNoise(d, _) | Op::Project(d, _) | Op::ColourMap(d, _) => {
                (d.to_vec(), None)
            }
            Op::Jump(_) | Op::JumpIfZero(..) => {
                unreachable!("control flow is followed by the caller")
            }
        };
        // Only points inside `reach` run this operation: whatever it writes is 0
        // outside `reach` as far as any later reader on this path can tell.
        let support = meet(support, s.reach);
        for d in dests {
            let d = usize::from(d);
            s.support[d] = support;
            s.point[d] = None;
            s.constant[d] = None;
        }
    }
}

#[cfg(test)]
mod tests {
    use std::collections::BTreeMap;

    use glam::Vec3;

    use crate::density::{Aabb, Density};
    use crate::pse::{Context, Kind, compile_expression, parse_functions};
    use crate::scene::desc::ObjectDesc;

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
    fn anything_else_may_be_non_zero_anywhere() {
        assert_eq!(support("noise(x)"), None);
        assert_eq!(support("D(x) + 0.1"), None);
        assert_eq!(support("D(x + [0.5, 0, 0])"), None);
        assert_eq!(support("cos(D(x))"), None);
        assert_eq!(support("if D(x) > 0 { 1 } else { 0.5 }"), None);
        assert_eq!(support("if D(x) <= 0 { 1 } else { D(x) }"), None);
    }
}
