//! Gilet & Dischler's distortion model (CGF 2009, section 4) as written in a scene.
//!
//! ```ron
//! distortion: (
//!     field: Boundary,
//!     terms: [
//!         (amplitude: 0.3, frequency: 4.0, shift: 0.5,
//!          transfer: Curve(interpolation: Spline, points: [(0.0, 0.0), (0.1, 1.0), (0.9, 1.0), (1.0, 0.0)])),
//!     ],
//! )
//! ```
//!
//! Everything is checked while it is read, so a mistake is reported at its line and
//! column; the checks that need the object (a field towards its boundary) run in
//! [`check_distortion`] when the enclosing scene or `Hypertexture` is complete.

use serde::Deserialize;

use super::values::{
    CurveDesc, Direction, Finite, Fraction, Interpolation, NonNegative, Positive, V3,
};

/// The most noise terms of one distortion (the paper's fixed n; they used 3).
pub const MAX_TERMS: usize = 8;
/// The largest side of a 2D shape transfer function grid.
pub const MAX_GRID_SIDE: usize = 64;

/// The space distortion of formula 3, `O(x − k·V/|V|)`, with `k` from formula 5:
/// `k = ⊕ a_i · T_i[(1 + noise((x + r_i V) · f_i)) / 2]`.
#[derive(Clone, Debug, Deserialize, PartialEq)]
#[serde(deny_unknown_fields, try_from = "DistortionFields")]
pub struct DistortionDesc {
    /// The vector field V along which points are shifted.
    pub field: VectorFieldDesc,
    /// The noise terms, combined in order starting from k = 0.
    pub terms: Vec<TermDesc>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields, rename = "Distortion")]
struct DistortionFields {
    #[serde(default)]
    field: VectorFieldDesc,
    terms: Vec<TermDesc>,
}

impl TryFrom<DistortionFields> for DistortionDesc {
    type Error = String;
    fn try_from(f: DistortionFields) -> Result<Self, String> {
        if f.terms.is_empty() || f.terms.len() > MAX_TERMS {
            return Err(format!(
                "distortion: from 1 to {MAX_TERMS} terms, found {}",
                f.terms.len()
            ));
        }
        Ok(DistortionDesc {
            field: f.field,
            terms: f.terms,
        })
    }
}

/// One noise of formula 5: amplitude a_i, frequency f_i, shift r_i, transfer T_i.
#[derive(Clone, Debug, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct TermDesc {
    /// The amplitude a: the depth of the hypertexture (0: no distortion).
    pub amplitude: NonNegative,
    /// The frequency f: the greater, the smaller and more numerous the features.
    pub frequency: Positive,
    /// The shift r in [0, 1]: noise is evaluated at `x + r·V` (1: on the boundary,
    /// like displacement mapping; 0: at x, holes and disconnected pieces).
    #[serde(default)]
    pub shift: Fraction,
    /// The shape transfer function T.
    pub transfer: TransferDesc,
    /// How this term combines with the result of the terms before it.
    #[serde(default)]
    pub operator: Operator,
    /// Whether the term takes part (the paper's check box).
    #[serde(default = "yes")]
    pub enabled: bool,
}

fn yes() -> bool {
    true
}

/// The operators ⊕ of formula 5.
#[derive(Clone, Copy, Debug, Default, Deserialize, PartialEq, Eq)]
pub enum Operator {
    /// `k + v`.
    #[default]
    Sum,
    /// `k ⊕ v = k·(1 − v) + v`: v covers what came before.
    Blend,
}

/// A shape transfer function: a 1D curve over the noise value (formula 4) or a 2D
/// grid over (noise value, object density) (formula 6). Values lie in [0, 1].
#[derive(Clone, Debug, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub enum TransferDesc {
    /// `T[(1 + noise) / 2]` through control points (`Linear`, `Spline` or `Step`).
    Curve(CurveDesc<Fraction>),
    /// `T2D[(1 + noise) / 2, O(x)]`, bilinear between grid values.
    Grid(GridDesc),
}

/// A 2D shape transfer function as a small grid of values in [0, 1]: `rows[j][i]`
/// is T at noise index `i / (columns − 1)` and object density `j / (rows − 1)`, so
/// the first row is the outer edge of the soft region (density 0) and the last
/// the core (density 1).
#[derive(Clone, Debug, Deserialize, PartialEq)]
#[serde(deny_unknown_fields, try_from = "GridFields")]
pub struct GridDesc {
    /// Columns per row (noise index), at least 2.
    pub columns: usize,
    /// Rows (object density), at least 2.
    pub rows: usize,
    /// Row-major values.
    pub values: Vec<f32>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields, rename = "Grid")]
struct GridFields {
    rows: Vec<Vec<Fraction>>,
}

impl TryFrom<GridFields> for GridDesc {
    type Error = String;
    fn try_from(f: GridFields) -> Result<Self, String> {
        let rows = f.rows.len();
        let columns = f.rows.first().map_or(0, Vec::len);
        if !(2..=MAX_GRID_SIDE).contains(&rows) || !(2..=MAX_GRID_SIDE).contains(&columns) {
            return Err(format!(
                "grid: from 2 to {MAX_GRID_SIDE} rows and columns, found {rows} rows of {columns}"
            ));
        }
        if let Some((j, r)) = f.rows.iter().enumerate().find(|(_, r)| r.len() != columns) {
            return Err(format!(
                "grid: row {j} has {} values, row 0 has {columns}",
                r.len()
            ));
        }
        Ok(GridDesc {
            columns,
            rows,
            values: f.rows.into_iter().flatten().map(|v| v.0).collect(),
        })
    }
}

/// The vector field V of formula 3 (section 4.3, Figure 8). On a sphere, box or
/// torus each field gives a direction and V reaches from x along it to the
/// object's outer (D = 0) surface (V = 0 outside the object, so it never grows);
/// with shift r = 1 the noise is then constant along field lines.
#[derive(Clone, Debug, Default, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub enum VectorFieldDesc {
    /// Towards the nearest point of the object's boundary: `V = b(x) − x`.
    /// Sphere, box or torus only.
    #[default]
    Boundary,
    /// Away from a (shifted) centre c. Sphere, box or torus only.
    Radial {
        /// The centre c.
        centre: V3,
    },
    /// One direction everywhere, `Constant(x, y, z)`. On an object that is not a
    /// primitive, V is this vector as written (and the object can grow by up to
    /// the amplitudes).
    Constant(V3),
    /// Towards the nearest boundary point, turned around an axis:
    /// `b(x) − x + twist · |b(x) − x| · axis × (x − c)`. Sphere, box or torus only.
    Curl {
        /// A point of the axis.
        #[serde(default)]
        centre: V3,
        /// The axis direction.
        axis: Direction,
        /// Strength (and sense) of the swirl.
        twist: Finite,
    },
    /// Another field's unit direction plus a vector noise,
    /// `û + amplitude · vnoise(frequency · x)`.
    Perturbed {
        /// The field perturbed.
        field: Box<VectorFieldDesc>,
        /// Amplitude of the vector noise.
        amplitude: NonNegative,
        /// Frequency of the vector noise.
        frequency: Positive,
    },
}

impl VectorFieldDesc {
    /// Whether the field needs the nearest boundary point of its object.
    pub fn needs_boundary(&self) -> bool {
        match self {
            VectorFieldDesc::Boundary
            | VectorFieldDesc::Radial { .. }
            | VectorFieldDesc::Curl { .. } => true,
            VectorFieldDesc::Constant(_) => false,
            VectorFieldDesc::Perturbed { field, .. } => field.needs_boundary(),
        }
    }

    /// How deeply fields are nested (a bound on the recursion at render time).
    fn depth(&self) -> usize {
        match self {
            VectorFieldDesc::Perturbed { field, .. } => 1 + field.depth(),
            _ => 1,
        }
    }
}

/// The deepest nesting of `Perturbed` fields.
pub const MAX_FIELD_DEPTH: usize = 4;

/// Checks a distortion against the object it distorts (whether that is a
/// primitive: a sphere, box, torus or mesh).
pub fn check_distortion(d: &DistortionDesc, object_is_primitive: bool) -> Result<(), String> {
    if d.field.depth() > MAX_FIELD_DEPTH {
        return Err(format!(
            "distortion: fields may be nested at most {MAX_FIELD_DEPTH} deep"
        ));
    }
    if d.field.needs_boundary() && !object_is_primitive {
        return Err(
            "distortion: this vector field points towards the object's boundary, so the object must be a Sphere, Box, Torus or Mesh (use Constant(..), or wrap a primitive in Hypertexture(object: ..., distortion: ...))"
                .into(),
        );
    }
    Ok(())
}

/// The range `(min, max)` a transfer function can take (before the amplitude).
pub fn transfer_range(t: &TransferDesc) -> (f32, f32) {
    match t {
        TransferDesc::Grid(g) => g
            .values
            .iter()
            .fold((f32::INFINITY, f32::NEG_INFINITY), |(lo, hi), &v| {
                (lo.min(v), hi.max(v))
            }),
        TransferDesc::Curve(c) => {
            let values: Vec<f32> = c.points.iter().map(|p| p.1.0).collect();
            let mut lo = f32::INFINITY;
            let mut hi = f32::NEG_INFINITY;
            for &v in &values {
                lo = lo.min(v);
                hi = hi.max(v);
            }
            if c.interpolation == Interpolation::Spline {
                // A Catmull–Rom segment lies in the convex hull of its Bézier
                // control points p1, p1 + (p2 − p0)/6, p2 − (p3 − p1)/6, p2.
                let n = values.len();
                for i in 0..n.saturating_sub(1) {
                    let p0 = values[i.saturating_sub(1)];
                    let (p1, p2) = (values[i], values[i + 1]);
                    let p3 = values[(i + 2).min(n - 1)];
                    for v in [p1 + (p2 - p0) / 6.0, p2 - (p3 - p1) / 6.0] {
                        lo = lo.min(v);
                        hi = hi.max(v);
                    }
                }
            }
            // T is clamped to [0, 1] when evaluated.
            (lo.clamp(0.0, 1.0), hi.clamp(0.0, 1.0))
        }
    }
}
