//! The hypertexture H(D(x), x): the object density tree with its density
//! modulation functions, built from the scene description.
//!
//! Evaluation is infallible and allocation-free: everything that can go wrong was
//! checked when the scene was loaded, and every constant (bias exponents, clamped
//! octave counts, squared radii) was computed then.

//!
//! - `mod.rs` (here): the tree [`Density`] and [`Hypertexture`], and the
//!   scalar evaluation, the reference every other path reproduces, at a point
//!   and a moment of [`crate::field::domain`].
//! - [`dmf`]: the density modulation functions, one file each, with all their
//!   forms (scalar, dual, lanes, bounds) side by side.
//! - [`lanes`]: [`Density::eval_lanes`], [`crate::math::simd::LANES`] points at once, with
//!   the one `#[target_feature]` copy per instruction set.
//! - [`dual`]: [`Density::eval_dual`], the density with its gradient.
//! - [`bounds`]: [`Density::support`], [`Density::support_ball`], where the
//!   density can be non-zero, and how far a distortion carries it.

use glam::Vec3;

use crate::desc::{DmfDesc, HardCore, ObjectDesc};
use crate::field::distortion::{self, Distortion};
use crate::field::domain::{Aabb, Field, Points};
use crate::field::soft::{Falloff, Primitive, SoftBox, SoftMesh, SoftSphere, SoftTorus, boolean};
use crate::math::dual::DualPoint;
use crate::math::simd::{Isa, Lanes};

pub mod bounds;
pub mod dmf;
pub mod dual;
pub mod lanes;

use dmf::{Dmf, InnerSurface, Modulation, Warp};

/// A node of the object density tree.
#[derive(Clone, Debug, PartialEq)]
pub enum Density {
    /// A soft sphere.
    Sphere(SoftSphere),
    /// A soft box.
    Box(SoftBox),
    /// A soft torus.
    Torus(SoftTorus),
    /// A closed triangle mesh, soft outside its surface.
    Mesh(SoftMesh),
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
    Expression(Box<dyn Expression>),
    /// The scene's hypertexture on a moving object: evaluated at the
    /// object-space point of the field's pose (the root of a moving scene only).
    Moving(Box<Density>),
}

/// What the density tree asks of a density written as an expression: the
/// Pixel Stream Editor's compiled programs implement it (`pse::density`), so
/// the tree holds them without depending on the language above it.
pub trait Expression: std::fmt::Debug + Send + Sync {
    /// The value at x, with `d` the density the expression reads as `D`.
    fn eval_scalar(&self, x: Vec3, d: f32, field: &Field) -> f32;
    /// The value (its three components) at each lane's point.
    fn eval_lanes(&self, x: &Points, d: &Lanes, field: &Field, isa: Isa) -> [Lanes; 3];
    /// A box outside which the value is 0, if the expression shows one.
    fn support(&self) -> Option<Aabb>;
    /// A ball outside which the value is 0, if the expression shows one.
    fn support_ball(&self) -> Option<(Vec3, f32)>;
    /// A copy in a box.
    fn clone_box(&self) -> Box<dyn Expression>;
    /// Whether `other` is the same expression.
    fn same_as(&self, other: &dyn Expression) -> bool;
    /// The expression as `Any`, to compare with another of its type.
    fn as_any(&self) -> &dyn std::any::Any;
}

impl Clone for Box<dyn Expression> {
    fn clone(&self) -> Self {
        self.clone_box()
    }
}

impl PartialEq for dyn Expression {
    fn eq(&self, other: &dyn Expression) -> bool {
        self.same_as(other)
    }
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
            ObjectDesc::Mesh(m) => match &m.mesh {
                Some(mesh) => Density::Mesh(SoftMesh::from_desc(std::sync::Arc::clone(mesh), m)),
                // Not attached (`SceneDesc::attach_meshes`): nothing, as a
                // union of no objects. `Scene::from_text` always attaches.
                None => Density::Union(Vec::new()),
            },
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
                    .with_hard_core(h.hard_core)
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
            Density::Mesh(m) => m.density(x),
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
            Density::Expression(p) => crate::field::shaping::clamp01(p.eval_scalar(x, 0.0, field)),
            Density::Moving(d) => d.eval(field.object_point(x), field),
        }
    }

    /// The density with every hypertexture's value DMFs left out (warps and
    /// distortions kept): the objects' own D, in [0, 1]. Its gradient is the
    /// normal where a ray reaches a hard region, where f = 1 and ∇f = 0.
    pub fn eval_object(&self, x: Vec3, field: &Field) -> f32 {
        match self {
            Density::Union(v) => v
                .iter()
                .fold(0.0, |a, d| boolean::union(a, d.eval_object(x, field))),
            Density::Intersection(v) => v.iter().fold(1.0, |a, d| {
                boolean::intersection(a, d.eval_object(x, field))
            }),
            Density::Difference(a, b) => {
                boolean::difference(a.eval_object(x, field), b.eval_object(x, field))
            }
            Density::Complement(a) => boolean::complement(a.eval_object(x, field)),
            Density::Max(v) => v.iter().fold(0.0, |a, d| a.max(d.eval_object(x, field))),
            Density::Min(v) => v.iter().fold(1.0, |a, d| a.min(d.eval_object(x, field))),
            Density::Hypertexture(h) => h.eval_object(x, field),
            Density::Moving(d) => d.eval_object(field.object_point(x), field),
            Density::Sphere(_)
            | Density::Box(_)
            | Density::Torus(_)
            | Density::Mesh(_)
            | Density::Expression(_) => self.eval(x, field),
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
            Density::Mesh(m) => m.project(x),
            _ => x,
        }
    }

    /// Whether `Density::project` (the fur's projection onto the inner surface) is
    /// defined for this node.
    pub fn can_project(desc: &ObjectDesc) -> bool {
        desc.is_primitive()
    }
}

/// The object O a distortion shifts: a soft primitive's outer surface for
/// its vector field, and the density.
impl distortion::Object for Density {
    #[inline(always)]
    fn primitive(&self) -> Option<Primitive<'_>> {
        match self {
            Density::Sphere(s) => Some(Primitive::Sphere(s)),
            Density::Box(b) => Some(Primitive::Box(b)),
            Density::Torus(t) => Some(Primitive::Torus(t)),
            Density::Mesh(m) => Some(Primitive::Mesh(m)),
            _ => None,
        }
    }

    #[inline(always)]
    fn density(&self, x: Vec3, field: &Field) -> f32 {
        self.eval(x, field)
    }
}

/// The object D a value DMF reads: the projection onto its inner surface
/// ([`Density::project`] in every form).
impl InnerSurface for Density {
    #[inline(always)]
    fn project(&self, x: Vec3) -> Vec3 {
        Density::project(self, x)
    }

    #[inline(always)]
    fn project_dual(&self, x: &DualPoint) -> DualPoint {
        Density::project_dual(self, x)
    }

    #[inline(always)]
    fn project_lanes_in_place(&self, x: &mut Points, live: u32) {
        Density::project_lanes_in_place(self, x, live)
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
    /// Whether the hard region (D = 1) stays solid, f = 1 ([`HardCore::Solid`]):
    /// the value DMFs then shape only the soft region.
    solid_core: bool,
    /// Whether the object is a sphere under one warp that scales about its
    /// centre, whose lanes can settle as the octaves go (see `lanes.rs`).
    settles: bool,
    /// Whether H is 0 at every point in a slot of the object's distance
    /// field beyond its band ([`Hypertexture::empty_at`]).
    empty_beyond: bool,
}

impl Hypertexture {
    /// Builds the DMF chain around `object` (the order was validated at load).
    pub fn build(object: Density, dmfs: &[DmfDesc], step: f32) -> Hypertexture {
        let mut warps = Vec::new();
        let mut modulation = Vec::new();
        for dmf in dmfs {
            match Dmf::build(dmf, step) {
                Dmf::Warp(w) => warps.push(w),
                Dmf::Value(m) => modulation.push(m),
            }
        }
        let settles = match (warps.as_slice(), &object) {
            ([w], Density::Sphere(sphere)) => {
                w.scale_range().is_some_and(|(c, _, _)| c == sphere.centre)
            }
            _ => false,
        };
        Hypertexture {
            object,
            warps,
            modulation,
            distortion: None,
            solid_core: true,
            settles,
            empty_beyond: false,
        }
        .with_empty_space()
    }

    /// The chain with [`Hypertexture::empty_beyond`] found: the object is a
    /// mesh read from a distance field, no warp moves x, and the field
    /// reaches past the distortion's largest displacement (so that D is 0
    /// within it of any point beyond the band, and the distortion's vector
    /// there moves nothing that matters: [`SoftMesh::covering`]).
    fn with_empty_space(mut self) -> Hypertexture {
        let moves = self
            .distortion
            .as_ref()
            .map_or(0.0, Distortion::max_displacement);
        let mesh = match &mut self.object {
            Density::Mesh(m) if self.warps.is_empty() => Some(m),
            _ => None,
        };
        self.empty_beyond = match mesh {
            Some(m) => {
                *m = m.clone().covering(moves);
                m.covers_distortion()
            }
            None => false,
        };
        self
    }

    /// The same chain with the hard region solid or shaped by the DMFs.
    pub fn with_hard_core(self, hard_core: HardCore) -> Hypertexture {
        Hypertexture {
            solid_core: hard_core == HardCore::Solid,
            ..self
        }
    }

    /// Whether the value DMFs leave this `d` = D(w(x)) as it is: 0 always
    /// (every value DMF maps 0 to 0), 1 when the hard region is solid.
    #[inline(always)]
    pub(crate) fn keeps(&self, d: f32) -> bool {
        d == 0.0 || (self.solid_core && d == 1.0)
    }

    /// The same chain with Gilet & Dischler's distortion after the warps.
    pub fn with_distortion(self, distortion: Option<Distortion>) -> Hypertexture {
        Hypertexture { distortion, ..self }.with_empty_space()
    }

    /// Whether H(x) is 0 for certain because x lies in a slot of the mesh's
    /// field wholly beyond its band ([`Hypertexture::empty_beyond`]).
    #[inline(always)]
    fn empty_at(&self, x: Vec3) -> bool {
        match &self.object {
            Density::Mesh(m) if self.empty_beyond => m.beyond(x),
            _ => false,
        }
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
        if self.empty_at(x) {
            return 0.0;
        }
        let mut p = x;
        for w in &self.warps {
            p = w.apply(p, field);
        }
        if let Some(d) = &self.distortion {
            p = d.apply(p, &self.object, field);
        }
        let d = self.object.eval(p, field);
        if self.keeps(d) {
            return d;
        }
        let mut v = d;
        for m in &self.modulation {
            if v == 0.0 {
                break; // every value DMF maps 0 to 0
            }
            v = m.apply(v, p, &self.object, field);
        }
        v
    }

    /// D(w(x)): the object under the warps and the distortion, without the
    /// value DMFs (the object's own density, whose gradient is the normal of
    /// its hard region).
    #[inline]
    pub fn eval_object(&self, x: Vec3, field: &Field) -> f32 {
        if self.empty_at(x) {
            return 0.0;
        }
        let mut p = x;
        for w in &self.warps {
            p = w.apply(p, field);
        }
        if let Some(d) = &self.distortion {
            p = d.apply(p, &self.object, field);
        }
        self.object.eval_object(p, field)
    }
}
