//! The compiled form of an expression and its evaluator.
//!
//! A [`Program`] is a list of [`Op`]s over a register file of at most
//! [`MAX_REGISTERS`] floats (registers are `u8`s, so no index can be out of
//! range). The register file lives on the stack and starts as a copy of the
//! program's template (inputs, then constants). Jumps only go forward, so a run
//! takes at most one step per operation: evaluation always terminates, never
//! allocates, and cannot fail. Vectors are three scalar registers; vector
//! arithmetic was lowered to scalar operations by the compiler.
//!
//! Only IEEE basic operations and `libm` are used, in a fixed order, so every CPU
//! computes the same bits, and the built-ins call the very functions the native
//! DMFs call (noise, turbulence, bias, gain, the soft objects' density and
//! projection), so an expression of a native DMF gives the same image.

use glam::Vec3;

use crate::field::curve::Curve;
use crate::field::density::Density;
use crate::field::domain::{Field, Points};
use crate::field::noise::VNOISE_OFFSET;
use crate::field::shaping::{Bias, Gain};
use crate::math::simd::Isa;
use crate::math::simd::{LANES, Lanes};

/// Registers per program: `u8` register names index a `[f32; 256]` file.
pub const MAX_REGISTERS: usize = 256;
/// Operations per program (after inlining scene functions).
pub const MAX_OPS: usize = 16_384;

/// Register of x.x (x.y, x.z follow).
pub const REG_X: u8 = 0;
/// Register of the time t.
pub const REG_T: u8 = 3;
/// Register of the frame number.
pub const REG_FRAME: u8 = 4;
/// Register of d, the density at the sample (colour and normal expressions).
pub const REG_D: u8 = 5;
/// Registers the inputs occupy.
pub const INPUTS: usize = 6;

/// Three registers holding a vector.
pub type V = [u8; 3];

/// A scalar function of one argument.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Fn1 {
    Abs,
    Floor,
    Fract,
    Sin,
    Cos,
    Tan,
    Exp,
    Log,
    Sqrt,
    Sign,
}

/// A scalar function of two arguments.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Fn2 {
    Pow,
    Min,
    Max,
    Atan2,
    Step,
    Bias,
    Gain,
}

/// One operation of the register code.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Op {
    /// `r[d] = r[a]`.
    Copy(u8, u8),
    Add(u8, u8, u8),
    Sub(u8, u8, u8),
    Mul(u8, u8, u8),
    Div(u8, u8, u8),
    /// `fmod`.
    Rem(u8, u8, u8),
    Neg(u8, u8),
    /// Comparisons and logic give 1 or 0.
    Lt(u8, u8, u8),
    Le(u8, u8, u8),
    Eq(u8, u8, u8),
    Ne(u8, u8, u8),
    And(u8, u8, u8),
    Or(u8, u8, u8),
    Not(u8, u8),
    F1(Fn1, u8, u8),
    F2(Fn2, u8, u8, u8),
    /// `bias_b(t)` with the exponent computed at load (constant b).
    BiasK(u8, u8, Bias),
    /// `gain_g(t)` with the exponent computed at load (constant g).
    GainK(u8, u8, Gain),
    /// `clamp(v, lo, hi)`.
    Clamp(u8, u8, u8, u8),
    /// `smoothstep(e0, e1, v)`.
    Smoothstep(u8, u8, u8, u8),
    /// `noise(p)`.
    Noise(u8, V),
    /// `vnoise(p)`.
    VNoise(V, V),
    /// `dnoise(p)`: the gradient of noise.
    DNoise(V, V),
    /// `turbulence(p, octaves)`.
    Turbulence(u8, V, u8),
    /// `fbm(p, octaves)`.
    Fbm(u8, V, u8),
    /// Perlin's improved noise (2002) at p.
    Improved(u8, V),
    /// The density of soft object `objects[i]` at p.
    Density(u8, u16, V),
    /// p projected onto the inner surface of the object.
    Project(V, V),
    /// The scene's colour map at s.
    ColourMap(V, u8),
    /// Continue at op `target`.
    Jump(u16),
    /// Continue at op `target` when `r[c] == 0`.
    JumpIfZero(u8, u16),
}

/// What an expression's value is.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Result3 {
    /// A number in a register.
    Scalar(u8),
    /// A vector in three registers.
    Vector(V),
}

/// A compiled expression: immutable, shared by every thread.
#[derive(Clone, Debug, PartialEq)]
pub struct Program {
    pub(crate) ops: Vec<Op>,
    /// Initial register values: zeros for the inputs and temporaries, then constants.
    pub(crate) template: Vec<f32>,
    pub(crate) result: Result3,
    /// The soft objects the expression calls (`D` and the scene's named objects).
    pub(crate) objects: Vec<Density>,
    /// The primitive `project` projects onto.
    pub(crate) surface: Option<Density>,
    /// The scene's colour map (for `colour_map(s)`).
    pub(crate) colour_map: Option<Curve<3>>,
    /// The value when the whole expression is a constant, computed in double
    /// precision at load (`coordinator eval` prints it).
    pub(crate) constant: Option<[f64; 3]>,
}

/// The inputs of one evaluation.
#[derive(Clone, Copy, Debug)]
pub struct Inputs {
    /// The point x.
    pub x: Vec3,
    /// The density at the sample (colour and normal expressions).
    pub d: f32,
}

impl Program {
    /// Whether the value is a vector.
    pub fn is_vector(&self) -> bool {
        matches!(self.result, Result3::Vector(_))
    }

    /// The value computed at load in double precision, when the expression is a
    /// constant.
    pub fn constant(&self) -> Option<[f64; 3]> {
        self.constant
    }

    /// Number of operations (for tests and diagnostics).
    pub fn len(&self) -> usize {
        self.ops.len()
    }

    /// Whether the program has no operations (a constant or an input).
    pub fn is_empty(&self) -> bool {
        self.ops.is_empty()
    }

    /// The scalar value (the x component of a vector value).
    #[inline]
    pub fn eval_scalar(&self, x: Vec3, d: f32, field: &Field) -> f32 {
        self.eval(Inputs { x, d }, field)[0]
    }

    /// The vector value (a scalar value repeated).
    #[inline]
    pub fn eval_vector(&self, x: Vec3, d: f32, field: &Field) -> Vec3 {
        Vec3::from_array(self.eval(Inputs { x, d }, field))
    }

    /// Runs the program.
    #[inline]
    pub fn eval(&self, inputs: Inputs, field: &Field) -> [f32; 3] {
        if self.template.len() <= 32 {
            self.run::<32>(inputs, field)
        } else if self.template.len() <= 64 {
            self.run::<64>(inputs, field)
        } else {
            self.run::<MAX_REGISTERS>(inputs, field)
        }
    }

    #[inline]
    fn run<const N: usize>(&self, inputs: Inputs, field: &Field) -> [f32; 3] {
        let mut r = [0.0f32; N];
        self.load_registers(&mut r, inputs, field);
        let ops = &self.ops[..];
        let mut pc = 0;
        while pc < ops.len() {
            let op = ops[pc];
            pc += 1;
            match op {
                Op::Jump(target) => pc = usize::from(target),
                Op::JumpIfZero(c, target) => {
                    if r[c as usize] == 0.0 {
                        pc = usize::from(target);
                    }
                }
                _ => self.exec(op, &mut r, field),
            }
        }
        match self.result {
            Result3::Scalar(a) => [r[a as usize]; 3],
            Result3::Vector(p) => [r[p[0] as usize], r[p[1] as usize], r[p[2] as usize]],
        }
    }

    /// Loads the register file for a run: the template, then the inputs.
    #[inline(always)]
    fn load_registers<const N: usize>(&self, r: &mut [f32; N], inputs: Inputs, field: &Field) {
        r[..self.template.len()].copy_from_slice(&self.template);
        r[REG_X as usize] = inputs.x.x;
        r[REG_X as usize + 1] = inputs.x.y;
        r[REG_X as usize + 2] = inputs.x.z;
        r[REG_T as usize] = field.time / field.frame_rate;
        r[REG_FRAME as usize] = field.frame as f32;
        r[REG_D as usize] = inputs.d;
    }

    /// Runs one operation other than a jump.
    #[inline(always)]
    fn exec<const N: usize>(&self, op: Op, r: &mut [f32; N], field: &Field) {
        macro_rules! r {
            ($i:expr) => {
                r[$i as usize]
            };
        }
        let v =
            |r: &[f32; N], p: V| Vec3::new(r[p[0] as usize], r[p[1] as usize], r[p[2] as usize]);
        let set = |r: &mut [f32; N], p: V, value: Vec3| {
            r[p[0] as usize] = value.x;
            r[p[1] as usize] = value.y;
            r[p[2] as usize] = value.z;
        };
        match op {
            Op::Copy(d, a) => r!(d) = r!(a),
            Op::Add(d, a, b) => r!(d) = r!(a) + r!(b),
            Op::Sub(d, a, b) => r!(d) = r!(a) - r!(b),
            Op::Mul(d, a, b) => r!(d) = r!(a) * r!(b),
            Op::Div(d, a, b) => r!(d) = r!(a) / r!(b),
            Op::Rem(d, a, b) => r!(d) = libm::fmodf(r!(a), r!(b)),
            Op::Neg(d, a) => r!(d) = -r!(a),
            Op::Lt(d, a, b) => r!(d) = truth(r!(a) < r!(b)),
            Op::Le(d, a, b) => r!(d) = truth(r!(a) <= r!(b)),
            Op::Eq(d, a, b) => r!(d) = truth(r!(a) == r!(b)),
            Op::Ne(d, a, b) => r!(d) = truth(r!(a) != r!(b)),
            Op::And(d, a, b) => r!(d) = truth(r!(a) != 0.0 && r!(b) != 0.0),
            Op::Or(d, a, b) => r!(d) = truth(r!(a) != 0.0 || r!(b) != 0.0),
            Op::Not(d, a) => r!(d) = truth(r!(a) == 0.0),
            Op::F1(f, d, a) => r!(d) = fn1(f, r!(a)),
            Op::F2(f, d, a, b) => r!(d) = fn2(f, r!(a), r!(b)),
            Op::BiasK(d, a, b) => r!(d) = b.apply(r!(a)),
            Op::GainK(d, a, g) => r!(d) = g.apply(r!(a)),
            Op::Clamp(d, a, lo, hi) => r!(d) = clamp(r!(a), r!(lo), r!(hi)),
            Op::Smoothstep(d, e0, e1, a) => r!(d) = smoothstep(r!(e0), r!(e1), r!(a)),
            Op::Noise(d, p) => r!(d) = field.noise.noise(v(r, p)),
            Op::VNoise(d, p) => set(r, d, field.noise.vnoise(v(r, p))),
            Op::DNoise(d, p) => set(r, d, dnoise(field, v(r, p))),
            Op::Turbulence(d, p, o) => {
                r!(d) = field.noise.turbulence(v(r, p), octaves(r!(o)));
            }
            Op::Fbm(d, p, o) => r!(d) = fbm(field, v(r, p), octaves(r!(o))),
            Op::Improved(d, p) => r!(d) = improved_at(v(r, p)),
            Op::Density(d, i, p) => {
                let p = v(r, p);
                r!(d) = self
                    .objects
                    .get(usize::from(i))
                    .map_or(0.0, |o| o.eval(p, field));
            }
            Op::Project(d, p) => {
                let p = v(r, p);
                set(r, d, self.surface.as_ref().map_or(p, |s| s.project(p)));
            }
            Op::ColourMap(d, s) => {
                let c = self
                    .colour_map
                    .as_ref()
                    .map_or([r!(s); 3], |m| m.eval(r!(s)));
                set(r, d, Vec3::from_array(c));
            }
            Op::Jump(_) | Op::JumpIfZero(..) => unreachable!("control flow is handled by run"),
        }
    }
}

/// Lane masking in [`Program::run_lanes`]: when the points take different
/// branches of an `if`, the lanes off the branch being run wait at the
/// operation they resume at. Lane l runs the operations from `resume[l]` on
/// (`usize::MAX` once it is running; jumps only go forwards, so every lane's
/// path is visited in order), `active` is the mask of running lanes and
/// `all_active` says that every lane runs. These macros take the three as
/// `[resume, active, all_active]`, so they stay locals of the interpreter's
/// loop: as the fields of a struct behind methods, the expression fur
/// (scenes/pse/fur.ron) renders about 10% slower.
///
/// `wake_lanes!`: wakes the lanes waiting at `pc`; when every lane waits
/// further on, goes on at the nearest (`continue`s the loop).
macro_rules! wake_lanes {
    ([$resume:ident, $active:ident, $all_active:ident], $pc:ident, $end:expr) => {
        if !$all_active {
            for l in 0..LANES {
                if $resume[l] == $pc {
                    ($resume[l], $active[l]) = (usize::MAX, true);
                }
            }
            $all_active = $active.iter().all(|&a| a);
            if !$active.iter().any(|&a| a) {
                // Every lane waits further on: go to the nearest.
                $pc = $resume.iter().copied().min().unwrap_or($end);
                continue;
            }
        }
    };
}

/// `Jump` to `target` (see `wake_lanes!`): when some lanes wait, the
/// running ones wait at `target` and the program counter stays.
macro_rules! jump {
    ([$resume:ident, $active:ident, $all_active:ident], $pc:ident, $target:expr) => {
        if $all_active {
            $pc = usize::from($target);
        } else {
            for l in 0..LANES {
                if $active[l] {
                    ($resume[l], $active[l]) = (usize::from($target), false);
                }
            }
            $all_active = false;
        }
    };
}

/// `JumpIfZero` on the lanes `cond` (see `wake_lanes!`): to `target` when
/// every lane runs and is 0; otherwise the running lanes at 0 wait at
/// `target` and the others go on.
macro_rules! jump_if_zero {
    ([$resume:ident, $active:ident, $all_active:ident], $pc:ident, $cond:expr, $target:expr) => {
        let mut zero = [false; LANES];
        for l in 0..LANES {
            zero[l] = $cond[l] == 0.0;
        }
        if $all_active && zero.iter().all(|&z| z) {
            $pc = usize::from($target);
        } else {
            for l in 0..LANES {
                if $active[l] && zero[l] {
                    ($resume[l], $active[l]) = (usize::from($target), false);
                    $all_active = false;
                }
            }
        }
    };
}

/// The registers `op` writes and their lanes before it, `(written, saved)`,
/// when some lane waits (see `wake_lanes!`; only looked up then).
macro_rules! save_written {
    ($all_active:ident, $op:ident, $r:ident) => {{
        let written = if $all_active {
            [None; 3]
        } else {
            $op.written()
        };
        let mut saved = [None; 3];
        for (s, w) in saved.iter_mut().zip(written) {
            *s = w.map(|w| $r[usize::from(w)]);
        }
        (written, saved)
    }};
}

/// Puts back, in the lanes that wait (see `wake_lanes!`), the registers
/// `save_written!` kept: they keep their values across the operations
/// they do not run.
macro_rules! restore_waiting {
    ([$active:ident, $all_active:ident], $r:ident, $written:ident, $saved:ident) => {
        if !$all_active {
            for (w, old) in $written.iter().zip($saved) {
                if let (Some(w), Some(old)) = (w, old) {
                    let reg = &mut $r[usize::from(*w)];
                    for l in 0..LANES {
                        if !$active[l] {
                            reg[l] = old[l];
                        }
                    }
                }
            }
        }
    };
}

impl Program {
    /// [`Program::eval`] at [`LANES`] points at once (`d` per point), with the
    /// same bits per lane: noise, bias, gain, the objects' densities and the
    /// projection are batched on `isa`; every other operation runs lane by lane
    /// with the scalar code. When the points take different branches of an `if`,
    /// both branches run with the lanes that did not take one masked: an
    /// operation's result is kept only in the lanes whose path runs it.
    pub fn eval_lanes(&self, x: &Points, d: &Lanes, field: &Field, isa: Isa) -> [Lanes; 3] {
        crate::math::simd::per_isa!(isa, (
            program: &Program = self, x: &Points = x, d: &Lanes = d, field: &Field = field,
        ) -> [Lanes; 3] {
            scalar => program.eval_points(x, d, field),
            lanes => program.run_simd(x, d, field, lanes),
        })
    }

    /// [`Program::eval`] at each of [`LANES`] points, one after another.
    fn eval_points(&self, x: &Points, d: &Lanes, field: &Field) -> [Lanes; 3] {
        let mut out = [[0.0; LANES]; 3];
        for l in 0..LANES {
            let v = self.eval(
                Inputs {
                    x: x.get(l),
                    d: d[l],
                },
                field,
            );
            for c in 0..3 {
                out[c][l] = v[c];
            }
        }
        out
    }

    /// [`Program::eval_lanes`] on a SIMD path, inlined into one copy per
    /// instruction set (by `per_isa!`) with the noise and power kernels.
    #[inline(always)]
    fn run_simd(&self, x: &Points, d: &Lanes, field: &Field, isa: Isa) -> [Lanes; 3] {
        if self.template.len() <= 32 {
            self.run_lanes::<32>(x, d, field, isa)
        } else if self.template.len() <= 64 {
            self.run_lanes::<64>(x, d, field, isa)
        } else {
            self.run_lanes::<MAX_REGISTERS>(x, d, field, isa)
        }
    }

    /// [`Program::eval_lanes`]'s interpreter: one pass over the operations
    /// with every lane's registers side by side, the arithmetic lane by lane
    /// and the built-ins a batch at a time (`wake_lanes!` and its siblings
    /// mask the lanes off the branch being run).
    #[allow(clippy::needless_range_loop)] // lane loops index several arrays at once
    #[inline(always)]
    fn run_lanes<const N: usize>(
        &self,
        x: &Points,
        d: &Lanes,
        field: &Field,
        isa: Isa,
    ) -> [Lanes; 3] {
        let mut r = [[0.0f32; LANES]; N];
        self.load_lane_registers(&mut r, x, d, field);
        let ops = &self.ops[..];
        // The lanes' paths through the branches: see `wake_lanes!`.
        let mut resume = [usize::MAX; LANES];
        let mut active = [true; LANES];
        let mut all_active = true;
        let mut pc = 0;
        loop {
            wake_lanes!([resume, active, all_active], pc, ops.len());
            if pc >= ops.len() {
                break;
            }
            let op = ops[pc];
            pc += 1;
            match op {
                Op::Jump(target) => {
                    jump!([resume, active, all_active], pc, target);
                    continue;
                }
                Op::JumpIfZero(c, target) => {
                    jump_if_zero!([resume, active, all_active], pc, r[c as usize], target);
                    continue;
                }
                _ => {}
            }
            // The lanes that do not run this operation keep their registers.
            let (written, saved) = save_written!(all_active, op, r);
            macro_rules! lanewise {
                ($d:expr, |$l:ident| $e:expr) => {{
                    let mut out = [0.0f32; LANES];
                    for $l in 0..LANES {
                        out[$l] = $e;
                    }
                    r[$d as usize] = out;
                }};
            }
            macro_rules! g {
                ($i:expr, $l:expr) => {
                    r[$i as usize][$l]
                };
            }
            match op {
                Op::Copy(d, a) => r[d as usize] = r[a as usize],
                Op::Add(d, a, b) => lanewise!(d, |l| g!(a, l) + g!(b, l)),
                Op::Sub(d, a, b) => lanewise!(d, |l| g!(a, l) - g!(b, l)),
                Op::Mul(d, a, b) => lanewise!(d, |l| g!(a, l) * g!(b, l)),
                Op::Div(d, a, b) => lanewise!(d, |l| g!(a, l) / g!(b, l)),
                Op::Rem(d, a, b) => lanewise!(d, |l| libm::fmodf(g!(a, l), g!(b, l))),
                Op::Neg(d, a) => lanewise!(d, |l| -g!(a, l)),
                Op::Lt(d, a, b) => lanewise!(d, |l| truth(g!(a, l) < g!(b, l))),
                Op::Le(d, a, b) => lanewise!(d, |l| truth(g!(a, l) <= g!(b, l))),
                Op::Eq(d, a, b) => lanewise!(d, |l| truth(g!(a, l) == g!(b, l))),
                Op::Ne(d, a, b) => lanewise!(d, |l| truth(g!(a, l) != g!(b, l))),
                Op::And(d, a, b) => {
                    lanewise!(d, |l| truth(g!(a, l) != 0.0 && g!(b, l) != 0.0))
                }
                Op::Or(d, a, b) => lanewise!(d, |l| truth(g!(a, l) != 0.0 || g!(b, l) != 0.0)),
                Op::Not(d, a) => lanewise!(d, |l| truth(g!(a, l) == 0.0)),
                Op::F1(f, d, a) => lanewise!(d, |l| fn1(f, g!(a, l))),
                Op::F2(f, d, a, b) => lanewise!(d, |l| fn2(f, g!(a, l), g!(b, l))),
                Op::BiasK(d, a, b) => r[d as usize] = b.apply_simd(&r[a as usize]),
                Op::GainK(d, a, g) => r[d as usize] = g.apply_simd(&r[a as usize]),
                Op::Clamp(d, a, lo, hi) => lanewise!(d, |l| clamp(g!(a, l), g!(lo, l), g!(hi, l))),
                Op::Smoothstep(d, e0, e1, a) => {
                    lanewise!(d, |l| smoothstep(g!(e0, l), g!(e1, l), g!(a, l)))
                }
                Op::Noise(d, p) => noise_lanes(&mut r, d, p, field, isa),
                Op::Density(d, i, p) => self.density_lanes(&mut r, d, i, p, field, isa),
                Op::Project(d, p) => self.project_lanes(&mut r, d, p),
                Op::VNoise(d, p) => vnoise_lanes(&mut r, d, p, field, isa),
                Op::Turbulence(d, p, o) => octaves_lanes(&mut r, [d, o], p, true, field, isa),
                Op::Fbm(d, p, o) => octaves_lanes(&mut r, [d, o], p, false, field, isa),
                // The rest: the scalar code, lane by lane.
                Op::DNoise(d, p) => dnoise_lanes(&mut r, d, p, field),
                Op::Improved(d, p) => improved_lanes(&mut r, d, p),
                Op::ColourMap(d, s) => self.colour_map_lanes(&mut r, d, s),
                Op::Jump(_) | Op::JumpIfZero(..) => unreachable!("control flow is handled above"),
            }
            restore_waiting!([active, all_active], r, written, saved);
        }
        match self.result {
            Result3::Scalar(a) => [r[a as usize]; 3],
            Result3::Vector(p) => [r[p[0] as usize], r[p[1] as usize], r[p[2] as usize]],
        }
    }

    /// Fills the register file of a lane run in place (a returned one is
    /// copied on every call): the template in every lane, then the inputs.
    #[inline(always)]
    fn load_lane_registers<const N: usize>(
        &self,
        r: &mut [Lanes; N],
        x: &Points,
        d: &Lanes,
        field: &Field,
    ) {
        for (reg, &value) in r.iter_mut().zip(&self.template) {
            *reg = [value; LANES];
        }
        r[REG_X as usize] = x.x;
        r[REG_X as usize + 1] = x.y;
        r[REG_X as usize + 2] = x.z;
        r[REG_T as usize] = [field.time / field.frame_rate; LANES];
        r[REG_FRAME as usize] = [field.frame as f32; LANES];
        r[REG_D as usize] = *d;
    }

    /// `Density(d, i, p)`: the density of soft object `objects[i]` at the
    /// points `p`, batched on `isa` (0 for an index out of range).
    #[inline(always)]
    fn density_lanes<const N: usize>(
        &self,
        r: &mut [Lanes; N],
        d: u8,
        i: u16,
        p: V,
        field: &Field,
        isa: Isa,
    ) {
        let q = points(r, p);
        r[d as usize] = self
            .objects
            .get(usize::from(i))
            .map_or([0.0; LANES], |o| o.eval_lanes(&q, field, isa));
    }

    /// `Project(d, p)`: the points `p` projected onto the inner surface of
    /// the object (the points themselves without one).
    #[inline(always)]
    fn project_lanes<const N: usize>(&self, r: &mut [Lanes; N], d: V, p: V) {
        let q = points(r, p);
        let q = match &self.surface {
            Some(s) => s.project_lanes(&q),
            None => q,
        };
        set_lanes(r, d, [q.x, q.y, q.z]);
    }

    /// `ColourMap(d, s)`: the scene's colour map at each lane's `s`, lane by
    /// lane (s in every channel without a colour map).
    #[allow(clippy::needless_range_loop)] // lane loops index several arrays at once
    #[inline(always)]
    fn colour_map_lanes<const N: usize>(&self, r: &mut [Lanes; N], d: V, s: u8) {
        let s = r[s as usize];
        let mut out = [[0.0; LANES]; 3];
        for l in 0..LANES {
            let c = self.colour_map.as_ref().map_or([s[l]; 3], |m| m.eval(s[l]));
            (out[0][l], out[1][l], out[2][l]) = (c[0], c[1], c[2]);
        }
        set_lanes(r, d, out);
    }
}

impl Op {
    /// The registers the operation writes (none for jumps).
    fn written(&self) -> [Option<u8>; 3] {
        match *self {
            Op::Copy(d, _)
            | Op::Add(d, ..)
            | Op::Sub(d, ..)
            | Op::Mul(d, ..)
            | Op::Div(d, ..)
            | Op::Rem(d, ..)
            | Op::Neg(d, _)
            | Op::Lt(d, ..)
            | Op::Le(d, ..)
            | Op::Eq(d, ..)
            | Op::Ne(d, ..)
            | Op::And(d, ..)
            | Op::Or(d, ..)
            | Op::Not(d, _)
            | Op::F1(_, d, _)
            | Op::F2(_, d, ..)
            | Op::BiasK(d, ..)
            | Op::GainK(d, ..)
            | Op::Clamp(d, ..)
            | Op::Smoothstep(d, ..)
            | Op::Noise(d, _)
            | Op::Turbulence(d, ..)
            | Op::Fbm(d, ..)
            | Op::Improved(d, _)
            | Op::Density(d, ..) => [Some(d), None, None],
            Op::VNoise(d, _) | Op::DNoise(d, _) | Op::Project(d, _) | Op::ColourMap(d, _) => {
                d.map(Some)
            }
            Op::Jump(_) | Op::JumpIfZero(..) => [None; 3],
        }
    }
}

/// The points whose coordinates are in the registers `p`.
#[inline(always)]
fn points<const N: usize>(r: &[Lanes; N], p: V) -> Points {
    Points {
        x: r[p[0] as usize],
        y: r[p[1] as usize],
        z: r[p[2] as usize],
    }
}

/// Writes the three lanes of a vector into its registers `d`.
#[inline(always)]
fn set_lanes<const N: usize>(r: &mut [Lanes; N], d: V, v: [Lanes; 3]) {
    (r[d[0] as usize], r[d[1] as usize], r[d[2] as usize]) = (v[0], v[1], v[2]);
}

/// `f(l)` for each lane l.
#[inline(always)]
fn each(f: impl Fn(usize) -> f32) -> Lanes {
    let mut out = [0.0; LANES];
    for (l, o) in out.iter_mut().enumerate() {
        *o = f(l);
    }
    out
}

/// `Noise(d, p)`: noise at the points `p`, a batch on `isa`.
#[inline(always)]
fn noise_lanes<const N: usize>(r: &mut [Lanes; N], d: u8, p: V, field: &Field, isa: Isa) {
    let q = points(r, p);
    r[d as usize] = field.noise.noise_lanes_on(isa, &q.x, &q.y, &q.z);
}

/// `VNoise(d, p)`: [`crate::field::noise::Noise::vnoise`] at the points `p`,
/// noise at x − c, x, x + c, each a batch on `isa`.
#[inline(always)]
fn vnoise_lanes<const N: usize>(r: &mut [Lanes; N], d: V, p: V, field: &Field, isa: Isa) {
    let q = points(r, p);
    let (qa, qc) = (q.map(|q| q - VNOISE_OFFSET), q.map(|q| q + VNOISE_OFFSET));
    let a = field.noise.noise_lanes_on(isa, &qa.x, &qa.y, &qa.z);
    let b = field.noise.noise_lanes_on(isa, &q.x, &q.y, &q.z);
    let c = field.noise.noise_lanes_on(isa, &qc.x, &qc.y, &qc.z);
    (r[d[0] as usize], r[d[1] as usize], r[d[2] as usize]) = (a, b, c);
}

/// `Turbulence` (`absolute`) or `Fbm` into register `d` at the points `p`
/// with the octave counts in register `o`: where every lane has the same
/// count, Σ noise(2^i x) / 2^i over the octaves, each a batch on `isa`, as
/// the scalar code sums; otherwise the scalar code lane by lane.
#[inline(always)]
fn octaves_lanes<const N: usize>(
    r: &mut [Lanes; N],
    [d, o]: [u8; 2],
    p: V,
    absolute: bool,
    field: &Field,
    isa: Isa,
) {
    let q = points(r, p);
    let o = r[o as usize].map(octaves);
    r[d as usize] = if o.iter().all(|&n| n == o[0]) {
        let mut sum = [0.0f32; LANES];
        let mut scale = 1.0f32;
        for _ in 0..o[0] {
            let s = q.map(|q| q * scale);
            let n = field.noise.noise_lanes_on(isa, &s.x, &s.y, &s.z);
            for l in 0..LANES {
                let v = if absolute { n[l].abs() } else { n[l] };
                sum[l] += v / scale;
            }
            scale *= 2.0;
        }
        sum
    } else if absolute {
        each(|l| field.noise.turbulence(q.get(l), o[l]))
    } else {
        each(|l| fbm(field, q.get(l), o[l]))
    };
}

/// `DNoise(d, p)`: the gradient of noise at each point, lane by lane.
#[allow(clippy::needless_range_loop)] // lane loops index several arrays at once
#[inline(always)]
fn dnoise_lanes<const N: usize>(r: &mut [Lanes; N], d: V, p: V, field: &Field) {
    let q = points(r, p);
    let mut out = [[0.0; LANES]; 3];
    for l in 0..LANES {
        let v = dnoise(field, q.get(l));
        (out[0][l], out[1][l], out[2][l]) = (v.x, v.y, v.z);
    }
    set_lanes(r, d, out);
}

/// `Improved(d, p)`: Perlin's improved noise at each point, lane by lane.
#[inline(always)]
fn improved_lanes<const N: usize>(r: &mut [Lanes; N], d: u8, p: V) {
    let q = points(r, p);
    r[d as usize] = each(|l| improved_at(q.get(l)));
}

/// Perlin's improved noise at `p` (in double precision, rounded to f32).
#[inline(always)]
fn improved_at(p: Vec3) -> f32 {
    crate::field::noise::improved(f64::from(p.x), f64::from(p.y), f64::from(p.z)) as f32
}

#[inline(always)]
fn truth(b: bool) -> f32 {
    if b { 1.0 } else { 0.0 }
}

/// An octave count from a register: floor, clamped to 0..=16 (NaN → 0).
#[inline]
fn octaves(v: f32) -> u32 {
    if v >= 1.0 {
        if v < 16.0 { v as u32 } else { 16 }
    } else {
        0
    }
}

/// `clamp(v, lo, hi)`: `max(lo, min(v, hi))` (NaN → lo).
#[inline]
pub(crate) fn clamp(v: f32, lo: f32, hi: f32) -> f32 {
    let v = if v < hi { v } else { hi };
    if v > lo { v } else { lo }
}

/// Hermite step between e0 and e1.
#[inline]
pub(crate) fn smoothstep(e0: f32, e1: f32, v: f32) -> f32 {
    let t = clamp((v - e0) / (e1 - e0), 0.0, 1.0);
    t * t * (3.0 - 2.0 * t)
}

/// Sums `noise(2^i p) / 2^i` (signed, unlike turbulence) in the order turbulence does.
#[inline]
fn fbm(field: &Field, p: Vec3, octaves: u32) -> f32 {
    let mut sum = 0.0;
    let mut scale = 1.0;
    for _ in 0..octaves {
        sum += field.noise.noise(p * scale) / scale;
        scale *= 2.0;
    }
    sum
}

/// Step of the central differences of `dnoise`: 2^-10 (exact in binary).
const DNOISE_STEP: f32 = 1.0 / 1024.0;

/// Perlin's Dnoise, the gradient of noise, by central differences of noise.
#[inline]
pub(crate) fn dnoise(field: &Field, p: Vec3) -> Vec3 {
    let n = |q: Vec3| field.noise.noise(q);
    let h = DNOISE_STEP;
    let inv = 1.0 / (2.0 * h);
    Vec3::new(
        (n(p + Vec3::new(h, 0.0, 0.0)) - n(p - Vec3::new(h, 0.0, 0.0))) * inv,
        (n(p + Vec3::new(0.0, h, 0.0)) - n(p - Vec3::new(0.0, h, 0.0))) * inv,
        (n(p + Vec3::new(0.0, 0.0, h)) - n(p - Vec3::new(0.0, 0.0, h))) * inv,
    )
}

#[inline]
pub(crate) fn fn1(f: Fn1, a: f32) -> f32 {
    match f {
        Fn1::Abs => a.abs(),
        Fn1::Floor => a.floor(),
        Fn1::Fract => a - a.floor(),
        Fn1::Sin => libm::sinf(a),
        Fn1::Cos => libm::cosf(a),
        Fn1::Tan => libm::tanf(a),
        Fn1::Exp => libm::expf(a),
        Fn1::Log => libm::logf(a),
        Fn1::Sqrt => a.sqrt(),
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

#[inline]
pub(crate) fn fn2(f: Fn2, a: f32, b: f32) -> f32 {
    match f {
        Fn2::Pow => libm::powf(a, b),
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
        Fn2::Atan2 => libm::atan2f(a, b),
        Fn2::Step => truth(b >= a),
        Fn2::Bias => Bias::new(a).apply(b),
        Fn2::Gain => Gain::new(a).apply(b),
    }
}
