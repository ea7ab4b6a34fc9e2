//! The checked values a description is made of: numbers in their ranges,
//! vectors, colours and curves. Each is checked as it is read, so a bad value
//! is reported at its line and column.

use serde::Deserialize;

/// A curve through control points over [0, 1], e.g. colour over density.
#[derive(Clone, Debug, Deserialize, PartialEq)]
#[serde(
    deny_unknown_fields,
    try_from = "CurveFields<T>",
    bound = "T: Deserialize<'de>"
)]
pub struct CurveDesc<T> {
    /// How to interpolate between control points.
    pub interpolation: Interpolation,
    /// Control points (key in [0, 1], value), keys strictly increasing.
    pub points: Vec<(f32, T)>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields, rename = "Map", bound = "T: Deserialize<'de>")]
struct CurveFields<T> {
    #[serde(default)]
    interpolation: Interpolation,
    points: Vec<(Fraction, T)>,
}

impl<T> TryFrom<CurveFields<T>> for CurveDesc<T> {
    type Error = String;
    fn try_from(f: CurveFields<T>) -> Result<Self, String> {
        if f.points.is_empty() {
            return Err("a map needs at least one control point".into());
        }
        if f.points.len() > 256 {
            return Err(format!(
                "a map may have at most 256 control points, not {}",
                f.points.len()
            ));
        }
        for w in f.points.windows(2) {
            if w[1].0.0 <= w[0].0.0 {
                return Err(format!(
                    "map keys must increase: {} comes after {}",
                    w[1].0.0, w[0].0.0
                ));
            }
        }
        Ok(CurveDesc {
            interpolation: f.interpolation,
            points: f.points.into_iter().map(|(k, v)| (k.0, v)).collect(),
        })
    }
}

impl CurveDesc<Rgb> {
    pub(super) fn white() -> Self {
        CurveDesc {
            interpolation: Interpolation::Linear,
            points: vec![(0.0, Rgb([1.0, 1.0, 1.0]))],
        }
    }
}

/// Interpolation between control points.
#[derive(Clone, Copy, Debug, Default, Deserialize, PartialEq, Eq)]
pub enum Interpolation {
    /// Piecewise linear.
    #[default]
    Linear,
    /// Catmull–Rom spline through the points.
    Spline,
    /// Constant from each key to the next: a step function (an opacity that
    /// extracts an iso-surface).
    Step,
}

macro_rules! checked_float {
    ($(#[$doc:meta])* $name:ident, $what:literal, |$v:ident| $ok:expr) => {
        $(#[$doc])*
        #[derive(Clone, Copy, Debug, Default, Deserialize, PartialEq, PartialOrd)]
        #[serde(try_from = "f64")]
        pub struct $name(pub f32);

        impl TryFrom<f64> for $name {
            type Error = String;
            fn try_from(raw: f64) -> Result<Self, String> {
                let $v = raw as f32;
                if raw.is_finite() && $v.is_finite() && $ok {
                    Ok($name($v))
                } else {
                    Err(format!("expected {}, found {}", $what, raw))
                }
            }
        }

        impl From<$name> for f32 {
            fn from(v: $name) -> f32 {
                v.0
            }
        }
    };
}

checked_float!(
    /// A finite number.
    Finite, "a finite number", |v| true
);
checked_float!(
    /// A finite number > 0.
    Positive, "a positive number", |v| v > 0.0
);
checked_float!(
    /// A finite number ≥ 0.
    NonNegative, "a number ≥ 0", |v| v >= 0.0
);
checked_float!(
    /// A number in [0, 1].
    Fraction, "a number in [0, 1]", |v| (0.0..=1.0).contains(&v)
);
checked_float!(
    /// A number strictly between 0 and 1 (a bias or gain parameter).
    UnitOpen, "a number strictly between 0 and 1", |v| v > 0.0 && v < 1.0
);
checked_float!(
    /// A vertical field of view in degrees, strictly between 0 and 180.
    FieldOfView, "a field of view strictly between 0 and 180 degrees", |v| v > 0.0 && v < 180.0
);

impl Positive {
    pub(super) fn one() -> Self {
        Positive(1.0)
    }
    pub(super) fn frame_rate() -> Self {
        Positive(24.0)
    }
    pub(super) fn shininess() -> Self {
        Positive(20.0)
    }
}

impl NonNegative {
    pub(super) fn one() -> Self {
        NonNegative(1.0)
    }
    pub(super) fn fifth() -> Self {
        NonNegative(0.2)
    }
}

impl Fraction {
    pub(super) fn threshold() -> Self {
        Fraction(0.99)
    }
}

impl UnitOpen {
    pub(super) fn fur_bias() -> Self {
        UnitOpen(0.3)
    }
    pub(super) fn fur_gain() -> Self {
        UnitOpen(0.9)
    }
    pub(super) fn curl_gain() -> Self {
        UnitOpen(0.8)
    }
}

/// An octave count, 1 to 16.
#[derive(Clone, Copy, Debug, Deserialize, PartialEq, Eq)]
#[serde(try_from = "u64")]
pub struct Octaves(pub u32);

impl Octaves {
    /// The most octaves a scene may ask for.
    pub const MOST: usize = 16;
}

impl TryFrom<u64> for Octaves {
    type Error = String;
    fn try_from(n: u64) -> Result<Self, String> {
        if (1..=Octaves::MOST as u64).contains(&n) {
            Ok(Octaves(n as u32))
        } else {
            Err(format!("expected an octave count from 1 to 16, found {n}"))
        }
    }
}

impl Octaves {
    pub(super) fn six() -> Self {
        Octaves(6)
    }
}

/// Checker squares around the horizon, 2 to 1024.
#[derive(Clone, Copy, Debug, Deserialize, PartialEq, Eq)]
#[serde(try_from = "u64")]
pub struct Squares(pub u32);

impl TryFrom<u64> for Squares {
    type Error = String;
    fn try_from(n: u64) -> Result<Self, String> {
        if (2..=1024).contains(&n) {
            Ok(Squares(n as u32))
        } else {
            Err(format!("expected a square count from 2 to 1024, found {n}"))
        }
    }
}

/// A point or vector with finite coordinates, written `(x, y, z)`.
#[derive(Clone, Copy, Debug, Default, Deserialize, PartialEq)]
#[serde(try_from = "(f64, f64, f64)")]
pub struct V3(pub glam::Vec3);

impl TryFrom<(f64, f64, f64)> for V3 {
    type Error = String;
    fn try_from((x, y, z): (f64, f64, f64)) -> Result<Self, String> {
        let v = glam::Vec3::new(x as f32, y as f32, z as f32);
        if v.is_finite() {
            Ok(V3(v))
        } else {
            Err(format!(
                "expected a vector of finite numbers, found ({x}, {y}, {z})"
            ))
        }
    }
}

impl V3 {
    pub(super) fn y() -> Self {
        V3(glam::Vec3::Y)
    }
}

/// A non-zero vector with finite coordinates, normalised when read.
#[derive(Clone, Copy, Debug, Deserialize, PartialEq)]
#[serde(try_from = "(f64, f64, f64)")]
pub struct Direction(pub glam::Vec3);

impl TryFrom<(f64, f64, f64)> for Direction {
    type Error = String;
    fn try_from(t: (f64, f64, f64)) -> Result<Self, String> {
        let v = V3::try_from(t)?.0;
        if v.length() < 1e-6 {
            return Err(format!(
                "expected a non-zero direction, found {:?}",
                v.to_array()
            ));
        }
        Ok(Direction(v.normalize()))
    }
}

impl Direction {
    pub(super) fn y() -> Self {
        Direction(glam::Vec3::Y)
    }
}

/// A linear RGB colour with finite components ≥ 0, written `(r, g, b)`.
#[derive(Clone, Copy, Debug, Deserialize, PartialEq)]
#[serde(try_from = "(f64, f64, f64)")]
pub struct Rgb(pub [f32; 3]);

impl TryFrom<(f64, f64, f64)> for Rgb {
    type Error = String;
    fn try_from(t: (f64, f64, f64)) -> Result<Self, String> {
        let v = V3::try_from(t)?.0;
        if v.min_element() < 0.0 {
            return Err(format!(
                "expected a colour with components ≥ 0, found {:?}",
                v.to_array()
            ));
        }
        Ok(Rgb(v.to_array()))
    }
}

impl Rgb {
    pub(super) fn ambient() -> Self {
        Rgb([0.1, 0.1, 0.1])
    }
}
