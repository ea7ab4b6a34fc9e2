//! The hypertexture H(D(x), x): the object density tree with its density
//! modulation functions, built from the scene description.
//!
//! Evaluation is infallible and allocation-free: everything that can go wrong was
//! checked when the scene was loaded, and every constant (bias exponents, clamped
//! octave counts, squared radii) was computed then.

use glam::Vec3;

use crate::distortion::Distortion;
use crate::dual::{Dual, DualPoint};
use crate::motion::Pose;
use crate::noise::{Noise, VNOISE_OFFSET, clamped_octaves};
use crate::scene::desc::{DmfDesc, ObjectDesc};
use crate::shaping::{Bias, Gain};
use crate::simd::{Isa, LANES, Lanes};
use crate::soft::{Falloff, SoftBox, SoftSphere, SoftTorus, boolean};

/// Where and when the field is evaluated: the noise tables and the drift of the
/// noise domain for the current frame.
#[derive(Clone, Copy, Debug)]
pub struct Field<'a> {
    /// The scene's noise tables.
    pub noise: &'a Noise,
    /// Noise is evaluated at `x - offset` (`offset = frame · flow`).
    pub offset: Vec3,
    /// The frame number (`frame` in expressions).
    pub frame: u32,
    /// The time in frames: `frame`, or within a frame while the shutter of
    /// motion blur is open (`t = time / frame_rate` in expressions).
    pub time: f32,
    /// Frames per second (`t = frame / frame_rate` in expressions).
    pub frame_rate: f32,
    /// Where the moving object is at this moment ([`Density::Moving`]).
    pub pose: Option<Pose>,
    /// Where the density can be non-zero at this moment, in world space, or
    /// `None`: anywhere (the marcher skips the samples outside it).
    pub support: Option<Support>,
}

impl Field<'_> {
    /// The object-space point of the world point x (x itself for a still object).
    #[inline]
    pub fn object_point(&self, x: Vec3) -> Vec3 {
        self.pose.map_or(x, |p| p.to_object(x))
    }

    /// The world direction of an object-space direction.
    #[inline]
    pub fn world_vector(&self, v: Vec3) -> Vec3 {
        self.pose.map_or(v, |p| p.to_world_vector(v))
    }
}

impl Field<'_> {
    #[inline]
    fn noise(&self, frequency: f32, x: Vec3) -> f32 {
        self.noise.noise((x - self.offset) * frequency)
    }

    #[inline]
    fn turbulence(&self, frequency: f32, x: Vec3, octaves: u32) -> f32 {
        self.noise
            .turbulence((x - self.offset) * frequency, octaves)
    }
}

/// A node of the object density tree.
#[derive(Clone, Debug, PartialEq)]
pub enum Density {
    /// A soft sphere.
    Sphere(SoftSphere),
    /// A soft box.
    Box(SoftBox),
    /// A soft torus.
    Torus(SoftTorus),
    /// Generalized union, folded.
    Union(Vec<Density>),
    /// Generalized intersection, folded.
    Intersection(Vec<Density>),
    /// Generalized difference.
    Difference(Box<Density>, Box<Density>),
    /// Generalized complement.
    Complement(Box<Density>),
    /// Largest density.
    Max(Vec<Density>),
    /// Smallest density.
    Min(Vec<Density>),
    /// An object with its own DMFs.
    Hypertexture(Box<Hypertexture>),
    /// A density written as an expression (the Pixel Stream Editor), clamped to [0, 1].
    Expression(Box<crate::pse::Program>),
    /// The scene's hypertexture on a moving object: evaluated at the
    /// object-space point of the field's pose (the root of a moving scene only).
    Moving(Box<Density>),
}

impl Density {
    /// Builds the runtime tree; `step` is the marching step used for frequency clamping.
    pub fn build(desc: &ObjectDesc, step: f32) -> Density {
        let all = |v: &Vec<ObjectDesc>| v.iter().map(|d| Density::build(d, step)).collect();
        match desc {
            ObjectDesc::Sphere(s) => Density::Sphere(SoftSphere {
                centre: s.centre.0,
                falloff: Falloff::new(s.radius, s.softness),
            }),
            ObjectDesc::Box(b) => Density::Box(SoftBox {
                centre: b.centre.0,
                falloff: b
                    .half_size
                    .0
                    .to_array()
                    .map(|h| Falloff::new(h, b.softness)),
            }),
            ObjectDesc::Torus(t) => Density::Torus(SoftTorus {
                centre: t.centre.0,
                axis: t.axis.0,
                major_radius: t.major_radius,
                falloff: Falloff::new(t.minor_radius, t.softness),
            }),
            ObjectDesc::Union(v) => Density::Union(all(v)),
            ObjectDesc::Intersection(v) => Density::Intersection(all(v)),
            ObjectDesc::Max(v) => Density::Max(all(v)),
            ObjectDesc::Min(v) => Density::Min(all(v)),
            ObjectDesc::Difference(a, b) => Density::Difference(
                Box::new(Density::build(a, step)),
                Box::new(Density::build(b, step)),
            ),
            ObjectDesc::Complement(a) => Density::Complement(Box::new(Density::build(a, step))),
            ObjectDesc::Hypertexture(h) => Density::Hypertexture(Box::new(
                Hypertexture::build(Density::build(&h.object, step), &h.modulation, step)
                    .with_distortion(h.distortion.as_ref().map(Distortion::build)),
            )),
        }
    }

    /// The density at x, in [0, 1].
    #[inline]
    pub fn eval(&self, x: Vec3, field: &Field) -> f32 {
        match self {
            Density::Sphere(s) => s.density(x),
            Density::Box(b) => b.density(x),
            Density::Torus(t) => t.density(x),
            Density::Union(v) => v
                .iter()
                .fold(0.0, |a, d| boolean::union(a, d.eval(x, field))),
            Density::Intersection(v) => {
                let mut a = 1.0;
                for d in v {
                    a = boolean::intersection(a, d.eval(x, field));
                    if a == 0.0 {
                        break;
                    }
                }
                a
            }
            Density::Difference(a, b) => {
                let a = a.eval(x, field);
                if a == 0.0 {
                    0.0
                } else {
                    boolean::difference(a, b.eval(x, field))
                }
            }
            Density::Complement(a) => boolean::complement(a.eval(x, field)),
            Density::Max(v) => v.iter().fold(0.0, |a, d| a.max(d.eval(x, field))),
            Density::Min(v) => v.iter().fold(1.0, |a, d| a.min(d.eval(x, field))),
            Density::Hypertexture(h) => h.eval(x, field),
            Density::Expression(p) => crate::shaping::clamp01(p.eval_scalar(x, 0.0, field)),
            Density::Moving(d) => d.eval(field.object_point(x), field),
        }
    }

    /// x projected perpendicularly onto the inner (D = 1) surface; only primitives
    /// can project (checked at load for every DMF that needs it).
    #[inline]
    pub(crate) fn project(&self, x: Vec3) -> Vec3 {
        match self {
            Density::Sphere(s) => s.project(x),
            Density::Box(b) => b.project(x),
            Density::Torus(t) => t.project(x),
            _ => x,
        }
    }

    /// [`Density::project`] at each point.
    #[inline(always)]
    pub(crate) fn project_lanes(&self, x: &Points) -> Points {
        match self {
            Density::Sphere(s) => x.map(|p| s.project(p)),
            Density::Box(b) => x.map(|p| b.project(p)),
            Density::Torus(t) => {
                let mut p = *x;
                t.project_lanes(&mut p.x, &mut p.y, &mut p.z);
                p
            }
            _ => *x,
        }
    }

    /// Whether `Density::project` (the fur's projection onto the inner surface) is
    /// defined for this node.
    pub fn can_project(desc: &ObjectDesc) -> bool {
        matches!(
            desc,
            ObjectDesc::Sphere(_) | ObjectDesc::Box(_) | ObjectDesc::Torus(_)
        )
    }
}

/// An object with its DMFs: `H(D(x), x) = f_n(... f_1(f_0(D(w(x)))))` where `w`
/// composes the position-dependent DMFs (warps).
#[derive(Clone, Debug, PartialEq)]
pub struct Hypertexture {
    /// D.
    object: Density,
    /// Position-dependent DMFs, applied to x in order before D is evaluated.
    warps: Vec<Warp>,
    /// Value DMFs, applied to the density in order.
    modulation: Vec<Modulation>,
    /// Gilet & Dischler's distortion (formula 3), applied after the warps.
    distortion: Option<Distortion>,
}

impl Hypertexture {
    /// Builds the DMF chain around `object` (the order was validated at load).
    pub fn build(object: Density, dmfs: &[DmfDesc], step: f32) -> Hypertexture {
        let mut warps = Vec::new();
        let mut modulation = Vec::new();
        for dmf in dmfs {
            match *dmf {
                DmfDesc::NoisyRadius {
                    frequency,
                    amplitude,
                    centre,
                } => warps.push(Warp::NoisyRadius {
                    frequency: frequency.0,
                    amplitude: amplitude.0,
                    centre: centre.0,
                }),
                DmfDesc::FractalRadius {
                    frequency,
                    octaves,
                    amplitude,
                    centre,
                } => warps.push(Warp::FractalRadius {
                    frequency: frequency.0,
                    octaves: clamped_octaves(frequency.0, step, octaves.0),
                    amplitude: amplitude.0,
                    centre: centre.0,
                }),
                DmfDesc::Dripping {
                    frequency,
                    amplitude,
                    stretch,
                    centre,
                } => warps.push(Warp::Dripping {
                    frequency: frequency.0,
                    amplitude: amplitude.0,
                    stretch: stretch.0,
                    centre: centre.0,
                }),
                DmfDesc::TurbulentRadius {
                    frequency,
                    amplitude,
                    octaves,
                    centre,
                } => warps.push(Warp::TurbulentRadius {
                    frequency: frequency.0,
                    amplitude: amplitude.0,
                    octaves: clamped_octaves(frequency.0, step, octaves.0),
                    centre: centre.0,
                }),
                DmfDesc::Bias(b) => modulation.push(Modulation::Bias(Bias::new(b.0))),
                DmfDesc::Gain(g) => modulation.push(Modulation::Gain(Gain::new(g.0))),
                DmfDesc::Fur {
                    frequency,
                    bias,
                    gain,
                    curliness,
                    curl_gain,
                } => modulation.push(Modulation::Fur(Fur {
                    frequency: frequency.0,
                    bias: Bias::new(bias.0),
                    gain: Gain::new(gain.0),
                    curliness: curliness.0,
                    curl_gain: Gain::new(curl_gain.0),
                })),
            }
        }
        Hypertexture {
            object,
            warps,
            modulation,
            distortion: None,
        }
    }

    /// The same chain with Gilet & Dischler's distortion after the warps.
    pub fn with_distortion(self, distortion: Option<Distortion>) -> Hypertexture {
        Hypertexture { distortion, ..self }
    }

    /// The distortion, if any.
    pub fn distortion(&self) -> Option<&Distortion> {
        self.distortion.as_ref()
    }

    /// The object D the DMFs modulate.
    pub fn object(&self) -> &Density {
        &self.object
    }

    /// H at x.
    #[inline]
    pub fn eval(&self, x: Vec3, field: &Field) -> f32 {
        let mut p = x;
        for w in &self.warps {
            p = w.apply(p, field);
        }
        if let Some(d) = &self.distortion {
            p = d.apply(p, &self.object, field);
        }
        let d = self.object.eval(p, field);
        let mut v = d;
        for m in &self.modulation {
            if v == 0.0 {
                break; // every value DMF maps 0 to 0
            }
            v = match m {
                Modulation::Bias(b) => b.apply(v),
                Modulation::Gain(g) => g.apply(v),
                Modulation::Fur(f) => f.apply(v, p, &self.object, field),
            };
        }
        v
    }
}

/// A position-dependent DMF: where D is evaluated.
#[derive(Clone, Copy, Debug, PartialEq)]
enum Warp {
    /// `c + (x - c)(1 + a · noise(f x))`.
    NoisyRadius {
        frequency: f32,
        amplitude: f32,
        centre: Vec3,
    },
    /// `c + (x - c)(1 + a · Σ noise(2^i f x) / (2^i f))`.
    FractalRadius {
        frequency: f32,
        octaves: u32,
        amplitude: f32,
        centre: Vec3,
    },
    /// y only, below the centre: `c.y + (y - c.y)(1 - a · max(0, noise(f · (x, stretch · y, z))))`,
    /// so material hangs down in drips where the noise is positive.
    Dripping {
        frequency: f32,
        amplitude: f32,
        stretch: f32,
        centre: Vec3,
    },
    /// `c + (x - c)(1 + a · turbulence(f x))`.
    TurbulentRadius {
        frequency: f32,
        amplitude: f32,
        octaves: u32,
        centre: Vec3,
    },
}

impl Warp {
    #[inline]
    fn apply(&self, x: Vec3, field: &Field) -> Vec3 {
        match *self {
            Warp::NoisyRadius {
                frequency,
                amplitude,
                centre,
            } => centre + (x - centre) * (1.0 + amplitude * field.noise(frequency, x)),
            Warp::FractalRadius {
                frequency,
                octaves,
                amplitude,
                centre,
            } => {
                let mut sum = 0.0;
                let mut f = frequency;
                for _ in 0..octaves {
                    sum += field.noise(f, x) / f;
                    f *= 2.0;
                }
                centre + (x - centre) * (1.0 + amplitude * sum)
            }
            Warp::Dripping {
                frequency,
                amplitude,
                stretch,
                centre,
            } => {
                if x.y >= centre.y {
                    return x;
                }
                let q = x - field.offset;
                let n = field
                    .noise
                    .noise(Vec3::new(q.x, q.y * stretch, q.z) * frequency);
                let pull = 1.0 - amplitude * n.max(0.0);
                Vec3::new(x.x, centre.y + (x.y - centre.y) * pull, x.z)
            }
            Warp::TurbulentRadius {
                frequency,
                amplitude,
                octaves,
                centre,
            } => {
                centre + (x - centre) * (1.0 + amplitude * field.turbulence(frequency, x, octaves))
            }
        }
    }
}

/// A DMF of the density value (position-independent or geometry-dependent).
#[derive(Clone, Copy, Debug, PartialEq)]
enum Modulation {
    Bias(Bias),
    Gain(Gain),
    Fur(Fur),
}

/// The paper's fur, straight (curliness 0) or curly (the tribble).
#[derive(Clone, Copy, Debug, PartialEq)]
struct Fur {
    /// Fineness: noise frequency on the inner surface.
    frequency: f32,
    /// Shapes the noise: more empty space than hair.
    bias: Bias,
    /// Shapes the noise: hard-edged hairs.
    gain: Gain,
    /// Magnitude of the curl.
    curliness: f32,
    /// `gain_0.8`: straight at the root (d = 1), curling towards the tip.
    curl_gain: Gain,
}

impl Fur {
    /// `f = gain(bias(s)) · d` with `s = noise(freq · project(x'))` brought into the
    /// unit interval where bias and gain are defined: `s = (1 + noise) / 2` (the
    /// paper's noise ranges over [-1, 1]; clamping it instead would leave half the
    /// surface bald).
    #[inline]
    fn apply(&self, d: f32, x: Vec3, object: &Density, field: &Field) -> f32 {
        let x = if self.curliness > 0.0 {
            let q = x - field.offset;
            x + field.noise.vnoise(q) * (self.curl_gain.apply(1.0 - d) * self.curliness)
        } else {
            x
        };
        let s = 0.5 * (1.0 + field.noise(self.frequency, object.project(x)));
        self.gain.apply(self.bias.apply(s)) * d
    }
}

/// The tree differentiated ([`crate::dual`]): the density and its gradient with
/// respect to the world point in one pass. `h` is the spacing of the central
/// differences of the parts without a derivative written out (the distortion
/// and expressions).
impl Density {
    /// [`Density::eval`] at `x` with its gradient.
    pub fn eval_dual(&self, x: &DualPoint, field: &Field, h: f32) -> Dual {
        match self {
            Density::Sphere(s) => s.density_dual(x),
            Density::Box(b) => b.density_dual(x),
            Density::Torus(t) => t.density_dual(x),
            Density::Union(v) => v.iter().fold(Dual::constant(0.0), |a, d| {
                let b = d.eval_dual(x, field, h);
                a + b - a * b
            }),
            Density::Intersection(v) => {
                let mut a = Dual::constant(1.0);
                for d in v {
                    a = a * d.eval_dual(x, field, h);
                    if a.v == 0.0 {
                        break;
                    }
                }
                a
            }
            Density::Difference(a, b) => {
                let a = a.eval_dual(x, field, h);
                if a.v == 0.0 {
                    return Dual::constant(0.0);
                }
                a - a * b.eval_dual(x, field, h)
            }
            Density::Complement(a) => -a.eval_dual(x, field, h) + 1.0,
            Density::Max(v) => v
                .iter()
                .fold(Dual::constant(0.0), |a, d| a.max(d.eval_dual(x, field, h))),
            Density::Min(v) => v
                .iter()
                .fold(Dual::constant(1.0), |a, d| a.min(d.eval_dual(x, field, h))),
            Density::Hypertexture(t) => t.eval_dual(x, field, h),
            Density::Expression(_) => x.apply(h, |p| self.eval(p, field)).clamp01(),
            Density::Moving(d) => match &field.pose {
                Some(pose) => d.eval_dual(&pose.to_object_dual(x), field, h),
                None => d.eval_dual(x, field, h),
            },
        }
    }

    /// [`Density::project`] with its Jacobian.
    #[inline]
    fn project_dual(&self, x: &DualPoint) -> DualPoint {
        match self {
            Density::Sphere(s) => s.project_dual(x),
            Density::Box(b) => b.project_dual(x),
            Density::Torus(t) => t.project_dual(x),
            _ => *x,
        }
    }
}

impl Hypertexture {
    /// [`Hypertexture::eval`] with its gradient.
    fn eval_dual(&self, x: &DualPoint, field: &Field, h: f32) -> Dual {
        let mut p = *x;
        for w in &self.warps {
            p = w.apply_dual(&p, field);
        }
        if let Some(d) = &self.distortion {
            p = p.through(h, |q| d.apply(q, &self.object, field));
        }
        let mut v = self.object.eval_dual(&p, field, h);
        for m in &self.modulation {
            if v.v == 0.0 {
                break; // every value DMF maps 0 to 0
            }
            v = match m {
                Modulation::Bias(b) => b.apply_dual(v),
                Modulation::Gain(g) => g.apply_dual(v),
                Modulation::Fur(f) => f.apply_dual(v, &p, &self.object, field),
            };
        }
        v
    }
}

impl Field<'_> {
    /// [`Field::noise`] with its gradient.
    #[inline]
    fn noise_dual(&self, frequency: f32, x: &DualPoint) -> Dual {
        self.noise
            .noise_dual(&x.offset(-self.offset).times(frequency))
    }
}

impl Warp {
    /// [`Warp::apply`] with its Jacobian.
    fn apply_dual(&self, x: &DualPoint, field: &Field) -> DualPoint {
        let scale_about = |centre: Vec3, s: Dual| x.offset(-centre).scale(s).offset(centre);
        match *self {
            Warp::NoisyRadius {
                frequency,
                amplitude,
                centre,
            } => scale_about(centre, field.noise_dual(frequency, x) * amplitude + 1.0),
            Warp::FractalRadius {
                frequency,
                octaves,
                amplitude,
                centre,
            } => {
                let mut sum = Dual::constant(0.0);
                let mut f = frequency;
                for _ in 0..octaves {
                    sum = sum + field.noise_dual(f, x) * (1.0 / f);
                    f *= 2.0;
                }
                scale_about(centre, sum * amplitude + 1.0)
            }
            Warp::Dripping {
                frequency,
                amplitude,
                stretch,
                centre,
            } => {
                if x.y.v >= centre.y {
                    return *x;
                }
                let mut q = x.offset(-field.offset);
                q.y = q.y * stretch;
                let n = field.noise.noise_dual(&q.times(frequency));
                let pull = -(n.max(Dual::constant(0.0)) * amplitude) + 1.0;
                DualPoint {
                    y: (x.y - centre.y) * pull + centre.y,
                    ..*x
                }
            }
            Warp::TurbulentRadius {
                frequency,
                amplitude,
                octaves,
                centre,
            } => {
                let q = x.offset(-field.offset).times(frequency);
                let mut sum = Dual::constant(0.0);
                let mut scale = 1.0f32;
                for _ in 0..octaves {
                    sum = sum + field.noise.noise_dual(&q.times(scale)).abs() * (1.0 / scale);
                    scale *= 2.0;
                }
                scale_about(centre, sum * amplitude + 1.0)
            }
        }
    }
}

impl Fur {
    /// [`Fur::apply`] with its gradient: through the curl, the projection onto
    /// the inner surface and the noise there.
    fn apply_dual(&self, d: Dual, x: &DualPoint, object: &Density, field: &Field) -> Dual {
        let x = if self.curliness > 0.0 {
            let q = x.offset(-field.offset);
            let vnoise = DualPoint {
                x: field.noise.noise_dual(&q.offset(-VNOISE_OFFSET)),
                y: field.noise.noise_dual(&q),
                z: field.noise.noise_dual(&q.offset(VNOISE_OFFSET)),
            };
            let curl = self.curl_gain.apply_dual(-d + 1.0) * self.curliness;
            x.add(&vnoise.scale(curl))
        } else {
            *x
        };
        let s = (field.noise_dual(self.frequency, &object.project_dual(&x)) + 1.0) * 0.5;
        self.gain.apply_dual(self.bias.apply_dual(s)) * d
    }
}

/// [`LANES`] points, one coordinate per array: the batch the vectorised paths
/// evaluate (several samples along a ray, or the gradient's neighbours).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Points {
    /// x of each point.
    pub x: Lanes,
    /// y of each point.
    pub y: Lanes,
    /// z of each point.
    pub z: Lanes,
}

impl Points {
    /// Point `l`.
    #[inline(always)]
    pub fn get(&self, l: usize) -> Vec3 {
        Vec3::new(self.x[l], self.y[l], self.z[l])
    }

    /// Sets point `l`.
    #[inline(always)]
    pub fn set(&mut self, l: usize, p: Vec3) {
        self.x[l] = p.x;
        self.y[l] = p.y;
        self.z[l] = p.z;
    }

    /// The points `f(point)`, lane by lane.
    #[inline(always)]
    pub(crate) fn map(&self, f: impl Fn(Vec3) -> Vec3) -> Points {
        let mut out = Points::default();
        for l in 0..LANES {
            out.set(l, f(self.get(l)));
        }
        out
    }
}

/// `f(point)` lane by lane.
#[inline(always)]
fn each(x: &Points, f: impl Fn(Vec3) -> f32) -> Lanes {
    let mut out = [0.0; LANES];
    for (l, o) in out.iter_mut().enumerate() {
        *o = f(x.get(l));
    }
    out
}

/// `f(a, b)` lane by lane.
#[inline(always)]
fn zip(a: &Lanes, b: &Lanes, f: impl Fn(f32, f32) -> f32) -> Lanes {
    let mut out = [0.0; LANES];
    for l in 0..LANES {
        out[l] = f(a[l], b[l]);
    }
    out
}

impl Field<'_> {
    /// `noise` at the points: the lane kernel itself, inlined into the
    /// per-instruction-set copy of [`Density::eval_lanes`] (`isa` is a
    /// constant there).
    #[inline(always)]
    fn noise_lanes(&self, p: &Points, isa: Isa) -> Lanes {
        self.noise.noise_lanes_on(isa, &p.x, &p.y, &p.z)
    }

    /// [`Field::noise`] at each point: `noise((x − offset) · frequency)`.
    #[inline(always)]
    fn noise_at(&self, frequency: f32, x: &Points, isa: Isa) -> Lanes {
        self.noise_lanes(&x.map(|p| (p - self.offset) * frequency), isa)
    }
}

impl Density {
    /// [`Density::eval`] at [`LANES`] points: the same bits lane by lane, with
    /// the noise and the powers computed a batch at a time on `isa`.
    #[inline]
    pub fn eval_lanes(&self, x: &Points, field: &Field, isa: Isa) -> Lanes {
        match isa {
            Isa::Scalar => each(x, |p| self.eval(p, field)),
            // SAFETY: a scene only carries a path that `Isa::available`
            // reported, and `Scene::with_isa` refuses the others.
            #[cfg(target_arch = "x86_64")]
            Isa::Sse41 => unsafe { x86::eval_lanes_sse41(self, x, field) },
            #[cfg(target_arch = "x86_64")]
            Isa::Avx2 => unsafe { x86::eval_lanes_avx2(self, x, field) },
            #[cfg(not(target_arch = "x86_64"))]
            _ => each(x, |p| self.eval(p, field)),
        }
    }

    /// [`Density::eval_lanes`] on a SIMD path: written once, inlined into a
    /// copy per instruction set (`x86` below) together with everything it
    /// calls but its children, so the lanes stay in that set's registers
    /// from the points to the powers.
    #[inline(always)]
    pub(crate) fn eval_lanes_simd(&self, x: &Points, field: &Field, isa: Isa) -> Lanes {
        match self {
            Density::Sphere(s) => s.density_lanes(&x.x, &x.y, &x.z),
            Density::Box(b) => each(x, |p| b.density(p)),
            Density::Torus(t) => t.density_lanes(&x.x, &x.y, &x.z),
            Density::Expression(program) => {
                program.eval_lanes(x, &[0.0; LANES], field, isa)[0].map(crate::shaping::clamp01)
            }
            Density::Union(v) => v.iter().fold([0.0; LANES], |a, d| {
                zip(&a, &d.eval_child(x, field, isa), boolean::union)
            }),
            Density::Intersection(v) => {
                let mut a = [1.0; LANES];
                for d in v {
                    if a.iter().all(|&a| a == 0.0) {
                        break;
                    }
                    let b = d.eval_child(x, field, isa);
                    // A lane that reached 0 stopped there (`eval` breaks out).
                    a = zip(&a, &b, |a, b| {
                        if a == 0.0 {
                            a
                        } else {
                            boolean::intersection(a, b)
                        }
                    });
                }
                a
            }
            Density::Difference(a, b) => {
                let a = a.eval_child(x, field, isa);
                if a.iter().all(|&a| a == 0.0) {
                    return [0.0; LANES];
                }
                let b = b.eval_child(x, field, isa);
                zip(&a, &b, |a, b| {
                    if a == 0.0 {
                        0.0
                    } else {
                        boolean::difference(a, b)
                    }
                })
            }
            Density::Complement(a) => a.eval_child(x, field, isa).map(boolean::complement),
            Density::Max(v) => v.iter().fold([0.0; LANES], |a, d| {
                zip(&a, &d.eval_child(x, field, isa), f32::max)
            }),
            Density::Min(v) => v.iter().fold([1.0; LANES], |a, d| {
                zip(&a, &d.eval_child(x, field, isa), f32::min)
            }),
            Density::Hypertexture(h) => h.eval_lanes_simd(x, field, isa),
            Density::Moving(d) => match &field.pose {
                Some(pose) => d.eval_child(&pose.to_object_lanes(x), field, isa),
                None => d.eval_child(x, field, isa),
            },
        }
    }
}

impl Density {
    /// A child's lanes inside [`Density::eval_lanes_simd`]: the primitives
    /// inline, the rest through [`Density::eval_lanes`].
    #[inline(always)]
    fn eval_child(&self, x: &Points, field: &Field, isa: Isa) -> Lanes {
        match self {
            Density::Sphere(s) => s.density_lanes(&x.x, &x.y, &x.z),
            Density::Torus(t) => t.density_lanes(&x.x, &x.y, &x.z),
            _ => self.eval_lanes(x, field, isa),
        }
    }
}

/// The copies of [`Density::eval_lanes_simd`] per instruction set.
#[cfg(target_arch = "x86_64")]
mod x86 {
    use super::*;

    #[target_feature(enable = "avx2")]
    pub(super) fn eval_lanes_avx2(d: &Density, x: &Points, field: &Field) -> Lanes {
        d.eval_lanes_simd(x, field, Isa::Avx2)
    }

    #[target_feature(enable = "sse4.1")]
    pub(super) fn eval_lanes_sse41(d: &Density, x: &Points, field: &Field) -> Lanes {
        d.eval_lanes_simd(x, field, Isa::Sse41)
    }
}

impl Hypertexture {
    /// [`Hypertexture::eval`] at [`LANES`] points on a SIMD path (see
    /// [`Density::eval_lanes_simd`]).
    #[inline(always)]
    fn eval_lanes_simd(&self, x: &Points, field: &Field, isa: Isa) -> Lanes {
        let mut p = *x;
        for w in &self.warps {
            p = w.apply_lanes(&p, field, isa);
        }
        if let Some(d) = &self.distortion {
            p = p.map(|q| d.apply(q, &self.object, field));
        }
        let mut v = self.object.eval_child(&p, field, isa);
        for m in &self.modulation {
            if v.iter().all(|&v| v == 0.0) {
                break;
            }
            let next = match m {
                Modulation::Bias(b) => b.apply_simd(&v),
                Modulation::Gain(g) => g.apply_simd(&v),
                Modulation::Fur(f) => f.apply_lanes(&v, &p, &self.object, field, isa),
            };
            // A lane at 0 stopped there (`eval` breaks out: every DMF keeps 0).
            v = zip(&v, &next, |v, n| if v == 0.0 { v } else { n });
        }
        v
    }
}

impl Warp {
    /// [`Warp::apply`] at each point (on a SIMD path).
    #[inline(always)]
    fn apply_lanes(&self, x: &Points, field: &Field, isa: Isa) -> Points {
        let scale_about = |centre: Vec3, s: &Lanes| {
            let mut out = Points::default();
            for (l, &s) in s.iter().enumerate() {
                out.set(l, centre + (x.get(l) - centre) * s);
            }
            out
        };
        match *self {
            Warp::NoisyRadius {
                frequency,
                amplitude,
                centre,
            } => {
                let n = field.noise_at(frequency, x, isa);
                scale_about(centre, &n.map(|n| 1.0 + amplitude * n))
            }
            Warp::FractalRadius {
                frequency,
                octaves,
                amplitude,
                centre,
            } => {
                let mut sum = [0.0; LANES];
                let mut f = frequency;
                for _ in 0..octaves {
                    let n = field.noise_at(f, x, isa);
                    sum = zip(&sum, &n, |s, n| s + n / f);
                    f *= 2.0;
                }
                scale_about(centre, &sum.map(|s| 1.0 + amplitude * s))
            }
            Warp::Dripping {
                frequency,
                amplitude,
                stretch,
                centre,
            } => {
                if x.y.iter().all(|&y| y >= centre.y) {
                    return *x;
                }
                let o = field.offset;
                let mut q = Points::default();
                for l in 0..LANES {
                    q.x[l] = (x.x[l] - o.x) * frequency;
                    q.y[l] = ((x.y[l] - o.y) * stretch) * frequency;
                    q.z[l] = (x.z[l] - o.z) * frequency;
                }
                let n = field.noise_lanes(&q, isa);
                let mut out = *x;
                for (l, &n) in n.iter().enumerate() {
                    let y = x.y[l];
                    let pull = 1.0 - amplitude * n.max(0.0);
                    let moved = centre.y + (y - centre.y) * pull;
                    out.y[l] = if y < centre.y { moved } else { y };
                }
                out
            }
            Warp::TurbulentRadius {
                frequency,
                amplitude,
                octaves,
                centre,
            } => {
                let q = x.map(|p| (p - field.offset) * frequency);
                let mut sum = [0.0; LANES];
                let mut scale = 1.0f32;
                for _ in 0..octaves {
                    let n = field.noise_lanes(&q.map(|p| p * scale), isa);
                    sum = zip(&sum, &n, |s, n| s + n.abs() / scale);
                    scale *= 2.0;
                }
                scale_about(centre, &sum.map(|t| 1.0 + amplitude * t))
            }
        }
    }
}

impl Fur {
    /// [`Fur::apply`] at each point (on a SIMD path).
    #[inline(always)]
    fn apply_lanes(
        &self,
        d: &Lanes,
        x: &Points,
        object: &Density,
        field: &Field,
        isa: Isa,
    ) -> Lanes {
        let x = if self.curliness > 0.0 {
            let q = x.map(|x| x - field.offset);
            let a = field.noise_lanes(&q.map(|q| q - VNOISE_OFFSET), isa);
            let b = field.noise_lanes(&q, isa);
            let c = field.noise_lanes(&q.map(|q| q + VNOISE_OFFSET), isa);
            let curl = self.curl_gain.apply_simd(&d.map(|d| 1.0 - d));
            let mut out = Points::default();
            for l in 0..LANES {
                let v = Vec3::new(a[l], b[l], c[l]);
                out.set(l, x.get(l) + v * (curl[l] * self.curliness));
            }
            out
        } else {
            *x
        };
        let s = field
            .noise_at(self.frequency, &object.project_lanes(&x), isa)
            .map(|n| 0.5 * (1.0 + n));
        let shaped = self.gain.apply_simd(&self.bias.apply_simd(&s));
        zip(&shaped, d, |f, d| f * d)
    }
}

/// An axis-aligned box `(min, max)`.
pub type Aabb = (Vec3, Vec3);

/// Where the density can be non-zero, as the marcher uses it: a box and,
/// where one is known, a ball (see [`Density::support_ball`]).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Support {
    /// The box of [`Density::support`].
    pub aabb: Aabb,
    /// The ball of [`Density::support_ball`] `(centre, radius)`.
    pub ball: Option<(Vec3, f32)>,
}

/// A bound on |noise| that holds for every seed, √(3/4) widened by 1% for
/// rounding. With W_c = ω(u_c)ω(v_c)ω(w_c) the weight and d_c the offset of
/// corner c (the weights are ≥ 0 and sum to 1: ω(t) + ω(1 − t) = 1 on each
/// axis) and |Γ_c| = 1:
/// |noise| ≤ Σ W_c |Γ_c·d_c| ≤ Σ W_c |d_c| ≤ √(Σ W_c |d_c|²) (Jensen)
/// = √(g(u) + g(v) + g(w)) with g(t) = ω(t)t² + ω(1 − t)(1 − t)², and
/// g(t) − ¼ = (2t − 1)²((2t − 1)² − 2)/4 ≤ 0 on [0, 1].
pub const NOISE_BOUND: f32 = 0.875;

fn hull(a: Aabb, b: Aabb) -> Aabb {
    (a.0.min(b.0), a.1.max(b.1))
}

/// The points x whose scaling about `centre` by some factor in `[lo, hi]` lands
/// in `b` (lo > 0): each coordinate is linear in 1/s, so the ends bound it.
fn unscale(b: Aabb, centre: Vec3, lo: f32, hi: f32, axes: Vec3) -> Option<Aabb> {
    if !(lo > 0.0 && hi.is_finite()) {
        return None;
    }
    let scaled = |s: f32| {
        let k = Vec3::ONE + axes * (1.0 / s - 1.0);
        let (p, q) = (centre + (b.0 - centre) * k, centre + (b.1 - centre) * k);
        (p.min(q), p.max(q))
    };
    Some(hull(scaled(lo), scaled(hi)))
}

impl Density {
    /// A box outside which the density is 0 for certain, or `None` when it may
    /// be non-zero anywhere (a complement). The marcher skips samples outside it.
    pub fn support(&self) -> Option<Aabb> {
        let all = |v: &[Density], join: fn(Aabb, Aabb) -> Aabb| {
            v.iter()
                .map(Density::support)
                .try_fold(None, |acc: Option<Aabb>, s| {
                    let s = s?;
                    Some(Some(acc.map_or(s, |a| join(a, s))))
                })
                .flatten()
        };
        let meet_known = |v: &[Density]| {
            v.iter()
                .filter_map(Density::support)
                .reduce(|a, b| (a.0.max(b.0), a.1.min(b.1)))
        };
        match self {
            Density::Sphere(s) => Some((
                s.centre - Vec3::splat(s.falloff.outer()),
                s.centre + Vec3::splat(s.falloff.outer()),
            )),
            Density::Box(b) => {
                let h = Vec3::new(
                    b.falloff[0].outer(),
                    b.falloff[1].outer(),
                    b.falloff[2].outer(),
                );
                Some((b.centre - h, b.centre + h))
            }
            Density::Torus(t) => {
                let a = t.axis;
                let r = t.falloff.outer();
                let across = (Vec3::ONE - a * a).max(Vec3::ZERO);
                let across = Vec3::new(across.x.sqrt(), across.y.sqrt(), across.z.sqrt());
                let reach = across * t.major_radius + Vec3::splat(r);
                Some((t.centre - reach, t.centre + reach))
            }
            Density::Union(v) | Density::Max(v) => all(v, hull),
            Density::Intersection(v) | Density::Min(v) => meet_known(v),
            Density::Difference(a, _) => a.support(),
            // A complement may be non-zero anywhere.
            Density::Complement(_) => None,
            Density::Expression(p) => p.support(),
            // In object space: the field maps it to the world of each moment.
            Density::Moving(d) => d.support(),
            Density::Hypertexture(h) => h.support(),
        }
    }
}

impl Density {
    /// A ball `(centre, radius)` outside which the density is 0 for certain,
    /// where one is known: around soft spheres and tori and the radial warps
    /// of them (the gallery's noisy, fractal and fiery spheres, the furry
    /// donut), tighter than the box of [`Density::support`] (the marcher skips
    /// what lies outside either).
    pub fn support_ball(&self) -> Option<(Vec3, f32)> {
        match self {
            Density::Sphere(s) => Some((s.centre, s.falloff.outer())),
            Density::Torus(t) => Some((t.centre, t.major_radius + t.falloff.outer())),
            Density::Intersection(v) | Density::Min(v) => v.iter().find_map(Density::support_ball),
            Density::Difference(a, _) => a.support_ball(),
            Density::Hypertexture(h) => h.support_ball(),
            // In object space, like `support`.
            Density::Moving(d) => d.support_ball(),
            Density::Expression(p) => p.support_ball(),
            _ => None,
        }
    }
}

impl Hypertexture {
    /// [`Density::support_ball`]: the object's, widened by the distortion's
    /// largest displacement and pulled back through the warps that scale about
    /// its centre (x is evaluated at c + (x − c)·s, s ≥ lo > 0, so |x − c| ≤ r / lo).
    fn support_ball(&self) -> Option<(Vec3, f32)> {
        let (centre, mut r) = self.object.support_ball()?;
        if let Some(d) = &self.distortion {
            r += d.max_displacement();
        }
        for w in self.warps.iter().rev() {
            let (about, lo, _) = w.scale_range()?;
            if about != centre || lo.is_nan() || lo <= 0.0 {
                return None;
            }
            r /= lo;
        }
        r.is_finite().then_some((centre, r))
    }

    /// [`Density::support`]: the object's, widened by the distortion's largest
    /// displacement and pulled back through the warps.
    pub fn support(&self) -> Option<Aabb> {
        let mut b = self.object.support()?;
        if let Some(d) = &self.distortion {
            // x is evaluated at x − k·V/|V| with |k| ≤ the largest displacement.
            let reach = Vec3::splat(d.max_displacement());
            b = (b.0 - reach, b.1 + reach);
        }
        for w in self.warps.iter().rev() {
            b = w.preimage(b)?;
        }
        Some(b)
    }
}

impl Warp {
    /// For the warps `c + (x − c)·s` that scale about a centre c: c and the
    /// range `[lo, hi]` of the factor s.
    fn scale_range(&self) -> Option<(Vec3, f32, f32)> {
        let m = NOISE_BOUND;
        match *self {
            Warp::NoisyRadius {
                amplitude, centre, ..
            } => {
                let a = amplitude.abs() * m;
                Some((centre, 1.0 - a, 1.0 + a))
            }
            Warp::FractalRadius {
                frequency,
                octaves,
                amplitude,
                centre,
            } => {
                let mut sum = 0.0;
                let mut f = frequency;
                for _ in 0..octaves {
                    sum += m / f;
                    f *= 2.0;
                }
                let a = amplitude.abs() * sum;
                Some((centre, 1.0 - a, 1.0 + a))
            }
            Warp::TurbulentRadius {
                amplitude,
                octaves,
                centre,
                ..
            } => {
                let mut t = 0.0;
                let mut scale = 1.0;
                for _ in 0..octaves {
                    t += m / scale;
                    scale *= 2.0;
                }
                let a = amplitude * t;
                Some((centre, 1.0 + a.min(0.0), 1.0 + a.max(0.0)))
            }
            Warp::Dripping { .. } => None,
        }
    }

    /// A box holding every x that this warp moves into `b`.
    fn preimage(&self, b: Aabb) -> Option<Aabb> {
        let m = NOISE_BOUND;
        if let Some((centre, lo, hi)) = self.scale_range() {
            return unscale(b, centre, lo, hi, Vec3::ONE);
        }
        match *self {
            Warp::NoisyRadius { .. }
            | Warp::FractalRadius { .. }
            | Warp::TurbulentRadius { .. } => None,
            Warp::Dripping {
                amplitude, centre, ..
            } => {
                // Below the centre y is scaled by a pull in [1 − a·M, 1]
                // (a ≥ 0) or [1, 1 − a·M]; above, x is unchanged.
                let pull = 1.0 - amplitude * m;
                match unscale(b, centre, pull.min(1.0), pull.max(1.0), Vec3::Y) {
                    Some(stretched) => Some(hull(b, stretched)),
                    // A pull that can reach 0 may bring any y below the
                    // centre to the centre's: only x and z stay bounded.
                    None => Some((
                        Vec3::new(b.0.x, f32::NEG_INFINITY, b.0.z),
                        Vec3::new(b.1.x, b.1.y.max(centre.y), b.1.z),
                    )),
                }
            }
        }
    }
}
