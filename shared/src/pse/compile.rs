//! Type checking and compilation of an expression into register code.
//!
//! Compilation walks the syntax tree once. Every value is a number or a 3-vector
//! (a vector is three scalar registers), known at load: a vector where a number
//! is expected is an error here, never at render time. Constants (literals and
//! knobs) are folded in double precision; what is left becomes [`Op`]s over
//! registers that are reused as soon as their value is dead. Scene functions are
//! inlined at each call with the types of that call's arguments; a function may
//! only call functions defined before it, so there is no recursion, and the size
//! of the result is capped ([`MAX_OPS`], [`MAX_REGISTERS`]).

use std::collections::{BTreeMap, HashMap};

use super::ExprError;
use super::eval::{
    Fn1, Fn2, INPUTS, MAX_OPS, MAX_REGISTERS, Op, Program, REG_D, REG_FRAME, REG_T, REG_X, Result3,
    V,
};
use super::parser::{
    BinOp, Block, Expr, ExprKind, FnDef, UnOp, parse_definitions, parse_expression,
};
use crate::field::curve::Curve;
use crate::field::density::Density;
use crate::field::shaping::{Bias, Gain};

/// Most scene functions.
pub const MAX_FUNCTIONS: usize = 64;
/// Most noise evaluations one evaluation may do (counting every branch and the
/// largest octave count where it is not a constant), so that no scene, however
/// small its text, makes a sample arbitrarily slow.
pub const MAX_NOISE_PER_SAMPLE: u32 = 4096;

/// What an expression computes, which decides its type and its inputs.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Kind {
    /// A density (a number) at the point x.
    Density,
    /// A colour (a vector; a number is grey) at a sample of density d.
    Colour,
    /// A displacement of the shading normal (a vector) at a sample of density d.
    Normal,
    /// Anything (`coordinator eval`); d is an input.
    Probe,
}

impl Kind {
    fn has_d(self) -> bool {
        !matches!(self, Kind::Density)
    }
}

/// What an expression can refer to besides the built-ins: the scene's knobs,
/// functions and soft objects, and its colour map.
#[derive(Clone, Copy, Debug)]
pub struct Context<'a> {
    /// Knob values (after command-line overrides).
    pub knobs: &'a BTreeMap<String, f64>,
    /// Scene functions, in definition order.
    pub functions: &'a [FnDef],
    /// Soft objects callable by name: `D` (the scene's object) and named objects.
    pub objects: &'a [(String, Density)],
    /// The primitive whose inner surface `project` projects onto.
    pub surface: Option<&'a Density>,
    /// The scene's colour map.
    pub colour_map: Option<&'a Curve<3>>,
}

/// The family of a built-in function: which of the compiler's emitters
/// compiles its call (each family type-checks, folds constants and emits its
/// operations alike).
#[derive(Clone, Copy, Debug)]
enum Family {
    /// A point in, noise (or its projection) out: `noise`, `improved`,
    /// `vnoise`, `dnoise`, `project`.
    Point,
    /// `turbulence` and `fbm`: a point and an octave count (6 by default).
    Octaves,
    /// `bias` and `gain`: a parameter and an argument.
    Shaping,
    /// A function of one number, component-wise on vectors.
    Unary(Fn1),
    /// A function of two numbers (`min` and `max` also of two vectors).
    Binary(Fn2),
    /// `clamp` and `smoothstep`: three numbers.
    Ternary,
    /// `mix(a, b, t)`: numbers or vectors a and b.
    Mix,
    /// Vector functions: `length`, `normalize`, `direction`, `dot`, `cross`,
    /// `colour_map`, `vec`.
    Vector,
}

/// A built-in function: its name, the argument counts it accepts and its family.
struct Builtin {
    /// The name a call uses.
    name: &'static str,
    /// The numbers of arguments it accepts.
    arity: &'static [usize],
    /// The emitter that compiles it.
    family: Family,
}

/// Shorthand for the table's rows.
const fn builtin(name: &'static str, arity: &'static [usize], family: Family) -> Builtin {
    Builtin {
        name,
        arity,
        family,
    }
}

/// Every built-in function. To add one: a row here, and its operation in the
/// family's emitter (or a new family).
const BUILTINS: &[Builtin] = &[
    builtin("noise", &[1], Family::Point),
    builtin("vnoise", &[1], Family::Point),
    builtin("dnoise", &[1], Family::Point),
    builtin("turbulence", &[1, 2], Family::Octaves),
    builtin("fbm", &[1, 2], Family::Octaves),
    builtin("bias", &[2], Family::Shaping),
    builtin("gain", &[2], Family::Shaping),
    builtin("abs", &[1], Family::Unary(Fn1::Abs)),
    builtin("floor", &[1], Family::Unary(Fn1::Floor)),
    builtin("fract", &[1], Family::Unary(Fn1::Fract)),
    builtin("sin", &[1], Family::Unary(Fn1::Sin)),
    builtin("cos", &[1], Family::Unary(Fn1::Cos)),
    builtin("tan", &[1], Family::Unary(Fn1::Tan)),
    builtin("exp", &[1], Family::Unary(Fn1::Exp)),
    builtin("log", &[1], Family::Unary(Fn1::Log)),
    builtin("sqrt", &[1], Family::Unary(Fn1::Sqrt)),
    builtin("sign", &[1], Family::Unary(Fn1::Sign)),
    builtin("pow", &[2], Family::Binary(Fn2::Pow)),
    builtin("min", &[2], Family::Binary(Fn2::Min)),
    builtin("max", &[2], Family::Binary(Fn2::Max)),
    builtin("atan2", &[2], Family::Binary(Fn2::Atan2)),
    builtin("step", &[2], Family::Binary(Fn2::Step)),
    builtin("clamp", &[3], Family::Ternary),
    builtin("smoothstep", &[3], Family::Ternary),
    builtin("mix", &[3], Family::Mix),
    builtin("length", &[1], Family::Vector),
    builtin("normalize", &[1], Family::Vector),
    builtin("direction", &[1], Family::Vector),
    builtin("dot", &[2], Family::Vector),
    builtin("cross", &[2], Family::Vector),
    builtin("project", &[1], Family::Point),
    builtin("colour_map", &[1], Family::Vector),
    builtin("improved", &[1, 3], Family::Point),
    builtin("vec", &[3], Family::Vector),
];

/// Names that are not functions but that a scene may not define either: the
/// object `D` and the inputs.
const RESERVED: [&str; 5] = ["D", "x", "t", "frame", "d"];

/// Whether `name` belongs to the language (a built-in function or a reserved name).
fn is_builtin(name: &str) -> bool {
    BUILTINS.iter().any(|b| b.name == name) || RESERVED.contains(&name)
}

/// Parses the scene's function definitions and checks their names and parameters.
pub fn parse_functions(src: &str) -> Result<Vec<FnDef>, ExprError> {
    let defs = parse_definitions(src)?;
    if defs.len() > MAX_FUNCTIONS {
        return Err(ExprError::new(
            defs[MAX_FUNCTIONS].at,
            format!("at most {MAX_FUNCTIONS} functions may be defined"),
        ));
    }
    for (i, f) in defs.iter().enumerate() {
        if is_builtin(&f.name) || f.name == "pi" {
            return Err(ExprError::new(
                f.at,
                format!("`{}` is a built-in name; choose another", f.name),
            ));
        }
        if defs[..i].iter().any(|g| g.name == f.name) {
            return Err(ExprError::new(
                f.at,
                format!("function `{}` is defined twice", f.name),
            ));
        }
        for (j, (p, at)) in f.params.iter().enumerate() {
            if f.params[..j].iter().any(|(q, _)| q == p) {
                return Err(ExprError::new(
                    *at,
                    format!("parameter `{p}` appears twice"),
                ));
            }
        }
    }
    Ok(defs)
}

/// Parses, checks and compiles `src` as an expression of `kind` in `ctx`.
pub fn compile_expression(src: &str, kind: Kind, ctx: &Context) -> Result<Program, ExprError> {
    let block = parse_expression(src)?;
    let mut c = Compiler::new(ctx, kind);
    let value = c.block(&block)?;
    let value = match (kind, value) {
        (Kind::Density, Val::V(_)) => {
            return Err(ExprError::new(
                block.value.at,
                "a density must be a number, but this is a vector",
            ));
        }
        (Kind::Normal, Val::S(_)) => {
            return Err(ExprError::new(
                block.value.at,
                "a normal perturbation must be a vector, but this is a number",
            ));
        }
        (Kind::Colour, Val::S(s)) => Val::V([s; 3]),
        (_, v) => v,
    };
    let constant = match value {
        Val::S(S::K(v)) => Some([v; 3]),
        Val::V([S::K(a), S::K(b), S::K(c)]) => Some([a, b, c]),
        _ => None,
    };
    let at = block.value.at;
    let result = match value {
        Val::S(s) => Result3::Scalar(c.reg(s, at)?),
        Val::V(v) => Result3::Vector([c.reg(v[0], at)?, c.reg(v[1], at)?, c.reg(v[2], at)?]),
    };
    Ok(Program {
        ops: c.ops,
        template: c.template,
        result,
        objects: ctx.objects.iter().map(|(_, d)| d.clone()).collect(),
        surface: ctx.surface.cloned(),
        colour_map: ctx.colour_map.cloned(),
        constant,
    })
}

/// A scalar at compile time: a constant (double precision) or a register.
#[derive(Clone, Copy, Debug, PartialEq)]
enum S {
    K(f64),
    R(u8),
}

/// A value at compile time.
#[derive(Clone, Copy, Debug, PartialEq)]
enum Val {
    S(S),
    V([S; 3]),
}

impl Val {
    fn type_name(self) -> &'static str {
        match self {
            Val::S(_) => "a number",
            Val::V(_) => "a vector",
        }
    }

    fn scalars(self) -> Vec<S> {
        match self {
            Val::S(s) => vec![s],
            Val::V(v) => v.to_vec(),
        }
    }
}

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum RegState {
    /// An input or a constant: never freed.
    Fixed,
    /// A temporary, bound by `pins` lets or parameters.
    Temp { pins: u32 },
    /// Free for reuse.
    Free,
}

struct Compiler<'a> {
    ctx: &'a Context<'a>,
    kind: Kind,
    ops: Vec<Op>,
    template: Vec<f32>,
    state: Vec<RegState>,
    free: Vec<u8>,
    constants: HashMap<u32, u8>,
    /// Bindings visible in the current function body (or the expression), innermost last.
    scope: Vec<(String, Val)>,
    /// Functions callable from the current body: `ctx.functions[..visible]`.
    visible: usize,
    /// Noise evaluations of the ops so far (an upper bound per evaluation).
    noise_cost: u32,
}

fn fold1(f: Fn1, a: f64) -> f64 {
    match f {
        Fn1::Abs => a.abs(),
        Fn1::Floor => libm::floor(a),
        Fn1::Fract => a - libm::floor(a),
        Fn1::Sin => libm::sin(a),
        Fn1::Cos => libm::cos(a),
        Fn1::Tan => libm::tan(a),
        Fn1::Exp => libm::exp(a),
        Fn1::Log => libm::log(a),
        Fn1::Sqrt => libm::sqrt(a),
        Fn1::Sign => {
            if a > 0.0 {
                1.0
            } else if a < 0.0 {
                -1.0
            } else {
                0.0
            }
        }
    }
}

fn fold2(f: Fn2, a: f64, b: f64) -> f64 {
    match f {
        Fn2::Pow => libm::pow(a, b),
        Fn2::Min => {
            if b < a {
                b
            } else {
                a
            }
        }
        Fn2::Max => {
            if b > a {
                b
            } else {
                a
            }
        }
        Fn2::Atan2 => libm::atan2(a, b),
        Fn2::Step => f64::from(u8::from(b >= a)),
        Fn2::Bias => f64::from(Bias::new(a as f32).apply(b as f32)),
        Fn2::Gain => f64::from(Gain::new(a as f32).apply(b as f32)),
    }
}

fn truth(b: bool) -> f64 {
    if b { 1.0 } else { 0.0 }
}

impl<'a> Compiler<'a> {
    fn new(ctx: &'a Context<'a>, kind: Kind) -> Compiler<'a> {
        Compiler {
            ctx,
            kind,
            ops: Vec::new(),
            template: vec![0.0; INPUTS],
            state: vec![RegState::Fixed; INPUTS],
            free: Vec::new(),
            constants: HashMap::new(),
            scope: Vec::new(),
            visible: ctx.functions.len(),
            noise_cost: 0,
        }
    }

    fn emit(&mut self, op: Op, at: usize) -> Result<(), ExprError> {
        if self.ops.len() >= MAX_OPS {
            return Err(ExprError::new(
                at,
                format!("the expression compiles to more than {MAX_OPS} operations"),
            ));
        }
        let octaves = |r: u8| match self.template.get(usize::from(r)) {
            Some(&k) if self.state[usize::from(r)] == RegState::Fixed && k >= 0.0 => {
                (k.min(16.0)) as u32
            }
            _ => 16,
        };
        self.noise_cost += match op {
            Op::Noise(..) | Op::Improved(..) | Op::Density(..) => 1,
            Op::VNoise(..) => 3,
            Op::DNoise(..) => 6,
            Op::Turbulence(_, _, o) | Op::Fbm(_, _, o) => octaves(o),
            _ => 0,
        };
        if self.noise_cost > MAX_NOISE_PER_SAMPLE {
            return Err(ExprError::new(
                at,
                format!(
                    "the expression evaluates noise more than {MAX_NOISE_PER_SAMPLE} times per sample"
                ),
            ));
        }
        self.ops.push(op);
        Ok(())
    }

    fn new_register(&mut self, at: usize, state: RegState) -> Result<u8, ExprError> {
        if self.template.len() >= MAX_REGISTERS {
            return Err(ExprError::new(
                at,
                format!("the expression needs more than {MAX_REGISTERS} registers"),
            ));
        }
        self.template.push(0.0);
        self.state.push(state);
        Ok((self.template.len() - 1) as u8)
    }

    fn alloc(&mut self, at: usize) -> Result<u8, ExprError> {
        if let Some(r) = self.free.pop() {
            self.state[usize::from(r)] = RegState::Temp { pins: 0 };
            return Ok(r);
        }
        self.new_register(at, RegState::Temp { pins: 0 })
    }

    fn alloc_v(&mut self, at: usize) -> Result<V, ExprError> {
        Ok([self.alloc(at)?, self.alloc(at)?, self.alloc(at)?])
    }

    /// The register holding `s` (constants get a register of the template).
    fn reg(&mut self, s: S, at: usize) -> Result<u8, ExprError> {
        match s {
            S::R(r) => Ok(r),
            S::K(v) => {
                let v = v as f32;
                if let Some(&r) = self.constants.get(&v.to_bits()) {
                    return Ok(r);
                }
                let r = self.new_register(at, RegState::Fixed)?;
                self.template[usize::from(r)] = v;
                self.constants.insert(v.to_bits(), r);
                Ok(r)
            }
        }
    }

    fn reg_v(&mut self, v: [S; 3], at: usize) -> Result<V, ExprError> {
        Ok([
            self.reg(v[0], at)?,
            self.reg(v[1], at)?,
            self.reg(v[2], at)?,
        ])
    }

    /// Frees the temporaries of a dead value (idempotent).
    fn release(&mut self, v: Val) {
        for s in v.scalars() {
            if let S::R(r) = s
                && self.state[usize::from(r)] == (RegState::Temp { pins: 0 })
            {
                self.state[usize::from(r)] = RegState::Free;
                self.free.push(r);
            }
        }
    }

    fn pin(&mut self, v: Val, by: i32) {
        for s in v.scalars() {
            if let S::R(r) = s
                && let RegState::Temp { pins } = &mut self.state[usize::from(r)]
            {
                *pins = pins.saturating_add_signed(by);
            }
        }
    }

    fn scalar(&self, v: Val, at: usize, what: &str) -> Result<S, ExprError> {
        match v {
            Val::S(s) => Ok(s),
            Val::V(_) => Err(ExprError::new(
                at,
                format!("{what} must be a number, but this is a vector"),
            )),
        }
    }

    fn vector(&self, v: Val, at: usize, what: &str) -> Result<[S; 3], ExprError> {
        match v {
            Val::V(v) => Ok(v),
            Val::S(_) => Err(ExprError::new(
                at,
                format!("{what} must be a vector, but this is a number (write [a, b, c])"),
            )),
        }
    }

    fn block(&mut self, b: &Block) -> Result<Val, ExprError> {
        let depth = self.scope.len();
        for (name, _, e) in &b.lets {
            let v = self.expr(e)?;
            self.pin(v, 1);
            self.scope.push((name.clone(), v));
        }
        let value = self.expr(&b.value)?;
        // The value may be a let's registers: keep them alive while unbinding.
        self.pin(value, 1);
        for (_, v) in self.scope.split_off(depth) {
            self.pin(v, -1);
            self.release(v);
        }
        self.pin(value, -1);
        Ok(value)
    }

    fn expr(&mut self, e: &Expr) -> Result<Val, ExprError> {
        match &e.kind {
            ExprKind::Num(v) => Ok(Val::S(S::K(*v))),
            ExprKind::Var(name) => self.var(name, e.at),
            ExprKind::Vector(parts) => {
                let mut out = [S::K(0.0); 3];
                for (i, p) in parts.iter().enumerate() {
                    let v = self.expr(p)?;
                    out[i] = self.scalar(v, p.at, "a vector component")?;
                }
                Ok(Val::V(out))
            }
            ExprKind::Component(v, i) => {
                let val = self.expr(v)?;
                let parts = self.vector(val, v.at, "the value before `.x`, `.y` or `.z`")?;
                let kept = parts[usize::from(*i)];
                for s in parts {
                    // `[s, s, s].x` shares s's register with the result.
                    if s != kept {
                        self.release(Val::S(s));
                    }
                }
                Ok(Val::S(kept))
            }
            ExprKind::Unary(op, a) => {
                let v = self.expr(a)?;
                match (op, v) {
                    (UnOp::Neg, Val::S(s)) => {
                        let out = self.neg(s, e.at)?;
                        self.release(v);
                        Ok(Val::S(out))
                    }
                    (UnOp::Neg, Val::V(p)) => {
                        // Every component first: `-[s, s, s]` reads s three times.
                        let mut out = [S::K(0.0); 3];
                        for i in 0..3 {
                            out[i] = self.neg(p[i], e.at)?;
                        }
                        self.release(v);
                        Ok(Val::V(out))
                    }
                    (UnOp::Not, v) => {
                        let s = self.scalar(v, a.at, "the operand of `!`")?;
                        if let S::K(k) = s {
                            return Ok(Val::S(S::K(truth(k == 0.0))));
                        }
                        let ra = self.reg(s, e.at)?;
                        let d = self.alloc(e.at)?;
                        self.emit(Op::Not(d, ra), e.at)?;
                        self.release(v);
                        Ok(Val::S(S::R(d)))
                    }
                }
            }
            ExprKind::Binary(op, a, b) => {
                if *op == BinOp::Mul {
                    if self.is_density_call(b) {
                        return self.times_density(a, b, false, e.at);
                    }
                    if self.is_density_call(a) {
                        return self.times_density(b, a, true, e.at);
                    }
                }
                let va = self.expr(a)?;
                let vb = self.expr(b)?;
                self.binary(*op, va, vb, a.at, b.at, e.at)
            }
            ExprKind::If(cond, then, otherwise) => self.if_else(cond, then, otherwise, e.at),
            ExprKind::Call(name, args) => self.call(name, args, e.at),
        }
    }

    fn var(&mut self, name: &str, at: usize) -> Result<Val, ExprError> {
        if let Some((_, v)) = self.scope.iter().rev().find(|(n, _)| n == name) {
            return Ok(*v);
        }
        if let Some(&k) = self.ctx.knobs.get(name) {
            return Ok(Val::S(S::K(k)));
        }
        Ok(match name {
            "x" => Val::V([S::R(REG_X), S::R(REG_X + 1), S::R(REG_X + 2)]),
            "t" => Val::S(S::R(REG_T)),
            "frame" => Val::S(S::R(REG_FRAME)),
            "pi" => Val::S(S::K(std::f64::consts::PI)),
            "d" if self.kind.has_d() => Val::S(S::R(REG_D)),
            "d" => {
                return Err(ExprError::new(
                    at,
                    "`d` (the density at the sample) is known only in colour and normal expressions; a density expression calls D(x)",
                ));
            }
            _ => {
                let mut known: Vec<&str> = self
                    .scope
                    .iter()
                    .map(|(n, _)| n.as_str())
                    .chain(self.ctx.knobs.keys().map(String::as_str))
                    .collect();
                known.extend(["x", "t", "frame", "pi"]);
                if self.kind.has_d() {
                    known.push("d");
                }
                known.dedup();
                let hint = if self.ctx.objects.iter().any(|(n, _)| n == name)
                    || self.ctx.functions.iter().any(|f| f.name == name)
                    || is_builtin(name)
                {
                    format!(" (`{name}` is a function: call it, `{name}(...)`)")
                } else {
                    String::new()
                };
                return Err(ExprError::new(
                    at,
                    format!(
                        "unknown name `{name}`{hint}; expected one of: {}",
                        known.join(", ")
                    ),
                ));
            }
        })
    }

    /// `-s` in a new register (the caller releases s).
    fn neg(&mut self, s: S, at: usize) -> Result<S, ExprError> {
        if let S::K(k) = s {
            return Ok(S::K(-k));
        }
        let ra = self.reg(s, at)?;
        let d = self.alloc(at)?;
        self.emit(Op::Neg(d, ra), at)?;
        Ok(S::R(d))
    }

    /// A scalar binary operation, folded when both sides are constants.
    fn scalar_op(&mut self, op: BinOp, a: S, b: S, at: usize) -> Result<S, ExprError> {
        if let (S::K(x), S::K(y)) = (a, b) {
            return Ok(S::K(match op {
                BinOp::Add => x + y,
                BinOp::Sub => x - y,
                BinOp::Mul => x * y,
                BinOp::Div => x / y,
                BinOp::Rem => libm::fmod(x, y),
                BinOp::Lt => truth(x < y),
                BinOp::Le => truth(x <= y),
                BinOp::Gt => truth(x > y),
                BinOp::Ge => truth(x >= y),
                BinOp::Eq => truth(x == y),
                BinOp::Ne => truth(x != y),
                BinOp::And => truth(x != 0.0 && y != 0.0),
                BinOp::Or => truth(x != 0.0 || y != 0.0),
            }));
        }
        let (ra, rb) = (self.reg(a, at)?, self.reg(b, at)?);
        let d = self.alloc(at)?;
        let o = match op {
            BinOp::Add => Op::Add(d, ra, rb),
            BinOp::Sub => Op::Sub(d, ra, rb),
            BinOp::Mul => Op::Mul(d, ra, rb),
            BinOp::Div => Op::Div(d, ra, rb),
            BinOp::Rem => Op::Rem(d, ra, rb),
            BinOp::Lt => Op::Lt(d, ra, rb),
            BinOp::Le => Op::Le(d, ra, rb),
            BinOp::Gt => Op::Lt(d, rb, ra),
            BinOp::Ge => Op::Le(d, rb, ra),
            BinOp::Eq => Op::Eq(d, ra, rb),
            BinOp::Ne => Op::Ne(d, ra, rb),
            BinOp::And => Op::And(d, ra, rb),
            BinOp::Or => Op::Or(d, ra, rb),
        };
        self.emit(o, at)?;
        Ok(S::R(d))
    }

    fn binary(
        &mut self,
        op: BinOp,
        va: Val,
        vb: Val,
        at_a: usize,
        at_b: usize,
        at: usize,
    ) -> Result<Val, ExprError> {
        let arithmetic = matches!(
            op,
            BinOp::Add | BinOp::Sub | BinOp::Mul | BinOp::Div | BinOp::Rem
        );
        let out = match (va, vb) {
            (Val::S(a), Val::S(b)) => Val::S(self.scalar_op(op, a, b, at)?),
            (Val::V(a), Val::V(b)) if arithmetic => {
                let mut out = [S::K(0.0); 3];
                for i in 0..3 {
                    out[i] = self.scalar_op(op, a[i], b[i], at)?;
                }
                Val::V(out)
            }
            (Val::V(a), Val::S(b)) if arithmetic => {
                let mut out = [S::K(0.0); 3];
                for i in 0..3 {
                    out[i] = self.scalar_op(op, a[i], b, at)?;
                }
                Val::V(out)
            }
            (Val::S(a), Val::V(b)) if matches!(op, BinOp::Mul | BinOp::Div) => {
                let mut out = [S::K(0.0); 3];
                for i in 0..3 {
                    out[i] = self.scalar_op(op, a, b[i], at)?;
                }
                Val::V(out)
            }
            (Val::S(_), Val::V(_)) if arithmetic => {
                return Err(ExprError::new(
                    at_a,
                    format!(
                        "number {} vector: expected a vector on the left (write [n, n, n] for a number in every component)",
                        op.symbol()
                    ),
                ));
            }
            (a, b) => {
                let (bad, at_bad) = if matches!(a, Val::V(_)) {
                    (a, at_a)
                } else {
                    (b, at_b)
                };
                return Err(ExprError::new(
                    at_bad,
                    format!(
                        "`{}` compares numbers, but this is {}",
                        op.symbol(),
                        bad.type_name()
                    ),
                ));
            }
        };
        self.release(va);
        self.release(vb);
        Ok(out)
    }

    fn is_density_call(&self, e: &Expr) -> bool {
        matches!(&e.kind, ExprKind::Call(name, _)
            if self.ctx.objects.iter().any(|(n, _)| n == name)
                && !self.ctx.functions[..self.visible].iter().any(|f| &f.name == name))
    }

    /// `other * D(p)`: D is evaluated first and `other` only where D is not 0 (a
    /// density of 0 makes the product 0, and most of space is empty).
    fn times_density(
        &mut self,
        other: &Expr,
        density: &Expr,
        density_first: bool,
        at: usize,
    ) -> Result<Val, ExprError> {
        let dv = self.expr(density)?;
        let S::R(rd) = self.scalar(dv, density.at, "a density")? else {
            let vo = self.expr(other)?;
            return self.binary(BinOp::Mul, vo, dv, other.at, density.at, at);
        };
        self.pin(dv, 1);
        let result = self.alloc(at)?;
        self.emit(Op::Copy(result, rd), at)?;
        let jump = self.ops.len();
        self.emit(Op::JumpIfZero(rd, 0), at)?;
        let vo = self.expr(other)?;
        let so = self.scalar(
            vo,
            other.at,
            "the factor of a density (write the product the other way round for a vector)",
        )?;
        let ro = self.reg(so, at)?;
        let op = if density_first {
            Op::Mul(result, rd, ro)
        } else {
            Op::Mul(result, ro, rd)
        };
        self.emit(op, at)?;
        self.release(vo);
        self.ops[jump] = Op::JumpIfZero(rd, self.ops.len() as u16);
        self.pin(dv, -1);
        self.release(dv);
        Ok(Val::S(S::R(result)))
    }

    fn if_else(
        &mut self,
        cond: &Expr,
        then: &Block,
        otherwise: &Block,
        at: usize,
    ) -> Result<Val, ExprError> {
        let vc = self.expr(cond)?;
        let sc = self.scalar(vc, cond.at, "the condition of `if`")?;
        if let S::K(k) = sc {
            return self.constant_if(k != 0.0, then, otherwise);
        }
        let rc = self.reg(sc, cond.at)?;
        let jump = self.ops.len();
        self.emit(Op::JumpIfZero(rc, 0), at)?;
        self.release(vc);
        let vt = self.block(then)?;
        let dst: Vec<u8> = (0..vt.scalars().len())
            .map(|_| self.alloc(at))
            .collect::<Result<_, _>>()?;
        for (i, s) in vt.scalars().into_iter().enumerate() {
            let r = self.reg(s, at)?;
            self.emit(Op::Copy(dst[i], r), at)?;
        }
        self.release(vt);
        let skip = self.ops.len();
        self.emit(Op::Jump(0), at)?;
        self.ops[jump] = Op::JumpIfZero(rc, self.ops.len() as u16);
        let ve = self.block(otherwise)?;
        if ve.type_name() != vt.type_name() {
            return Err(ExprError::new(
                otherwise.value.at,
                format!(
                    "the branches of `if` differ: {} after `if`, {} after `else`",
                    vt.type_name(),
                    ve.type_name()
                ),
            ));
        }
        for (i, s) in ve.scalars().into_iter().enumerate() {
            let r = self.reg(s, at)?;
            self.emit(Op::Copy(dst[i], r), at)?;
        }
        self.release(ve);
        self.ops[skip] = Op::Jump(self.ops.len() as u16);
        Ok(match dst[..] {
            [a] => Val::S(S::R(a)),
            [a, b, c] => Val::V([S::R(a), S::R(b), S::R(c)]),
            _ => unreachable!("values have 1 or 3 components"),
        })
    }

    /// An `if` whose condition is known at load (a knob, a constant): only the
    /// branch taken is kept. The other is still compiled, in text order, so its
    /// mistakes are reported, and its operations are then dropped.
    fn constant_if(
        &mut self,
        take_then: bool,
        then: &Block,
        otherwise: &Block,
    ) -> Result<Val, ExprError> {
        let start = self.ops.len();
        let vt = self.block(then)?;
        let then_type = vt.type_name();
        if !take_then {
            self.release(vt);
            self.ops.truncate(start);
        }
        let mid = self.ops.len();
        let ve = self.block(otherwise)?;
        if ve.type_name() != then_type {
            return Err(ExprError::new(
                otherwise.value.at,
                format!(
                    "the branches of `if` differ: {then_type} after `if`, {} after `else`",
                    ve.type_name()
                ),
            ));
        }
        if take_then {
            self.release(ve);
            self.ops.truncate(mid);
            Ok(vt)
        } else {
            Ok(ve)
        }
    }

    fn call(&mut self, name: &str, args: &[Expr], at: usize) -> Result<Val, ExprError> {
        if let Some(i) = self.ctx.functions[..self.visible]
            .iter()
            .position(|f| f.name == name)
        {
            return self.inline(i, args, at);
        }
        if self.ctx.functions.iter().any(|f| f.name == name) {
            return Err(ExprError::new(
                at,
                format!(
                    "`{name}` is defined later: a function may only call functions defined before it (no recursion)"
                ),
            ));
        }
        if let Some(i) = self.ctx.objects.iter().position(|(n, _)| n == name) {
            let [p] = self.args::<1>(name, args, at)?;
            let pv = self.vector(p.0, p.1, &format!("the point of {name}(p)"))?;
            let rp = self.reg_v(pv, at)?;
            let d = self.alloc(at)?;
            self.emit(Op::Density(d, i as u16, rp), at)?;
            self.release(p.0);
            return Ok(Val::S(S::R(d)));
        }
        let Some(builtin) = BUILTINS.iter().find(|b| b.name == name) else {
            let mut names: Vec<&str> = BUILTINS.iter().map(|b| b.name).collect();
            names.extend(self.ctx.objects.iter().map(|(n, _)| n.as_str()));
            names.extend(
                self.ctx.functions[..self.visible]
                    .iter()
                    .map(|f| f.name.as_str()),
            );
            names.sort_unstable();
            names.dedup();
            return Err(ExprError::new(
                at,
                format!(
                    "unknown function `{name}`; expected one of: {}",
                    names.join(", ")
                ),
            ));
        };
        if !builtin.arity.contains(&args.len()) {
            let counts: Vec<String> = builtin.arity.iter().map(usize::to_string).collect();
            return Err(ExprError::new(
                at,
                format!(
                    "{name} takes {} argument{}, found {}",
                    counts.join(" or "),
                    if builtin.arity == [1] { "" } else { "s" },
                    args.len()
                ),
            ));
        }
        match builtin.family {
            Family::Point => self.point_builtin(name, args, at),
            Family::Octaves => self.octaves_builtin(name, args, at),
            Family::Shaping => self.shaping_builtin(name, args, at),
            Family::Unary(f) => self.unary_builtin(f, name, args, at),
            Family::Binary(f) => self.binary_builtin(f, name, args, at),
            Family::Ternary => self.ternary_builtin(name, args, at),
            Family::Mix => self.mix_builtin(name, args, at),
            Family::Vector => self.vector_builtin(name, args, at),
        }
    }

    /// `noise`, `improved`, `vnoise`, `dnoise`, `project`: a point in.
    fn point_builtin(&mut self, name: &str, args: &[Expr], at: usize) -> Result<Val, ExprError> {
        let p = if name == "improved" && args.len() == 3 {
            let [a, b, c] = self.args::<3>(name, args, at)?;
            let v = [
                self.scalar(a.0, a.1, "x")?,
                self.scalar(b.0, b.1, "y")?,
                self.scalar(c.0, c.1, "z")?,
            ];
            (Val::V(v), at)
        } else {
            let [p] = self.args::<1>(name, args, at)?;
            p
        };
        let pv = self.vector(p.0, p.1, &format!("the argument of {name}"))?;
        if name == "improved"
            && let [S::K(a), S::K(b), S::K(c)] = pv
        {
            return Ok(Val::S(S::K(crate::field::noise::improved(a, b, c))));
        }
        if name == "project" && self.ctx.surface.is_none() {
            return Err(ExprError::new(
                at,
                "project(p) projects onto the inner surface of the scene's object, which must then be a Sphere, Box, Torus or Mesh",
            ));
        }
        let rp = self.reg_v(pv, at)?;
        let out = match name {
            "noise" | "improved" => {
                let d = self.alloc(at)?;
                let op = if name == "noise" {
                    Op::Noise(d, rp)
                } else {
                    Op::Improved(d, rp)
                };
                self.emit(op, at)?;
                Val::S(S::R(d))
            }
            _ => {
                let d = self.alloc_v(at)?;
                let op = match name {
                    "vnoise" => Op::VNoise(d, rp),
                    "dnoise" => Op::DNoise(d, rp),
                    _ => Op::Project(d, rp),
                };
                self.emit(op, at)?;
                Val::V(d.map(S::R))
            }
        };
        self.release(p.0);
        Ok(out)
    }

    /// `turbulence(p, octaves)`, `fbm(p, octaves)`.
    fn octaves_builtin(&mut self, name: &str, args: &[Expr], at: usize) -> Result<Val, ExprError> {
        let (p, n) = match args.len() {
            1 => {
                let [p] = self.args::<1>(name, args, at)?;
                (p, (Val::S(S::K(6.0)), at))
            }
            _ => {
                let [p, n] = self.args::<2>(name, args, at)?;
                (p, n)
            }
        };
        let pv = self.vector(p.0, p.1, &format!("the point of {name}(p, octaves)"))?;
        let ns = self.scalar(n.0, n.1, "the octave count")?;
        let rp = self.reg_v(pv, at)?;
        let rn = self.reg(ns, at)?;
        let d = self.alloc(at)?;
        let op = if name == "fbm" {
            Op::Fbm(d, rp, rn)
        } else {
            Op::Turbulence(d, rp, rn)
        };
        self.emit(op, at)?;
        self.release(p.0);
        self.release(n.0);
        Ok(Val::S(S::R(d)))
    }

    /// `bias(b, t)`, `gain(g, t)`: constant parameters become precomputed curves.
    fn shaping_builtin(&mut self, name: &str, args: &[Expr], at: usize) -> Result<Val, ExprError> {
        let [b, t] = self.args::<2>(name, args, at)?;
        let sb = self.scalar(b.0, b.1, &format!("the parameter of {name}"))?;
        let st = self.scalar(t.0, t.1, &format!("the argument of {name}"))?;
        let f = if name == "bias" { Fn2::Bias } else { Fn2::Gain };
        if let (S::K(kb), S::K(kt)) = (sb, st) {
            return Ok(Val::S(S::K(fold2(f, kb, kt))));
        }
        let rt = self.reg(st, at)?;
        let d = self.alloc(at)?;
        let op = match sb {
            S::K(k) if name == "bias" => Op::BiasK(d, rt, Bias::new(k as f32)),
            S::K(k) => Op::GainK(d, rt, Gain::new(k as f32)),
            S::R(rb) => Op::F2(f, d, rb, rt),
        };
        self.emit(op, at)?;
        self.release(t.0);
        self.release(b.0);
        Ok(Val::S(S::R(d)))
    }

    /// `f(a)` for a function of one number, component-wise on vectors.
    fn unary_builtin(
        &mut self,
        f: Fn1,
        name: &str,
        args: &[Expr],
        at: usize,
    ) -> Result<Val, ExprError> {
        let [a] = self.args::<1>(name, args, at)?;
        // Component-wise on vectors.
        let mut out = Vec::new();
        for s in a.0.scalars() {
            out.push(match s {
                S::K(k) => S::K(fold1(f, k)),
                S::R(r) => {
                    let d = self.alloc(at)?;
                    self.emit(Op::F1(f, d, r), at)?;
                    S::R(d)
                }
            });
        }
        self.release(a.0);
        Ok(match out[..] {
            [s] => Val::S(s),
            [x, y, z] => Val::V([x, y, z]),
            _ => unreachable!("values have 1 or 3 components"),
        })
    }

    /// `f(a, b)` for a function of two numbers (`min`, `max` also on vectors).
    fn binary_builtin(
        &mut self,
        f: Fn2,
        name: &str,
        args: &[Expr],
        at: usize,
    ) -> Result<Val, ExprError> {
        let [a, b] = self.args::<2>(name, args, at)?;
        let pairs: Vec<(S, S)> = match (a.0, b.0) {
            (Val::S(x), Val::S(y)) => vec![(x, y)],
            (Val::V(x), Val::V(y)) if matches!(f, Fn2::Min | Fn2::Max) => {
                (0..3).map(|i| (x[i], y[i])).collect()
            }
            _ => {
                let bad = if matches!(a.0, Val::V(_)) { a } else { b };
                return Err(ExprError::new(
                    bad.1,
                    format!("the arguments of {name} must be numbers, but this is a vector"),
                ));
            }
        };
        let mut out = Vec::new();
        for (x, y) in pairs {
            out.push(match (x, y) {
                (S::K(x), S::K(y)) => S::K(fold2(f, x, y)),
                _ => {
                    let (rx, ry) = (self.reg(x, at)?, self.reg(y, at)?);
                    let d = self.alloc(at)?;
                    self.emit(Op::F2(f, d, rx, ry), at)?;
                    S::R(d)
                }
            });
        }
        self.release(a.0);
        self.release(b.0);
        Ok(match out[..] {
            [s] => Val::S(s),
            [x, y, z] => Val::V([x, y, z]),
            _ => unreachable!("values have 1 or 3 components"),
        })
    }

    /// `clamp(x, lo, hi)`, `smoothstep(lo, hi, x)`.
    fn ternary_builtin(&mut self, name: &str, args: &[Expr], at: usize) -> Result<Val, ExprError> {
        let [a, b, c] = self.args::<3>(name, args, at)?;
        let sa = self.scalar(a.0, a.1, &format!("each argument of {name}"))?;
        let sb = self.scalar(b.0, b.1, &format!("each argument of {name}"))?;
        let sc = self.scalar(c.0, c.1, &format!("each argument of {name}"))?;
        if let (S::K(x), S::K(y), S::K(z)) = (sa, sb, sc) {
            let v = if name == "clamp" {
                fold2(Fn2::Max, fold2(Fn2::Min, x, z), y)
            } else {
                let t = ((z - x) / (y - x)).clamp(0.0, 1.0);
                t * t * (3.0 - 2.0 * t)
            };
            return Ok(Val::S(S::K(v)));
        }
        let (ra, rb, rc) = (self.reg(sa, at)?, self.reg(sb, at)?, self.reg(sc, at)?);
        let d = self.alloc(at)?;
        let op = if name == "clamp" {
            Op::Clamp(d, ra, rb, rc)
        } else {
            Op::Smoothstep(d, ra, rb, rc)
        };
        self.emit(op, at)?;
        for v in [a.0, b.0, c.0] {
            self.release(v);
        }
        Ok(Val::S(S::R(d)))
    }

    /// `mix(a, b, t)`.
    fn mix_builtin(&mut self, name: &str, args: &[Expr], at: usize) -> Result<Val, ExprError> {
        let [a, b, t] = self.args::<3>(name, args, at)?;
        let st = self.scalar(t.0, t.1, "the weight of mix")?;
        if a.0.type_name() != b.0.type_name() {
            return Err(ExprError::new(
                b.1,
                format!(
                    "mix(a, b, t) needs a and b of one type, but a is {} and this is {}",
                    a.0.type_name(),
                    b.0.type_name()
                ),
            ));
        }
        // a + (b - a) t, component by component; a stays alive throughout.
        self.pin(a.0, 1);
        let diff = self.binary(BinOp::Sub, b.0, a.0, b.1, a.1, at)?;
        let scaled = self.binary(BinOp::Mul, diff, Val::S(st), at, t.1, at)?;
        self.pin(scaled, 1);
        let out = self.binary(BinOp::Add, a.0, scaled, a.1, at, at)?;
        self.pin(scaled, -1);
        self.pin(a.0, -1);
        // (t was released by the product that consumed it.)
        self.release(scaled);
        self.release(a.0);
        Ok(out)
    }

    fn dot(&mut self, a: [S; 3], b: [S; 3], at: usize) -> Result<S, ExprError> {
        let xx = self.scalar_op(BinOp::Mul, a[0], b[0], at)?;
        let yy = self.scalar_op(BinOp::Mul, a[1], b[1], at)?;
        let s = self.scalar_op(BinOp::Add, xx, yy, at)?;
        self.release(Val::S(xx));
        self.release(Val::S(yy));
        let zz = self.scalar_op(BinOp::Mul, a[2], b[2], at)?;
        let out = self.scalar_op(BinOp::Add, s, zz, at)?;
        self.release(Val::S(s));
        self.release(Val::S(zz));
        Ok(out)
    }

    fn vector_builtin(&mut self, name: &str, args: &[Expr], at: usize) -> Result<Val, ExprError> {
        match name {
            "vec" => {
                let [a, b, c] = self.args::<3>(name, args, at)?;
                Ok(Val::V([
                    self.scalar(a.0, a.1, "a vector component")?,
                    self.scalar(b.0, b.1, "a vector component")?,
                    self.scalar(c.0, c.1, "a vector component")?,
                ]))
            }
            "colour_map" => {
                let [s] = self.args::<1>(name, args, at)?;
                let ss = self.scalar(s.0, s.1, "the argument of colour_map")?;
                let rs = self.reg(ss, at)?;
                let d = self.alloc_v(at)?;
                self.emit(Op::ColourMap(d, rs), at)?;
                self.release(s.0);
                Ok(Val::V(d.map(S::R)))
            }
            // `direction` is the 1985 paper's name for `normalize`.
            "length" | "normalize" | "direction" => {
                let [a] = self.args::<1>(name, args, at)?;
                let v = self.vector(a.0, a.1, &format!("the argument of {name}"))?;
                let l2 = self.dot(v, v, at)?;
                let len = match l2 {
                    S::K(k) => S::K(libm::sqrt(k)),
                    S::R(r) => {
                        let d = self.alloc(at)?;
                        self.emit(Op::F1(Fn1::Sqrt, d, r), at)?;
                        self.release(Val::S(l2));
                        S::R(d)
                    }
                };
                if name == "length" {
                    self.release(a.0);
                    return Ok(Val::S(len));
                }
                let mut out = [S::K(0.0); 3];
                for i in 0..3 {
                    out[i] = self.scalar_op(BinOp::Div, v[i], len, at)?;
                }
                self.release(Val::S(len));
                self.release(a.0);
                Ok(Val::V(out))
            }
            "dot" => {
                let [a, b] = self.args::<2>(name, args, at)?;
                let va = self.vector(a.0, a.1, "each argument of dot")?;
                let vb = self.vector(b.0, b.1, "each argument of dot")?;
                let out = self.dot(va, vb, at)?;
                self.release(a.0);
                self.release(b.0);
                Ok(Val::S(out))
            }
            _ => {
                let [a, b] = self.args::<2>(name, args, at)?;
                let u = self.vector(a.0, a.1, "each argument of cross")?;
                let v = self.vector(b.0, b.1, "each argument of cross")?;
                let mut out = [S::K(0.0); 3];
                for (i, (j, k)) in [(1, 2), (2, 0), (0, 1)].into_iter().enumerate() {
                    let p = self.scalar_op(BinOp::Mul, u[j], v[k], at)?;
                    let q = self.scalar_op(BinOp::Mul, u[k], v[j], at)?;
                    out[i] = self.scalar_op(BinOp::Sub, p, q, at)?;
                    self.release(Val::S(p));
                    self.release(Val::S(q));
                }
                self.release(a.0);
                self.release(b.0);
                Ok(Val::V(out))
            }
        }
    }

    /// Compiles exactly `N` arguments: (value, offset) each.
    fn args<const N: usize>(
        &mut self,
        name: &str,
        args: &[Expr],
        at: usize,
    ) -> Result<[(Val, usize); N], ExprError> {
        if args.len() != N {
            return Err(ExprError::new(
                at,
                format!(
                    "{name} takes {N} argument{}, found {}",
                    if N == 1 { "" } else { "s" },
                    args.len()
                ),
            ));
        }
        let mut out = [(Val::S(S::K(0.0)), 0); N];
        for (i, a) in args.iter().enumerate() {
            let v = self.expr(a)?;
            // Keep earlier arguments alive while later ones are compiled.
            self.pin(v, 1);
            out[i] = (v, a.at);
        }
        for (v, _) in out {
            self.pin(v, -1);
        }
        Ok(out)
    }

    fn inline(&mut self, index: usize, args: &[Expr], at: usize) -> Result<Val, ExprError> {
        let f = &self.ctx.functions[index];
        if args.len() != f.params.len() {
            return Err(ExprError::new(
                at,
                format!(
                    "{} takes {} argument(s), found {}",
                    f.name,
                    f.params.len(),
                    args.len()
                ),
            ));
        }
        let mut bound = Vec::new();
        for ((p, _), a) in f.params.iter().zip(args) {
            let v = self.expr(a)?;
            self.pin(v, 1);
            bound.push((p.clone(), v));
        }
        let saved_scope = std::mem::replace(&mut self.scope, bound);
        let saved_visible = std::mem::replace(&mut self.visible, index);
        let result = self.block(&f.body).map_err(|mut e| {
            if !e.message.starts_with("in function") {
                let (line, column) = e.line_column(&f.source);
                e.message = format!(
                    "in function `{}`, at {line}:{column} of functions: {}",
                    f.name, e.message
                );
                e.at = at;
            }
            e
        });
        self.visible = saved_visible;
        let bound = std::mem::replace(&mut self.scope, saved_scope);
        let value = result?;
        self.pin(value, 1);
        for (_, v) in bound {
            self.pin(v, -1);
            self.release(v);
        }
        self.pin(value, -1);
        Ok(value)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::field::domain::Field;
    use crate::field::noise::Noise;
    use glam::Vec3;

    fn field(noise: &Noise) -> Field<'_> {
        Field {
            noise,
            offset: Vec3::ZERO,
            frame: 0,
            time: 0.0,
            frame_rate: 24.0,
            pose: None,
            support: None,
        }
    }

    /// Knobs and functions, no objects, no colour map.
    fn plain_context<'a>(knobs: &'a BTreeMap<String, f64>, functions: &'a [FnDef]) -> Context<'a> {
        Context {
            knobs,
            functions,
            objects: &[],
            surface: None,
            colour_map: None,
        }
    }

    fn ctx_eval(src: &str, x: Vec3) -> Result<[f32; 3], ExprError> {
        let knobs = BTreeMap::from([("freq".to_string(), 4.0)]);
        let functions =
            parse_functions("fn sq(a) { a * a } fn quad(a) { sq(sq(a)) }\nfn bad(a) { a < 1 }")
                .unwrap();
        let ctx = plain_context(&knobs, &functions);
        let p = compile_expression(src, Kind::Probe, &ctx)?;
        let noise = Noise::default();
        let f = field(&noise);
        let value = p.eval(super::super::eval::Inputs { x, d: 0.25 }, &f);
        // The lane-parallel register code gives the same bits on every path.
        let mut points = crate::field::domain::Points::default();
        for l in 0..crate::math::simd::LANES {
            points.set(l, x);
        }
        for isa in crate::math::simd::Isa::available() {
            let lanes = p.eval_lanes(&points, &[0.25; crate::math::simd::LANES], &f, isa);
            for (c, lane) in lanes.iter().enumerate() {
                for v in lane {
                    assert_eq!(v.to_bits(), value[c].to_bits(), "{src} on {isa:?}");
                }
            }
        }
        Ok(value)
    }

    fn scalar(src: &str) -> f32 {
        ctx_eval(src, Vec3::new(1.0, 2.0, 3.0)).unwrap()[0]
    }

    #[test]
    fn lanes_that_part_ways_give_each_points_value() {
        let knobs = BTreeMap::from([("freq".to_string(), 4.0)]);
        let functions = parse_functions("fn sq(a) { a * a }").unwrap();
        let ctx = plain_context(&knobs, &functions);
        let noise = Noise::default();
        let f = field(&noise);
        let mut points = crate::field::domain::Points::default();
        let at = |l: usize| Vec3::new(l as f32 * 0.3 - 1.0, (l % 3) as f32 * 0.7, 0.2 * l as f32);
        for l in 0..crate::math::simd::LANES {
            points.set(l, at(l));
        }
        let d: [f32; crate::math::simd::LANES] = std::array::from_fn(|l| l as f32 / 8.0);
        for src in [
            "if x.x > 0 { noise(x * freq) } else { sq(x.y) + d }",
            "if x.x > 0.5 { 1 } else if x.y > 0.5 { vnoise(x).y } else if d > 0.3 { 3 } else { x.z }",
            "let a = if x.y > 0.2 { x * 2 } else { x + [1, 0, 0] }; if a.x < 0 { length(a) } else { turbulence(a, 3) }",
            "let s = if x.z > 0.5 { noise(x) } else { 0 }; if s > 0 { s * 2 } else { s - 1 }",
            "if x.x > 10 { 1 } else { 2 }",
        ] {
            let p = compile_expression(src, Kind::Probe, &ctx).unwrap();
            for isa in crate::math::simd::Isa::available() {
                let lanes = p.eval_lanes(&points, &d, &f, isa);
                for l in 0..crate::math::simd::LANES {
                    let one = p.eval(super::super::eval::Inputs { x: at(l), d: d[l] }, &f);
                    for c in 0..3 {
                        assert_eq!(
                            lanes[c][l].to_bits(),
                            one[c].to_bits(),
                            "{src}, lane {l}, {isa:?}"
                        );
                    }
                }
            }
        }
    }

    #[test]
    fn an_if_known_at_load_keeps_one_branch() {
        let knobs = BTreeMap::from([("freq".to_string(), 4.0)]);
        let ctx = plain_context(&knobs, &[]);
        let compile = |src| compile_expression(src, Kind::Probe, &ctx);
        // The operations, whatever their registers.
        let code = |src| {
            let ops = compile(src).map(|p| p.ops).unwrap();
            ops.iter().map(std::mem::discriminant).collect::<Vec<_>>()
        };
        let folded = code("if freq > 2 { noise(x) } else { turbulence(x, 4) + 1 }");
        assert_eq!(folded, code("noise(x)"));
        let folded = code("if freq > 5 { noise(x) } else { turbulence(x, 4) + 1 }");
        assert_eq!(folded, code("turbulence(x, 4) + 1"));
        // The branch not taken is still checked.
        let e = compile("if freq > 2 { 1 } else { [1, 2, 3] }").unwrap_err();
        assert!(
            e.message.contains("the branches of `if` differ"),
            "{}",
            e.message
        );
        let e = compile("if freq > 2 { 1 } else { nosuch(x) }").unwrap_err();
        assert!(e.message.contains("nosuch"), "{}", e.message);
    }

    #[test]
    fn arithmetic_lets_and_branches() {
        assert_eq!(scalar("1 + 2 * 3"), 7.0);
        assert_eq!(scalar("let a = x.y; let b = a * freq; b - 1"), 7.0);
        assert_eq!(scalar("if x.x > 0.5 { 10 } else { 20 }"), 10.0);
        assert_eq!(
            scalar("if x.x > 5 { 10 } else if x.z == 3 { 30 } else { 20 }"),
            30.0
        );
        assert_eq!(scalar("quad(x.y)"), 16.0);
        assert_eq!(scalar("length(x * 2 - x)"), 14f32.sqrt());
        assert_eq!(scalar("dot(x, [1, 0, 0]) + cross(x, [0, 0, 1]).y"), 0.0);
        assert_eq!(scalar("d"), 0.25);
        assert_eq!(scalar("mix(x, [0, 0, 0], 0.5).z"), 1.5);
        assert_eq!(scalar("direction(x * 2).y"), scalar("normalize(x).y"));
        // Temporaries as operands: no register is reused while still needed.
        assert_eq!(
            scalar("mix(x * 2, x * 3, 0.25).y"),
            4.0 + (6.0 - 4.0) * 0.25
        );
        assert_eq!(
            scalar("mix(x.x * 2, x.y * 4, 0.5)"),
            2.0 + (8.0 - 2.0) * 0.5
        );
        assert_eq!(
            scalar("[x.y * 2, 0, 0].x + [x.z + 0, x.z + 0, x.z + 0].y"),
            7.0
        );
        assert_eq!(scalar("let s = x.y * 2; [s, s, s].z + s"), 8.0);
        assert_eq!(
            scalar("clamp(x.z, 0, 1) + smoothstep(0, 4, x.y) + min(1, 2) + max(x, -x).x"),
            3.5
        );
        assert_eq!(scalar("!(x.x < 2) || 0"), 0.0);
        assert_eq!(
            scalar("7 % 4 + abs(-x.x) + floor(x.y + 0.5) + fract(x.x + 0.25)"),
            6.25
        );
    }

    #[test]
    fn noise_builtins_call_the_native_functions() {
        let noise = Noise::default();
        let p = Vec3::new(0.3, 1.7, -2.2);
        let got = ctx_eval("noise(x * freq) + turbulence(x, 5)", p).unwrap()[0];
        assert_eq!(got, noise.noise(p * 4.0) + noise.turbulence(p, 5));
        let v = ctx_eval("vnoise(x)", p).unwrap();
        assert_eq!(Vec3::from_array(v), noise.vnoise(p));
        let g = ctx_eval("bias(0.3, x.x) + gain(0.9, x.x)", p).unwrap()[0];
        assert_eq!(
            g,
            crate::field::shaping::bias(0.3, 0.3) + crate::field::shaping::gain(0.9, 0.3)
        );
        // dnoise is the gradient: compare with a wider finite difference.
        let dn = Vec3::from_array(ctx_eval("dnoise(x)", p).unwrap());
        let h = 1e-2;
        let fd = (noise.noise(p + Vec3::X * h) - noise.noise(p - Vec3::X * h)) / (2.0 * h);
        assert!((dn.x - fd).abs() < 1e-2, "{dn} vs {fd}");
    }

    #[test]
    #[allow(clippy::approx_constant)] // 3.14 is Perlin's reference input
    fn constants_fold_in_double_precision() {
        let knobs = BTreeMap::new();
        let ctx = plain_context(&knobs, &[]);
        let p = compile_expression("improved(3.14, 42, 7)", Kind::Probe, &ctx).unwrap();
        assert_eq!(p.constant().unwrap()[0], 0.136_919_958_784_000_12);
        assert!(p.is_empty());
    }

    #[test]
    fn type_and_name_errors_at_load() {
        let err = |s: &str| ctx_eval(s, Vec3::ZERO).unwrap_err();
        let e = err("noise(1)");
        assert!(e.message.contains("must be a vector"), "{}", e.message);
        assert_eq!(e.at, 6);
        let e = err("1 + fre");
        assert!(e.message.contains("unknown name `fre`") && e.message.contains("freq"));
        assert_eq!(e.at, 4);
        assert!(err("x < 1").message.contains("compares numbers"));
        assert!(err("if 1 { x } else { 1 }").message.contains("branches"));
        assert!(err("nosie(x)").message.contains("unknown function"));
        assert!(err("noise(x, x)").message.contains("takes 1 argument"));
        assert!(err("project(x)").message.contains("Sphere"));
        assert!(err("sq(x, 1)").message.contains("takes 1"));
        let e = err("1 + bad(x)");
        assert_eq!(e.at, 4, "at the call");
        assert!(
            e.message
                .starts_with("in function `bad`, at 2:13 of functions: `<` compares numbers"),
            "{}",
            e.message
        );
        assert!(err("1 - x").message.contains("vector on the left"));
        let knobs = BTreeMap::new();
        let ctx = plain_context(&knobs, &[]);
        assert!(compile_expression("x", Kind::Density, &ctx).is_err());
        assert!(compile_expression("d", Kind::Density, &ctx).is_err());
        assert!(compile_expression("1", Kind::Normal, &ctx).is_err());
        assert!(
            compile_expression("1", Kind::Colour, &ctx)
                .unwrap()
                .is_vector()
        );
    }

    #[test]
    fn functions_cannot_recurse_or_explode() {
        assert!(parse_functions("fn noise(a) { a }").is_err());
        assert!(parse_functions("fn f(a) { a } fn f(b) { b }").is_err());
        assert!(parse_functions("fn f(a, a) { a }").is_err());
        let functions = parse_functions("fn f(a) { g(a) } fn g(a) { f(a) }").unwrap();
        let knobs = BTreeMap::new();
        let ctx = plain_context(&knobs, &functions);
        let e = compile_expression("g(1)", Kind::Probe, &ctx).unwrap_err();
        assert!(e.message.contains("defined later"), "{}", e.message);
        // Each function doubles the size of the last: capped, not hung.
        let doubling = |base: &str| {
            let mut defs = format!("fn f0(a) {{ {base} }}");
            for i in 1..40 {
                defs += &format!(" fn f{i}(a) {{ f{}(a) + f{}(a + 1) }}", i - 1, i - 1);
            }
            let functions = parse_functions(&defs).unwrap();
            let ctx = Context {
                functions: &functions,
                ..ctx
            };
            compile_expression("f39(x.x)", Kind::Probe, &ctx)
                .unwrap_err()
                .message
        };
        let e = doubling("noise([a, a, a])");
        assert!(e.contains("noise more than"), "{e}");
        let e = doubling("a * 2 + 1");
        assert!(e.contains("operations"), "{e}");
        let sum = vec!["turbulence(x * 2, k)"; 100].join(" + ");
        let k = BTreeMap::from([("k".to_string(), 16.0)]);
        let heavy = Context { knobs: &k, ..ctx };
        let e = compile_expression(&format!("({sum}) + ({sum}) + ({sum})"), Kind::Probe, &heavy)
            .unwrap_err();
        assert!(e.message.contains("noise more than"), "{}", e.message);
        let k = BTreeMap::from([("k".to_string(), 4.0)]);
        let light = Context { knobs: &k, ..ctx };
        assert!(
            compile_expression(&format!("({sum}) + ({sum}) + ({sum})"), Kind::Probe, &light)
                .is_ok()
        );
    }

    #[test]
    fn registers_are_reused() {
        // A long sum of noises needs a handful of registers, not one per term.
        let src = vec!["noise(x * 3)"; 100].join(" + ");
        let knobs = BTreeMap::new();
        let ctx = plain_context(&knobs, &[]);
        let p = compile_expression(&src, Kind::Density, &ctx).unwrap();
        assert!(p.len() >= 100);
        assert!(p.template.len() < 16, "{}", p.template.len());
    }

    /// A random well-typed expression and its value computed directly, in the
    /// same f32 operations: the register code must agree bit for bit (this is
    /// what caught `mix` reusing a live register).
    fn random_expression(
        r: &mut crate::math::random::SplitMix64,
        x: Vec3,
        depth: u32,
    ) -> (String, f32) {
        let leaf = |r: &mut crate::math::random::SplitMix64| match r.below(4) {
            0 => ("x.x".to_string(), x.x),
            1 => ("x.y".to_string(), x.y),
            2 => ("x.z".to_string(), x.z),
            _ => {
                let k = r.below(5) as f32;
                (format!("{k}"), k)
            }
        };
        if depth == 0 {
            return leaf(r);
        }
        let sub = |r: &mut crate::math::random::SplitMix64| random_expression(r, x, depth - 1);
        match r.below(9) {
            0 => leaf(r),
            1 => {
                let ((a, va), (b, vb)) = (sub(r), sub(r));
                (format!("({a} + {b})"), va + vb)
            }
            2 => {
                let ((a, va), (b, vb)) = (sub(r), sub(r));
                (format!("({a} * {b})"), va * vb)
            }
            3 => {
                let ((a, va), (b, vb)) = (sub(r), sub(r));
                (format!("min({a}, {b})"), if vb < va { vb } else { va })
            }
            4 => {
                let ((a, va), (b, vb), (c, vc), (d, vd)) = (sub(r), sub(r), sub(r), sub(r));
                (
                    format!(
                        "if {a} < {b} {{ let v = {c}; let w = v; w * v - {d} }} else {{ {d} }}"
                    ),
                    if va < vb { vc * vc - vd } else { vd },
                )
            }
            5 => {
                let ((a, va), (b, vb), (t, vt)) = (sub(r), sub(r), sub(r));
                (format!("mix({a}, {b}, {t})"), va + (vb - va) * vt)
            }
            6 => {
                let ((a, va), (b, vb), (c, vc)) = (sub(r), sub(r), sub(r));
                let i = r.below(3) as usize;
                (
                    format!("[{a}, {b}, {c}].{}", ["x", "y", "z"][i]),
                    [va, vb, vc][i],
                )
            }
            7 => {
                let ((a, va), (b, vb)) = (sub(r), sub(r));
                let i = r.below(3) as usize;
                (
                    format!("(-[{a}, {b}, {a}]).{}", ["x", "y", "z"][i]),
                    -[va, vb, va][i],
                )
            }
            _ => {
                let ((a, va), (b, vb), (c, _)) = (sub(r), sub(r), sub(r));
                (
                    format!("(mix([{a}, {b}, {c}], [{c}, {a}, {b}], {b}) * {a}).y"),
                    (vb + (va - vb) * vb) * va,
                )
            }
        }
    }

    #[test]
    fn register_code_agrees_with_direct_evaluation() {
        let mut r = crate::math::random::SplitMix64::new(42);
        let mut failures: Vec<String> = Vec::new();
        for _ in 0..5000 {
            let x = Vec3::new(
                r.next_f32() * 4.0 - 2.0,
                r.next_f32() * 4.0 - 2.0,
                r.next_f32() * 4.0 - 2.0,
            );
            let (src, expected) = random_expression(&mut r, x, 4);
            let Ok(got) = ctx_eval(&src, x) else {
                continue; // too deep or too large: capped, not wrong
            };
            if got[0].to_bits() != expected.to_bits() {
                failures.push(format!("{src} at {x}: {} vs {expected}", got[0]));
            }
        }
        failures.sort_by_key(String::len);
        assert!(
            failures.is_empty(),
            "{} failures, shortest: {}",
            failures.len(),
            failures.first().map_or("", |s| s)
        );
    }
}
