//! The density modulation functions, one file each, with every form of a DMF
//! side by side: the scalar reference, the dual (value and gradient), the
//! lanes (inlined into a SIMD path's copy) and, for a warp, the bound on how
//! far it moves a point (for the support).
//!
//! Adding a DMF is one file implementing [`WarpDmf`] (it moves the point
//! where D is evaluated) or [`ValueDmf`] (it reshapes the density), and one
//! line in `warps!` or `modulations!` below, which builds the enum that
//! dispatches to it and reads it from its [`DmfDesc`]. The test at the bottom
//! runs every registered DMF on every path.

use glam::Vec3;

use crate::desc::{DmfDesc, Octaves};
use crate::field::domain::{Aabb, Field, Points, unscale};
use crate::field::noise::NOISE_BOUND;
use crate::math::dual::{Dual, DualPoint};
use crate::math::simd::{Isa, Lanes};

mod bias;
mod dripping;
mod fractal_radius;
mod fur;
mod gain;
mod noisy_radius;
mod turbulent_radius;

pub use dripping::Dripping;
pub use fractal_radius::FractalRadius;
pub use fur::Fur;
pub use noisy_radius::NoisyRadius;
pub use turbulent_radius::TurbulentRadius;

/// A position-dependent DMF: `x ↦ w(x)`, where D is then evaluated. Every
/// form gives, lane by lane, the bits of [`WarpDmf::apply`].
pub trait WarpDmf: Sized {
    /// The warp described by `desc` (`None`: another DMF's description);
    /// `step` is the marching step, for frequency clamping.
    fn from_desc(desc: &DmfDesc, step: f32) -> Option<Self>;

    /// w(x): the scalar reference.
    fn apply(&self, x: Vec3, field: &Field) -> Vec3;

    /// w(x) with its Jacobian.
    fn apply_dual(&self, x: &DualPoint, field: &Field) -> DualPoint;

    /// w at each point, inlined into a SIMD path's copy (`isa` is a
    /// constant there): implementations are `#[inline(always)]`. A warp
    /// summing octaves into the factor s of [`WarpDmf::scale_range`] gives
    /// `settled(lo, hi)`, before each octave, the range `[lo, hi]` where each
    /// lane's s must end, and the octaves left skip a register's worth of
    /// the lanes it returns (a bit mask); such a lane comes out as another
    /// point of that range, with the same D. The other warps ignore it.
    fn apply_lanes(&self, x: &Points, field: &Field, isa: Isa, settled: &impl Settling) -> Points;

    /// For the warps `c + (x − c)·s` that scale about a centre c: c and the
    /// range `[lo, hi]` of the factor s.
    fn scale_range(&self) -> Option<(Vec3, f32, f32)>;

    /// A box holding every x that this warp moves into `b`, or `None`: anywhere.
    fn preimage(&self, b: Aabb) -> Option<Aabb> {
        let (centre, lo, hi) = self.scale_range()?;
        unscale(b, centre, lo, hi, Vec3::ONE)
    }
}

/// A DMF of the density value: `d ↦ f(d)`, possibly depending on the point x
/// (after the warps) and on the object D (the fur projects onto it). Every
/// value DMF maps 0 to 0, so the chain stops at the first 0.
pub trait ValueDmf: Sized {
    /// The DMF described by `desc` (`None`: another DMF's description).
    fn from_desc(desc: &DmfDesc, step: f32) -> Option<Self>;

    /// f(d) at x: the scalar reference.
    fn apply(&self, d: f32, x: Vec3, object: &impl InnerSurface, field: &Field) -> f32;

    /// f(d) at x with its gradient.
    fn apply_dual(&self, d: Dual, x: &DualPoint, object: &impl InnerSurface, field: &Field)
    -> Dual;

    /// f at each lane, inlined into a SIMD path's copy: implementations are
    /// `#[inline(always)]`. Only the lanes whose bit is set in `live` are
    /// used: the others may come out as anything (a noise kernel skips a
    /// register's worth of them).
    fn apply_lanes(
        &self,
        d: &Lanes,
        x: &Points,
        object: &impl InnerSurface,
        field: &Field,
        isa: Isa,
        live: u32,
    ) -> Lanes;
}

/// What a value DMF reads of the object D it modulates: the point x
/// projected onto D's inner (D = 1) surface, where the fur grows from (only
/// primitives project: checked at load for every DMF that needs it). The
/// density tree implements it.
pub trait InnerSurface {
    /// x projected perpendicularly onto the inner surface.
    fn project(&self, x: Vec3) -> Vec3;

    /// [`InnerSurface::project`] with its Jacobian.
    fn project_dual(&self, x: &DualPoint) -> DualPoint;

    /// [`InnerSurface::project`] at the lanes set in `live` (bit l for lane
    /// l), in place; the other points are left.
    fn project_lanes_in_place(&self, x: &mut Points, live: u32);
}

/// Which lanes' D is settled, for [`WarpDmf::apply_lanes`].
pub trait Settling {
    /// The lanes (a bit mask) whose D is the same for every scale factor s
    /// in `[lo, hi]`, lane by lane.
    fn settled(&self, lo: &Lanes, hi: &Lanes) -> u32;
}

/// No lane is ever settled: w at every lane.
pub struct Unsettled;

impl Settling for Unsettled {
    #[inline(always)]
    fn settled(&self, _: &Lanes, _: &Lanes) -> u32 {
        0
    }
}

/// A bound on |Σ noise(·)/w_j| over `count` octaves of weights w, 2w, 4w, …:
/// [`NOISE_BOUND`] per octave, widened by 0.1% for the sum's rounding.
fn octaves_bound(w: f32, count: u32) -> f32 {
    let (mut bound, mut w) = (0.0, w);
    for _ in 0..count {
        bound += NOISE_BOUND / w;
        w *= 2.0;
    }
    bound * 1.001
}

/// [`octaves_bound`] of the octaves from each one on, of `octaves`
/// weighted w, 2w, 4w, …: how far a sum can still move after each octave,
/// found once per scene rather than at every sample.
pub(super) fn bounds_left(w: f32, octaves: u32) -> [f32; Octaves::MOST] {
    let mut left = [0.0; Octaves::MOST];
    let mut w = w;
    for (octave, bound) in (0..octaves).zip(&mut left) {
        *bound = octaves_bound(w, octaves - octave);
        w *= 2.0;
    }
    left
}

/// The registry of warps: `Variant(Type)`, one line each. Builds the enum
/// [`Warp`] and its dispatch, with the attributes the hot paths rely on.
macro_rules! warps {
    ($($(#[$doc:meta])* $name:ident($ty:ty),)*) => {
        /// A position-dependent DMF: where D is evaluated.
        #[derive(Clone, Copy, Debug, PartialEq)]
        pub enum Warp {
            $($(#[$doc])* $name($ty),)*
        }

        impl Warp {
            /// The warp described by `desc`, if it is one.
            pub(crate) fn from_desc(desc: &DmfDesc, step: f32) -> Option<Warp> {
                $(if let Some(w) = <$ty as WarpDmf>::from_desc(desc, step) {
                    return Some(Warp::$name(w));
                })*
                None
            }

            /// [`WarpDmf::apply`].
            #[inline]
            pub(crate) fn apply(&self, x: Vec3, field: &Field) -> Vec3 {
                match self {
                    $(Warp::$name(w) => <$ty as WarpDmf>::apply(w, x, field),)*
                }
            }

            /// [`WarpDmf::apply_dual`].
            pub(crate) fn apply_dual(&self, x: &DualPoint, field: &Field) -> DualPoint {
                match self {
                    $(Warp::$name(w) => <$ty as WarpDmf>::apply_dual(w, x, field),)*
                }
            }

            /// [`WarpDmf::apply_lanes`] with no lane settled: w at every lane.
            #[inline(always)]
            pub(crate) fn apply_lanes(&self, x: &Points, field: &Field, isa: Isa) -> Points {
                self.apply_lanes_settling(x, field, isa, &Unsettled)
            }

            /// [`WarpDmf::apply_lanes`].
            #[inline(always)]
            pub(crate) fn apply_lanes_settling(
                &self,
                x: &Points,
                field: &Field,
                isa: Isa,
                settled: &impl Settling,
            ) -> Points {
                match self {
                    $(Warp::$name(w) => <$ty as WarpDmf>::apply_lanes(w, x, field, isa, settled),)*
                }
            }

            /// [`WarpDmf::scale_range`].
            pub(crate) fn scale_range(&self) -> Option<(Vec3, f32, f32)> {
                match self {
                    $(Warp::$name(w) => <$ty as WarpDmf>::scale_range(w),)*
                }
            }

            /// [`WarpDmf::preimage`].
            pub(crate) fn preimage(&self, b: Aabb) -> Option<Aabb> {
                match self {
                    $(Warp::$name(w) => <$ty as WarpDmf>::preimage(w, b),)*
                }
            }
        }
    };
}

/// The registry of value DMFs: `Variant(Type)`, one line each. Builds the
/// enum [`Modulation`] and its dispatch.
macro_rules! modulations {
    ($($(#[$doc:meta])* $name:ident($ty:ty),)*) => {
        /// A DMF of the density value (position-independent or geometry-dependent).
        #[derive(Clone, Copy, Debug, PartialEq)]
        pub enum Modulation {
            $($(#[$doc])* $name($ty),)*
        }

        impl Modulation {
            /// The value DMF described by `desc`, if it is one.
            pub(crate) fn from_desc(desc: &DmfDesc, step: f32) -> Option<Modulation> {
                $(if let Some(m) = <$ty as ValueDmf>::from_desc(desc, step) {
                    return Some(Modulation::$name(m));
                })*
                None
            }

            /// [`ValueDmf::apply`].
            #[inline]
            pub(crate) fn apply(
                &self,
                d: f32,
                x: Vec3,
                object: &impl InnerSurface,
                field: &Field,
            ) -> f32 {
                match self {
                    $(Modulation::$name(m) => <$ty as ValueDmf>::apply(m, d, x, object, field),)*
                }
            }

            /// [`ValueDmf::apply_dual`].
            pub(crate) fn apply_dual(
                &self,
                d: Dual,
                x: &DualPoint,
                object: &impl InnerSurface,
                field: &Field,
            ) -> Dual {
                match self {
                    $(Modulation::$name(m) => <$ty as ValueDmf>::apply_dual(m, d, x, object, field),)*
                }
            }

            /// [`ValueDmf::apply_lanes`].
            #[inline(always)]
            pub(crate) fn apply_lanes(
                &self,
                d: &Lanes,
                x: &Points,
                object: &impl InnerSurface,
                field: &Field,
                isa: Isa,
                live: u32,
            ) -> Lanes {
                match self {
                    $(Modulation::$name(m) => <$ty as ValueDmf>::apply_lanes(m, d, x, object, field, isa, live),)*
                }
            }
        }
    };
}

warps! {
    /// `c + (x − c)(1 + a · noise(f x))`.
    NoisyRadius(NoisyRadius),
    /// `c + (x − c)(1 + a · Σ noise(2^i f x) / (2^i f))`.
    FractalRadius(FractalRadius),
    /// Material hanging down in drips below the centre.
    Dripping(Dripping),
    /// `c + (x − c)(1 + a · turbulence(f x))`.
    TurbulentRadius(TurbulentRadius),
}

modulations! {
    /// `bias_b(d)`.
    Bias(crate::field::shaping::Bias),
    /// `gain_g(d)`.
    Gain(crate::field::shaping::Gain),
    /// The paper's fur.
    Fur(Fur),
}

/// A DMF of either kind, as the scene lists them.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Dmf {
    /// Applied to x before D is evaluated.
    Warp(Warp),
    /// Applied to the density.
    Value(Modulation),
}

impl Dmf {
    /// The DMF of `desc`; `step` is the marching step (frequency clamping).
    ///
    /// # Panics
    /// When a [`DmfDesc`] variant has no DMF registered above (a programming
    /// error that the every-DMF test catches).
    pub fn build(desc: &DmfDesc, step: f32) -> Dmf {
        Warp::from_desc(desc, step)
            .map(Dmf::Warp)
            .or_else(|| Modulation::from_desc(desc, step).map(Dmf::Value))
            .expect("every DmfDesc variant has a DMF registered in density::dmf")
    }
}

#[cfg(test)]
mod tests;
