//! Gilet & Dischler's hypertexture model (CGF 2009, section 4): a space distortion
//! controlled by shape transfer functions and an explicit vector field.
//!
//! The object O is evaluated at a shifted point (formula 3)
//!
//! `O(x − k · V(x)/|V(x)|)`, where V = 0 means no shift,
//!
//! with the distortion factor k combined step by step from n noise terms
//! (formulas 4 and 5, and 6 for a 2D transfer function)
//!
//! `k = ⊕_i a_i · T_i[(1 + noise((x + r_i V) · f_i)) / 2 (, O(x))]`.
//!
//! The paper writes the noise argument as `(x + rV)/f` but says the greater f, the
//! smaller and more numerous the features: f is a frequency, so we multiply.
//! T returns a value in [0, 1], so |k| is bounded by the amplitudes
//! ([`Distortion::max_displacement`]) and the object can reach no further than that
//! beyond its own support (no further at all with the boundary field, which always
//! points into the object).

use glam::Vec3;

use crate::desc::distortion::{
    DistortionDesc, GridDesc, Operator, TransferDesc, VectorFieldDesc, transfer_range,
};
use crate::field::curve::Curve;
use crate::field::domain::{Field, Points};
use crate::field::shaping::clamp01;
use crate::field::soft::Primitive;
use crate::math::simd::{Isa, LANES};

/// Our gradient noise never leaves [−0.65, 0.65] and 99.8 % of it lies within
/// ±0.5, while the paper's noise spans [−1, 1] (its Figure 3 histogram): the
/// transfer function is indexed by `(1 + NOISE_GAIN · noise) / 2`, clamped, so
/// that its ends are reached now and then (holes and craters at the extremes).
pub const NOISE_GAIN: f32 = 2.0;

/// A shape transfer function T (1D) or T2D, values in [0, 1].
#[derive(Clone, Debug, PartialEq)]
pub enum Transfer {
    /// `T[t]` through control points, clamped to [0, 1].
    Curve(Curve<1>),
    /// T2D[t, O(x)], bilinear over a grid.
    Grid {
        /// Values per row.
        columns: usize,
        /// Rows.
        rows: usize,
        /// Row-major values.
        values: Vec<f32>,
    },
}

impl Transfer {
    /// Builds T from its description.
    pub fn build(desc: &TransferDesc) -> Transfer {
        match desc {
            TransferDesc::Curve(c) => Transfer::Curve(Curve::scalars(c)),
            TransferDesc::Grid(GridDesc {
                columns,
                rows,
                values,
            }) => Transfer::Grid {
                columns: *columns,
                rows: *rows,
                values: values.clone(),
            },
        }
    }

    /// Whether T reads the object density (a 2D transfer function).
    pub fn is_2d(&self) -> bool {
        matches!(self, Transfer::Grid { .. })
    }

    /// T at noise index `t` and object density `o` (both in [0, 1]; `o` is
    /// ignored by a 1D function).
    #[inline(always)]
    pub fn eval(&self, t: f32, o: f32) -> f32 {
        match self {
            Transfer::Curve(c) => clamp01(c.eval1(t)),
            Transfer::Grid {
                columns,
                rows,
                values,
            } => {
                let (c, r) = (*columns, *rows);
                let u = clamp01(t) * (c - 1) as f32;
                let v = clamp01(o) * (r - 1) as f32;
                let (i, j) = ((u as usize).min(c - 2), (v as usize).min(r - 2));
                let (fu, fv) = (u - i as f32, v - j as f32);
                let at = |i: usize, j: usize| values[j * c + i];
                let bottom = at(i, j) + (at(i + 1, j) - at(i, j)) * fu;
                let top = at(i, j + 1) + (at(i + 1, j + 1) - at(i, j + 1)) * fu;
                bottom + (top - bottom) * fv
            }
        }
    }
}

/// The vector field V (section 4.3, Figure 8).
///
/// On a sphere, box or torus every field is a direction `u(x)` carried as far as
/// the object's outer (D = 0) surface, `V = û · (distance from x to the boundary
/// along û)`, so that `x + V` lies on the boundary: with r = 1 the noise is the
/// same all along a field line and features follow the field (peaks along radii,
/// straight up, or curling). Outside the object V = 0: nothing moves, so density
/// never reaches beyond the object. On other objects only `Constant` (perhaps
/// `Perturbed`) is allowed and V is the field's vector as it stands.
#[derive(Clone, Debug, PartialEq)]
pub enum VectorField {
    /// Towards the nearest point of the object's outer surface.
    Boundary,
    /// Away from a centre c.
    Radial {
        /// The centre c.
        centre: Vec3,
    },
    /// A constant direction.
    Constant(Vec3),
    /// Towards the nearest boundary point plus `twist · axis × (x − c)`.
    Curl {
        /// A point of the axis.
        centre: Vec3,
        /// Unit axis.
        axis: Vec3,
        /// Swirl strength.
        twist: f32,
    },
    /// Another field's direction plus `amplitude · vnoise(frequency · x)`.
    Perturbed {
        /// The field perturbed.
        field: Box<VectorField>,
        /// Amplitude of the vector noise.
        amplitude: f32,
        /// Its frequency.
        frequency: f32,
    },
}

impl VectorField {
    /// Builds V from its description.
    pub fn build(desc: &VectorFieldDesc) -> VectorField {
        match desc {
            VectorFieldDesc::Boundary => VectorField::Boundary,
            VectorFieldDesc::Radial { centre } => VectorField::Radial { centre: centre.0 },
            VectorFieldDesc::Constant(v) => VectorField::Constant(v.0),
            VectorFieldDesc::Curl {
                centre,
                axis,
                twist,
            } => VectorField::Curl {
                centre: centre.0,
                axis: axis.0,
                twist: twist.0,
            },
            VectorFieldDesc::Perturbed {
                field,
                amplitude,
                frequency,
            } => VectorField::Perturbed {
                field: Box::new(VectorField::build(field)),
                amplitude: amplitude.0,
                frequency: frequency.0,
            },
        }
    }

    /// The (unnormalised) direction of the field at x.
    #[inline(always)]
    fn direction(&self, x: Vec3, object: Option<Primitive>, field: &Field) -> Vec3 {
        match self {
            VectorField::Boundary => object.map_or(x, |p| p.boundary_point(x)) - x,
            VectorField::Radial { centre } => x - *centre,
            VectorField::Constant(v) => *v,
            VectorField::Curl {
                centre,
                axis,
                twist,
            } => {
                let to = object.map_or(x, |p| p.boundary_point(x)) - x;
                let swirl = axis.cross(x - *centre) * *twist;
                // The swirl scaled like the way out, so it turns the field everywhere.
                to + swirl * to.length()
            }
            VectorField::Perturbed {
                field: inner,
                amplitude,
                frequency,
            } => {
                let u = inner.direction(x, object, field);
                let len2 = u.length_squared();
                let u = if len2 > 1e-20 { u / len2.sqrt() } else { u };
                u + field.noise.vnoise((x - field.offset) * *frequency) * *amplitude
            }
        }
    }

    /// V(x) for `object`, the primitive O is, if it is one (fields other than
    /// `Constant` were checked at load to have a primitive object).
    #[inline(always)]
    pub fn at(&self, x: Vec3, object: Option<Primitive>, field: &Field) -> Vec3 {
        if let VectorField::Boundary = self {
            return object.map_or(Vec3::ZERO, |p| p.boundary_point(x) - x);
        }
        let v = self.direction(x, object, field);
        let len2 = v.length_squared();
        if len2 <= 1e-20 {
            return Vec3::ZERO;
        }
        let u = v / len2.sqrt();
        // Not a primitive (only `Constant`, perturbed or not, passes the load
        // check): the vector as the field gives it.
        object.map_or(v, |p| u * p.exit_distance(x, u))
    }
}

/// The object O of formula 3 as the distortion reads it: the soft primitive
/// whose outer surface the vector field follows, if O is one, and O(x), which
/// a 2D transfer function reads. The density tree implements it.
pub trait Object {
    /// The soft primitive O is, or `None` for any other object.
    fn primitive(&self) -> Option<Primitive<'_>>;

    /// O(x).
    fn density(&self, x: Vec3, field: &Field) -> f32;
}

/// One noise term of formula 5.
#[derive(Clone, Debug, PartialEq)]
pub struct Term {
    /// a.
    pub amplitude: f32,
    /// f.
    pub frequency: f32,
    /// r.
    pub shift: f32,
    /// T or T2D.
    pub transfer: Transfer,
    /// ⊕.
    pub operator: Operator,
}

/// The distortion of formula 3 with its terms (only the enabled ones).
#[derive(Clone, Debug, PartialEq)]
pub struct Distortion {
    /// V.
    field: VectorField,
    /// The enabled terms, in order.
    terms: Vec<Term>,
    /// Whether any term reads O(x) (a 2D transfer function).
    needs_density: bool,
    /// `max |k|`.
    max_displacement: f32,
}

impl Distortion {
    /// Builds the distortion from its (checked) description.
    pub fn build(desc: &DistortionDesc) -> Distortion {
        let enabled: Vec<_> = desc.terms.iter().filter(|t| t.enabled).collect();
        let terms: Vec<Term> = enabled
            .iter()
            .map(|t| Term {
                amplitude: t.amplitude.0,
                frequency: t.frequency.0,
                shift: t.shift.0,
                transfer: Transfer::build(&t.transfer),
                operator: t.operator,
            })
            .collect();
        let ranges: Vec<(f32, f32, Operator)> = enabled
            .iter()
            .map(|t| {
                let (lo, hi) = transfer_range(&t.transfer);
                (t.amplitude.0 * lo, t.amplitude.0 * hi, t.operator)
            })
            .collect();
        Distortion {
            field: VectorField::build(&desc.field),
            needs_density: terms.iter().any(|t| t.transfer.is_2d()),
            terms,
            max_displacement: k_bound(&ranges),
        }
    }

    /// The largest distance |k| a point can be shifted: density can reach at most
    /// this far beyond the undistorted object.
    pub fn max_displacement(&self) -> f32 {
        self.max_displacement
    }

    /// The distortion factor k at x, given V(x) and the object density O(x).
    #[inline]
    pub fn factor(&self, x: Vec3, v: Vec3, o: f32, field: &Field) -> f32 {
        let mut k = 0.0f32;
        for term in &self.terms {
            let q = (x + v * term.shift - field.offset) * term.frequency;
            let t = clamp01(0.5 * (1.0 + NOISE_GAIN * field.noise.noise(q)));
            let value = term.amplitude * term.transfer.eval(t, o);
            k = combine(term.operator, k, value);
        }
        k
    }

    /// The point at which the object is evaluated instead of x:
    /// `x − k · V/|V|` (x itself where V = 0).
    #[inline]
    pub fn apply(&self, x: Vec3, object: &impl Object, field: &Field) -> Vec3 {
        let v = self.field.at(x, object.primitive(), field);
        let len2 = v.length_squared();
        if len2 <= 1e-20 {
            return x;
        }
        let o = if self.needs_density {
            object.density(x, field)
        } else {
            0.0
        };
        let k = self.factor(x, v, o, field);
        if k == 0.0 {
            return x;
        }
        x - v * (k / len2.sqrt())
    }
}

impl Distortion {
    /// [`Distortion::apply`] at [`LANES`] points on a SIMD path `isa`: V, O
    /// and the transfer functions lane by lane, each term's noise a batch
    /// at a time in the lane kernel (the bits of `noise`, at the lanes where
    /// V ≠ 0 only). Inlined into the per-instruction-set copies of the
    /// density's lane code.
    #[inline(always)]
    pub(crate) fn apply_lanes(
        &self,
        x: &Points,
        object: &impl Object,
        field: &Field,
        isa: Isa,
    ) -> Points {
        let primitive = object.primitive();
        let mut v = Points::default();
        // A mesh's boundary points from its field a register at a time.
        let boundary = match (&self.field, primitive) {
            (VectorField::Boundary, Some(Primitive::Mesh(m))) => Some(m.boundary_point_lanes(x)),
            _ => None,
        };
        let mut len2 = [0.0f32; LANES];
        let mut live = 0u32;
        for (l, len2) in len2.iter_mut().enumerate() {
            // `VectorField::at`.
            let vl = match &boundary {
                Some(b) => b.get(l) - x.get(l),
                None => self.field.at(x.get(l), primitive, field),
            };
            v.set(l, vl);
            *len2 = vl.length_squared();
            // As `apply`: a lane goes on unless `len2 <= 1e-20` (NaN too).
            live |= u32::from(*len2 > 1e-20 || len2.is_nan()) << l;
        }
        if live == 0 {
            return *x;
        }
        let mut o = [0.0f32; LANES];
        if self.needs_density {
            for (l, o) in o.iter_mut().enumerate() {
                if live & (1 << l) != 0 {
                    *o = object.density(x.get(l), field);
                }
            }
        }
        let mut k = [0.0f32; LANES];
        for term in &self.terms {
            let q = x.map_with(&v, |x, v| {
                (x + v * term.shift - field.offset) * term.frequency
            });
            let n = field.noise.noise_lanes_live(isa, live, &q.x, &q.y, &q.z);
            for l in 0..LANES {
                let t = clamp01(0.5 * (1.0 + NOISE_GAIN * n[l]));
                let value = term.amplitude * term.transfer.eval(t, o[l]);
                k[l] = combine(term.operator, k[l], value);
            }
        }
        let mut out = *x;
        for l in 0..LANES {
            if live & (1 << l) != 0 && k[l] != 0.0 {
                out.set(l, x.get(l) - v.get(l) * (k[l] / len2[l].sqrt()));
            }
        }
        out
    }
}

/// `k ⊕ v` for one step of formula 5.
#[inline]
pub fn combine(operator: Operator, k: f32, v: f32) -> f32 {
    match operator {
        Operator::Sum => k + v,
        Operator::Blend => k * (1.0 - v) + v,
    }
}

/// `max |k|` over every value the terms can take, by interval arithmetic: a sum
/// adds intervals; a blend `k(1 − v) + v` is bilinear, so its extremes lie at the
/// corners.
fn k_bound(terms: &[(f32, f32, Operator)]) -> f32 {
    let (mut lo, mut hi) = (0.0f32, 0.0f32);
    for &(vlo, vhi, op) in terms {
        match op {
            Operator::Sum => {
                lo += vlo;
                hi += vhi;
            }
            Operator::Blend => {
                let corners = [
                    combine(op, lo, vlo),
                    combine(op, lo, vhi),
                    combine(op, hi, vlo),
                    combine(op, hi, vhi),
                ];
                lo = corners.iter().copied().fold(f32::INFINITY, f32::min);
                hi = corners.iter().copied().fold(f32::NEG_INFINITY, f32::max);
            }
        }
    }
    lo.abs().max(hi.abs())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::desc::{CurveDesc, Fraction, Interpolation};
    use crate::field::density::Density;
    use crate::{Overrides, Scene};

    fn curve(interpolation: Interpolation, points: &[(f32, f32)]) -> Transfer {
        Transfer::build(&TransferDesc::Curve(CurveDesc {
            interpolation,
            points: points.iter().map(|&(k, v)| (k, Fraction(v))).collect(),
        }))
    }

    const HOLES: [(f32, f32); 4] = [(0.0, 0.0), (0.2, 1.0), (0.8, 1.0), (1.0, 0.0)];

    #[test]
    fn transfer_functions_hit_their_control_points() {
        for interpolation in [
            Interpolation::Linear,
            Interpolation::Spline,
            Interpolation::Step,
        ] {
            let t = curve(interpolation, &HOLES);
            for (k, v) in HOLES {
                assert!(
                    (t.eval(k, 0.3) - v).abs() < 1e-6,
                    "{interpolation:?} at {k}"
                );
            }
        }
        // Linear halfway, step holds the left value, spline stays within [0, 1].
        assert_eq!(curve(Interpolation::Linear, &HOLES).eval(0.1, 0.0), 0.5);
        assert_eq!(curve(Interpolation::Step, &HOLES).eval(0.1, 0.0), 0.0);
        let overshoot = curve(
            Interpolation::Spline,
            &[(0.0, 0.0), (0.5, 1.0), (0.6, 1.0), (1.0, 0.0)],
        );
        for i in 0..=100 {
            let v = overshoot.eval(i as f32 / 100.0, 0.0);
            assert!((0.0..=1.0).contains(&v), "{v}");
        }
        // A 2D grid at its nodes and bilinear between them.
        let grid = Transfer::Grid {
            columns: 3,
            rows: 2,
            values: vec![0.0, 0.5, 1.0, 1.0, 0.5, 0.0],
        };
        assert_eq!(grid.eval(0.0, 0.0), 0.0);
        assert_eq!(grid.eval(0.5, 0.0), 0.5);
        assert_eq!(grid.eval(1.0, 0.0), 1.0);
        assert_eq!(grid.eval(0.0, 1.0), 1.0);
        assert_eq!(grid.eval(1.0, 1.0), 0.0);
        assert_eq!(grid.eval(0.25, 0.5), 0.5);
        assert!(grid.is_2d() && !curve(Interpolation::Linear, &HOLES).is_2d());
    }

    #[test]
    fn sum_and_blend_combine_known_values() {
        assert_eq!(combine(Operator::Sum, 0.25, 0.5), 0.75);
        // v1 ⊕ v2 = v1·(1 − v2) + v2.
        assert_eq!(combine(Operator::Blend, 0.25, 0.5), 0.625);
        assert_eq!(combine(Operator::Blend, 0.0, 0.4), 0.4);
        assert_eq!(combine(Operator::Blend, 0.7, 1.0), 1.0);
        assert_eq!(combine(Operator::Blend, 0.7, 0.0), 0.7);
        // Step by step from k = 0 with constant transfer functions: ((0 + 0.2) ⊕ 0.5) + 0.1.
        let constant = |v: f32| curve(Interpolation::Linear, &[(0.0, v)]);
        let d = Distortion {
            field: VectorField::Constant(Vec3::Y),
            terms: vec![
                Term {
                    amplitude: 0.4,
                    frequency: 1.0,
                    shift: 0.0,
                    transfer: constant(0.5),
                    operator: Operator::Sum,
                },
                Term {
                    amplitude: 1.0,
                    frequency: 1.0,
                    shift: 0.0,
                    transfer: constant(0.5),
                    operator: Operator::Blend,
                },
                Term {
                    amplitude: 0.2,
                    frequency: 1.0,
                    shift: 0.0,
                    transfer: constant(0.5),
                    operator: Operator::Sum,
                },
            ],
            needs_density: false,
            max_displacement: 0.0,
        };
        let noise = crate::field::noise::Noise::default();
        let field = Field {
            noise: &noise,
            offset: Vec3::ZERO,
            frame: 0,
            time: 0.0,
            frame_rate: 24.0,
            pose: None,
            support: None,
        };
        let k = d.factor(Vec3::new(0.3, 0.1, 0.7), Vec3::Y, 0.0, &field);
        assert!((k - (0.2 * 0.5 + 0.5 + 0.1)).abs() < 1e-6, "{k}");
        // Interval bounds: sums add, blends take the corners.
        assert_eq!(
            k_bound(&[(0.0, 0.3, Operator::Sum), (0.0, 0.2, Operator::Sum)]),
            0.5
        );
        assert!(
            (k_bound(&[(0.0, 0.5, Operator::Sum), (0.0, 0.5, Operator::Blend)]) - 0.75).abs()
                < 1e-6
        );
        // An amplitude above 1 can make a blend negative: |k| counts.
        assert!(
            (k_bound(&[(0.0, 3.0, Operator::Sum), (0.0, 2.0, Operator::Blend)]) - 3.0).abs() < 1e-6
        );
    }

    fn sphere_scene(distortion: &str) -> Scene {
        let text = format!(
            "Scene(image: (width: 8, height: 8),
              camera: (eye: (0.0, 0.0, 5.0), look_at: (0.0, 0.0, 0.0), projection: Perspective(fov_y: 30.0)),
              march: (bounds: (min: (-2.0, -2.0, -2.0), max: (2.0, 2.0, 2.0)), step: Diagonal(200), opacity: 20.0),
              object: Sphere(radius: 0.5, softness: 1.0),
              distortion: {distortion})"
        );
        Scene::from_text(&text, "test", Overrides::default()).unwrap()
    }

    /// Random points in the ball of radius 2.
    fn probes() -> impl Iterator<Item = Vec3> {
        let mut rng = crate::math::random::SplitMix64::new(6);
        std::iter::repeat_with(move || {
            Vec3::new(rng.next_f32(), rng.next_f32(), rng.next_f32()) * 4.0 - Vec3::splat(2.0)
        })
        .filter(|p| p.length() <= 2.0)
        .take(20_000)
    }

    const HOLES_RON: &str =
        "Curve(interpolation: Spline, points: [(0.0, 0.0), (0.2, 1.0), (0.8, 1.0), (1.0, 0.0)])";

    #[test]
    fn zero_amplitude_leaves_the_object_unchanged() {
        let plain = sphere_scene("None");
        for field in [
            "Boundary",
            "Constant(0.0, 1.0, 0.0)",
            "Perturbed(field: Curl(axis: (0.0, 1.0, 0.0), twist: 2.0), amplitude: 0.5, frequency: 3.0)",
        ] {
            let flat = sphere_scene(&format!(
                "(field: {field}, terms: [(amplitude: 0.0, frequency: 4.0, shift: 0.5, transfer: {HOLES_RON})])"
            ));
            assert_eq!(flat.max_displacement(), 0.0);
            for x in probes() {
                assert_eq!(
                    flat.density_at(x, 0),
                    plain.density_at(x, 0),
                    "{field} at {x:?}"
                );
            }
        }
        // A disabled term is no term at all.
        let off = sphere_scene(&format!(
            "(terms: [(amplitude: 0.5, frequency: 4.0, transfer: {HOLES_RON}, enabled: false)])"
        ));
        for x in probes().take(2000) {
            assert_eq!(off.density_at(x, 0), plain.density_at(x, 0));
        }
    }

    #[test]
    fn the_distortion_stays_within_its_bound() {
        let outer = 1.0; // radius 0.5 + softness / 2
        // Pointing into the object, the boundary field never grows it at all.
        let inward = sphere_scene(&format!(
            "(terms: [(amplitude: 0.4, frequency: 4.0, shift: 0.0, transfer: {HOLES_RON}),
                      (amplitude: 0.3, frequency: 9.0, shift: 1.0, transfer: {HOLES_RON}, operator: Blend)])"
        ));
        assert!(
            (inward.max_displacement() - 0.58).abs() < 1e-5,
            "{}",
            inward.max_displacement()
        );
        let mut changed = 0;
        let plain = sphere_scene("None");
        for x in probes() {
            let d = inward.density_at(x, 0);
            if x.length() >= outer {
                assert_eq!(d, 0.0, "at {x:?}");
            }
            changed += usize::from(d != plain.density_at(x, 0));
        }
        assert!(changed > 1000, "the distortion did something ({changed})");
        // On a primitive no field moves density beyond it.
        for field in [
            "Constant(0.0, 0.3, 0.0)",
            "Perturbed(field: Boundary, amplitude: 1.0, frequency: 2.0)",
            "Radial(centre: (0.0, 0.4, 0.0))",
            "Curl(axis: (0.0, 1.0, 0.0), twist: 3.0)",
        ] {
            let s = sphere_scene(&format!(
                "(field: {field}, terms: [(amplitude: 0.5, frequency: 3.0, shift: 0.5, transfer: {HOLES_RON})])"
            ));
            assert_eq!(s.max_displacement(), 0.5);
            for x in probes() {
                if x.length() >= outer {
                    assert_eq!(s.density_at(x, 0), 0.0, "{field} at {x:?}");
                }
            }
        }
        // A constant vector (perturbed or not) on a compound object carries density
        // out by at most a·max T.
        for field in [
            "Constant(0.0, 0.3, 0.0)",
            "Perturbed(field: Constant(0.0, 0.3, 0.0), amplitude: 0.8, frequency: 2.0)",
        ] {
            let union = union_scene(&format!(
                "(field: {field}, terms: [(amplitude: 0.5, frequency: 3.0, shift: 0.5, transfer: Curve(points: [(0.0, 0.2), (0.5, 0.8), (1.0, 0.1)]))])"
            ));
            let bound = union.max_displacement();
            assert!((bound - 0.4).abs() < 1e-6, "{bound}");
            let mut beyond = 0;
            for x in probes() {
                // Distance beyond the union's support (two spheres of outer radius 0.6).
                let gap = x.length().min((x - Vec3::new(0.5, 0.0, 0.0)).length()) - 0.6;
                let d = union.density_at(x, 0);
                if gap >= bound {
                    assert_eq!(d, 0.0, "{field} at {x:?}");
                } else if gap > 0.0 && d > 0.0 {
                    beyond += 1;
                }
            }
            assert!(beyond > 0, "{field} does carry density outwards");
        }
    }

    fn union_scene(distortion: &str) -> Scene {
        let text = format!(
            "Scene(image: (width: 8, height: 8),
              camera: (eye: (0.0, 0.0, 5.0), look_at: (0.0, 0.0, 0.0), projection: Perspective(fov_y: 30.0)),
              march: (bounds: (min: (-2.0, -2.0, -2.0), max: (2.0, 2.0, 2.0)), step: Diagonal(200), opacity: 20.0),
              object: Union([Sphere(radius: 0.5, softness: 0.2), Sphere(centre: (0.5, 0.0, 0.0), radius: 0.5, softness: 0.2)]),
              distortion: {distortion})"
        );
        Scene::from_text(&text, "test", Overrides::default()).unwrap()
    }

    #[test]
    fn the_lane_paths_give_the_scalar_bits() {
        // Every vector field, a 1D and a 2D transfer function, both
        // operators; on a sphere, a box, a torus and (a constant field) a union.
        let grid = "Grid(rows: [[0.0, 1.0, 0.2], [0.6, 0.0, 1.0]])";
        let cases = [
            "Boundary".to_string(),
            "Radial(centre: (0.1, 0.0, 0.0))".to_string(),
            "Constant(0.0, 0.3, 0.0)".to_string(),
            "Curl(axis: (0.0, 1.0, 0.0), twist: 3.0)".to_string(),
            "Perturbed(field: Boundary, amplitude: 1.0, frequency: 2.0)".to_string(),
        ];
        let objects = [
            "Sphere(radius: 0.5, softness: 1.0)",
            "Box(half_size: (0.6, 0.4, 0.5), softness: 0.5)",
            "Torus(major_radius: 0.8, minor_radius: 0.3, softness: 0.4)",
        ];
        let terms = format!(
            "[(amplitude: 0.4, frequency: 4.0, shift: 0.5, transfer: {HOLES_RON}),
              (amplitude: 0.3, frequency: 9.0, shift: 1.0, transfer: {grid}, operator: Blend)]"
        );
        let mut scenes = Vec::new();
        for object in objects {
            for field in &cases {
                scenes.push(object_scene(
                    object,
                    &format!("(field: {field}, terms: {terms})"),
                ));
            }
        }
        scenes.push(union_scene(&format!(
            "(field: Constant(0.0, 0.3, 0.0), terms: {terms})"
        )));
        let points: Vec<Vec3> = probes().take(LANES * 64).collect();
        for scene in &scenes {
            let field = scene.field(0);
            let Density::Hypertexture(h) = &scene.density else {
                panic!("a distorted object is a hypertexture")
            };
            let d = h.distortion().expect("the scene has a distortion");
            let mut moved = 0;
            for chunk in points.chunks(LANES) {
                let mut x = Points::default();
                for (l, &p) in chunk.iter().enumerate() {
                    x.set(l, p);
                }
                let scalar = x.map(|p| d.apply(p, h.object(), &field));
                moved += (0..LANES).filter(|&l| scalar.get(l) != x.get(l)).count();
                for isa in Isa::available().into_iter().filter(|&i| i != Isa::Scalar) {
                    let lanes = lanes_on(d, &x, h.object(), &field, isa);
                    for l in 0..LANES {
                        assert_eq!(
                            lanes.get(l).to_array().map(f32::to_bits),
                            scalar.get(l).to_array().map(f32::to_bits),
                            "{} at {:?}",
                            isa.name(),
                            x.get(l)
                        );
                    }
                }
            }
            assert!(moved > 20, "the distortion moves points ({moved})");
        }
    }

    /// [`Distortion::apply_lanes`] compiled for `isa`, as the density's
    /// lane code inlines it.
    fn lanes_on(d: &Distortion, x: &Points, object: &Density, field: &Field, isa: Isa) -> Points {
        crate::math::simd::per_isa!(isa, (
            d: &Distortion = d, x: &Points = x, o: &Density = object, f: &Field = field,
        ) -> Points {
            scalar => x.map(|p| d.apply(p, o, f)),
            lanes => d.apply_lanes(x, o, f, lanes),
        })
    }

    fn object_scene(object: &str, distortion: &str) -> Scene {
        let text = format!(
            "Scene(image: (width: 8, height: 8),
              camera: (eye: (0.0, 0.0, 5.0), look_at: (0.0, 0.0, 0.0), projection: Perspective(fov_y: 30.0)),
              march: (bounds: (min: (-2.0, -2.0, -2.0), max: (2.0, 2.0, 2.0)), step: Diagonal(200), opacity: 20.0),
              object: {object},
              distortion: {distortion})"
        );
        Scene::from_text(&text, "test", Overrides::default()).unwrap()
    }

    #[test]
    fn fields_towards_the_boundary_need_a_primitive() {
        let text = "Scene(image: (width: 8, height: 8),
              camera: (eye: (0.0, 0.0, 5.0), look_at: (0.0, 0.0, 0.0), projection: Perspective(fov_y: 30.0)),
              march: (bounds: (min: (-2.0, -2.0, -2.0), max: (2.0, 2.0, 2.0)), step: Diagonal(200), opacity: 20.0),
              object: Union([Sphere(radius: 0.5, softness: 0.2), Sphere(centre: (0.5, 0.0, 0.0), radius: 0.5, softness: 0.2)]),
              distortion: (terms: [(amplitude: 0.2, frequency: 3.0, transfer: Curve(points: [(0.0, 1.0)]))]))";
        let err = Scene::from_text(text, "t.ron", Overrides::default())
            .unwrap_err()
            .to_string();
        assert!(err.contains("Sphere, Box, Torus or Mesh"), "{err}");
        let ok = text.replace("(terms:", "(field: Constant(0.0, 1.0, 0.0), terms:");
        assert!(Scene::from_text(&ok, "t.ron", Overrides::default()).is_ok());
        let bad_grid = text.replace(
            "Curve(points: [(0.0, 1.0)])",
            "Grid(rows: [[0.0, 1.0], [0.5]])",
        );
        let err = Scene::from_text(&bad_grid, "t.ron", Overrides::default())
            .unwrap_err()
            .to_string();
        assert!(
            err.contains("t.ron:") && err.contains("row 1 has 1 values"),
            "{err}"
        );
        let bad_value = text.replace("(0.0, 1.0)]", "(0.0, 1.5)]");
        let err = Scene::from_text(&bad_value, "t.ron", Overrides::default())
            .unwrap_err()
            .to_string();
        assert!(err.contains("[0, 1]"), "{err}");
    }

    #[test]
    fn noise_gain_reaches_the_ends_of_the_transfer_function() {
        // The paper's noise spans [−1, 1]; ours, scaled by NOISE_GAIN, should reach
        // both ends of T now and then, but mostly stay inside.
        let noise = crate::field::noise::Noise::default();
        let (mut low, mut high, n) = (0, 0, 100_000);
        for i in 0..n {
            let t = i as f32;
            let p = Vec3::new(t * 0.0731, t * 0.0413 + 0.5, t * 0.0177 + 0.25);
            let v = 0.5 * (1.0 + NOISE_GAIN * noise.noise(p));
            low += usize::from(v <= 0.05);
            high += usize::from(v >= 0.95);
        }
        for tail in [low, high] {
            assert!(tail > n / 1000 && tail < n / 10, "{low} {high}");
        }
    }
}
