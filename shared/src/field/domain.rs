//! The domain of the density: where it is evaluated (a point, or
//! [`Points`], [`LANES`] of them at once), when ([`Field`]: the moment, with
//! its noise tables, the drift of the noise domain and the object's pose),
//! and where it can be non-zero ([`Aabb`], [`Support`]). The density tree
//! ([`super::density`]), the distortion ([`super::distortion`]) and the
//! layers above read points and moments in these terms.

use glam::Vec3;

use crate::field::motion::Pose;
use crate::field::noise::Noise;
use crate::math::simd::{LANES, Lanes};

/// An axis-aligned box `(min, max)`.
pub type Aabb = (Vec3, Vec3);

/// Where the density can be non-zero, as the marcher uses it: a box and,
/// where one is known, a ball (see [`crate::field::density::Density::support_ball`]).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Support {
    /// The box of [`crate::field::density::Density::support`].
    pub aabb: Aabb,
    /// The ball of [`crate::field::density::Density::support_ball`] `(centre, radius)`.
    pub ball: Option<(Vec3, f32)>,
}

/// The smallest box holding `a` and `b`.
pub(crate) fn hull(a: Aabb, b: Aabb) -> Aabb {
    (a.0.min(b.0), a.1.max(b.1))
}

/// The points x whose scaling about `centre` by some factor in `[lo, hi]` lands
/// in `b` (lo > 0): each coordinate is linear in 1/s, so the ends bound it.
pub(crate) fn unscale(b: Aabb, centre: Vec3, lo: f32, hi: f32, axes: Vec3) -> Option<Aabb> {
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
    /// Where the moving object is at this moment ([`crate::field::density::Density::Moving`]).
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
    pub(crate) fn noise(&self, frequency: f32, x: Vec3) -> f32 {
        self.noise.noise((x - self.offset) * frequency)
    }

    #[inline]
    pub(crate) fn turbulence(&self, frequency: f32, x: Vec3, octaves: u32) -> f32 {
        self.noise
            .turbulence((x - self.offset) * frequency, octaves)
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

    /// The points `c + (x − c)·s` lane by lane: a warp's scaling about `centre`.
    #[inline(always)]
    pub(crate) fn scale_about(&self, centre: Vec3, s: &Lanes) -> Points {
        let mut out = Points::default();
        for (l, &s) in s.iter().enumerate() {
            out.set(l, centre + (self.get(l) - centre) * s);
        }
        out
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

    /// The points `f(point, other point)`, lane by lane.
    #[inline(always)]
    pub(crate) fn map_with(&self, other: &Points, f: impl Fn(Vec3, Vec3) -> Vec3) -> Points {
        let mut out = Points::default();
        for l in 0..LANES {
            out.set(l, f(self.get(l), other.get(l)));
        }
        out
    }
}

/// `f(a)` lane by lane: always inlined, where `[f32; N]::map` is left a
/// call compiled without the path's instruction set.
#[inline(always)]
pub(crate) fn map(a: &Lanes, f: impl Fn(f32) -> f32) -> Lanes {
    let mut out = [0.0; LANES];
    for l in 0..LANES {
        out[l] = f(a[l]);
    }
    out
}

/// `f(a, b)` lane by lane.
#[inline(always)]
pub(crate) fn zip(a: &Lanes, b: &Lanes, f: impl Fn(f32, f32) -> f32) -> Lanes {
    let mut out = [0.0; LANES];
    for l in 0..LANES {
        out[l] = f(a[l], b[l]);
    }
    out
}
