//! The hypertexture H(D(x), x): the object density tree with its density
//! modulation functions, built from the scene description.
//!
//! Evaluation is infallible and allocation-free: everything that can go wrong was
//! checked when the scene was loaded, and every constant (bias exponents, clamped
//! octave counts, squared radii) was computed then.

use glam::Vec3;

use crate::noise::{Noise, clamped_octaves};
use crate::scene::desc::{DmfDesc, ObjectDesc};
use crate::shaping::{Bias, Gain};
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
    /// Frames per second (`t = frame / frame_rate` in expressions).
    pub frame_rate: f32,
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
            ObjectDesc::Hypertexture(h) => Density::Hypertexture(Box::new(Hypertexture::build(
                Density::build(&h.object, step),
                &h.modulation,
                step,
            ))),
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

    /// Whether [`Density::project`] is defined for this node.
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
        }
    }

    /// H at x.
    #[inline]
    pub fn eval(&self, x: Vec3, field: &Field) -> f32 {
        let mut p = x;
        for w in &self.warps {
            p = w.apply(p, field);
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
