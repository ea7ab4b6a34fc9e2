//! Forward-mode differentiation: the density and its gradient in one pass
//! through the density chain (`gradient: Dual`).
//!
//! A [`Dual`] is a number with its gradient with respect to the world point x
//! (a dual number with three infinitesimal parts); a [`DualPoint`] is a point
//! with its Jacobian. Every node of the density tree maps a `DualPoint` to a
//! `Dual` by the chain rule: the primitives and the booleans exactly, the noise
//! from the derivative of its cubic drop-off, bias and gain from the derivative
//! of the power they compute, the warps and the fur through their Jacobians
//! (the fur's projection onto the inner surface included).
//!
//! Two parts of the tree have no derivative written out and are differentiated
//! by central differences over a step ([`spacing`]) where they occur,
//! the result then flowing on through the chain rule: Gilet & Dischler's
//! distortion (its transfer functions are curves and grids) and expressions of
//! the Pixel Stream Editor (a compiled program).
//!
//! The gradient is the derivative of the density, where the paper's differences
//! are its slope over a step: the two differ where the density bends within a
//! step (fine noise, the edge of a hair), so the image differs slightly, and
//! the 1989 differences stay the default (docs/benchmark-log.md, "The dual-number gradient", measures both).
//! Like the rest of the library it uses basic IEEE operations in a fixed order
//! (no fused multiply-add), so every CPU computes the same bits.

use std::ops::{Add, Div, Mul, Neg, Sub};

use glam::Vec3;

/// The spacing of the central differences of the parts without a derivative
/// written out: the marching step, as `gradient: Central` differences. Finer
/// differences follow the derivative more closely but, like the derivative,
/// do not see where the density jumps: Gilet & Dischler's distortion
/// `x − k·V/|V|` jumps where the boundary field turns (the seams of a box's
/// nearest points), and surfaces made of such jumps (the cave's) would be lit
/// as if they faced elsewhere. Over a step, the jump is seen.
#[inline]
pub fn spacing(step: f32) -> f32 {
    step
}

/// A number and its gradient with respect to the world point.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Dual {
    /// The value.
    pub v: f32,
    /// Its gradient.
    pub d: Vec3,
}

impl Dual {
    /// A constant (zero gradient).
    #[inline(always)]
    pub const fn constant(v: f32) -> Dual {
        Dual { v, d: Vec3::ZERO }
    }

    /// `g(self)` given `g(v)` and `g'(v)`.
    #[inline(always)]
    pub fn chain(self, value: f32, slope: f32) -> Dual {
        Dual {
            v: value,
            d: self.d * slope,
        }
    }

    /// √self (zero gradient at 0, where the root has none).
    #[inline(always)]
    pub fn sqrt(self) -> Dual {
        let r = self.v.sqrt();
        let slope = if r > 0.0 { 0.5 / r } else { 0.0 };
        self.chain(r, slope)
    }

    /// |self| (the one-sided slope +1 at 0).
    #[inline(always)]
    pub fn abs(self) -> Dual {
        if self.v < 0.0 { -self } else { self }
    }

    /// The larger of the two, with its gradient.
    #[inline(always)]
    pub fn max(self, other: Dual) -> Dual {
        if other.v > self.v { other } else { self }
    }

    /// The smaller of the two, with its gradient.
    #[inline(always)]
    pub fn min(self, other: Dual) -> Dual {
        if other.v < self.v { other } else { self }
    }

    /// Clamped to [0, 1]: constant where clamped.
    #[inline(always)]
    pub fn clamp01(self) -> Dual {
        // As `shaping::clamp01`: NaN goes to 0.
        if self.v > 0.0 {
            if self.v < 1.0 {
                self
            } else {
                Dual::constant(1.0)
            }
        } else {
            Dual::constant(0.0)
        }
    }
}

impl Add for Dual {
    type Output = Dual;
    #[inline(always)]
    fn add(self, o: Dual) -> Dual {
        Dual {
            v: self.v + o.v,
            d: self.d + o.d,
        }
    }
}

impl Sub for Dual {
    type Output = Dual;
    #[inline(always)]
    fn sub(self, o: Dual) -> Dual {
        Dual {
            v: self.v - o.v,
            d: self.d - o.d,
        }
    }
}

impl Mul for Dual {
    type Output = Dual;
    #[inline(always)]
    fn mul(self, o: Dual) -> Dual {
        Dual {
            v: self.v * o.v,
            d: self.d * o.v + o.d * self.v,
        }
    }
}

impl Div for Dual {
    type Output = Dual;
    #[inline(always)]
    fn div(self, o: Dual) -> Dual {
        let q = self.v / o.v;
        Dual {
            v: q,
            d: (self.d - o.d * q) / o.v,
        }
    }
}

impl Neg for Dual {
    type Output = Dual;
    #[inline(always)]
    fn neg(self) -> Dual {
        Dual {
            v: -self.v,
            d: -self.d,
        }
    }
}

impl Add<f32> for Dual {
    type Output = Dual;
    #[inline(always)]
    fn add(self, o: f32) -> Dual {
        Dual {
            v: self.v + o,
            d: self.d,
        }
    }
}

impl Sub<f32> for Dual {
    type Output = Dual;
    #[inline(always)]
    fn sub(self, o: f32) -> Dual {
        Dual {
            v: self.v - o,
            d: self.d,
        }
    }
}

impl Mul<f32> for Dual {
    type Output = Dual;
    #[inline(always)]
    fn mul(self, o: f32) -> Dual {
        Dual {
            v: self.v * o,
            d: self.d * o,
        }
    }
}

/// A point and its Jacobian with respect to the world point: one [`Dual`] per
/// coordinate.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct DualPoint {
    /// x and its gradient.
    pub x: Dual,
    /// y and its gradient.
    pub y: Dual,
    /// z and its gradient.
    pub z: Dual,
}

impl DualPoint {
    /// The world point itself: the identity Jacobian.
    #[inline(always)]
    pub fn at(p: Vec3) -> DualPoint {
        DualPoint {
            x: Dual { v: p.x, d: Vec3::X },
            y: Dual { v: p.y, d: Vec3::Y },
            z: Dual { v: p.z, d: Vec3::Z },
        }
    }

    /// A fixed point (zero Jacobian).
    #[inline(always)]
    pub fn constant(p: Vec3) -> DualPoint {
        DualPoint {
            x: Dual::constant(p.x),
            y: Dual::constant(p.y),
            z: Dual::constant(p.z),
        }
    }

    /// The point without its Jacobian.
    #[inline(always)]
    pub fn value(&self) -> Vec3 {
        Vec3::new(self.x.v, self.y.v, self.z.v)
    }

    /// `self · b`, summed in a fixed order.
    #[inline(always)]
    pub fn dot(&self, b: Vec3) -> Dual {
        self.x * b.x + self.y * b.y + self.z * b.z
    }

    /// `|self|²`.
    #[inline(always)]
    pub fn length_squared(&self) -> Dual {
        self.x * self.x + self.y * self.y + self.z * self.z
    }

    /// `self + o`.
    #[inline(always)]
    pub fn add(&self, o: &DualPoint) -> DualPoint {
        DualPoint {
            x: self.x + o.x,
            y: self.y + o.y,
            z: self.z + o.z,
        }
    }

    /// `self − o`.
    #[inline(always)]
    pub fn sub(&self, o: &DualPoint) -> DualPoint {
        DualPoint {
            x: self.x - o.x,
            y: self.y - o.y,
            z: self.z - o.z,
        }
    }

    /// `f` of each coordinate, with its axis (0, 1, 2).
    #[inline(always)]
    fn map(&self, f: impl Fn(Dual, usize) -> Dual) -> DualPoint {
        DualPoint {
            x: f(self.x, 0),
            y: f(self.y, 1),
            z: f(self.z, 2),
        }
    }

    /// `self + c` for a constant c.
    #[inline(always)]
    pub fn offset(&self, c: Vec3) -> DualPoint {
        self.map(|v, i| v + c[i])
    }

    /// `self · s` for a dual s.
    #[inline(always)]
    pub fn scale(&self, s: Dual) -> DualPoint {
        self.map(|v, _| v * s)
    }

    /// `self · s` for a constant s.
    #[inline(always)]
    pub fn times(&self, s: f32) -> DualPoint {
        self.map(|v, _| v * s)
    }

    /// `c · s` for a constant vector c and a dual s.
    #[inline(always)]
    pub fn along(c: Vec3, s: Dual) -> DualPoint {
        DualPoint {
            x: s * c.x,
            y: s * c.y,
            z: s * c.z,
        }
    }

    /// `self / |self|`, or the constant `fallback` where `self` is too short to
    /// have a direction (as the soft objects' projections).
    #[inline(always)]
    pub fn direction_or(&self, fallback: Vec3) -> DualPoint {
        let len2 = self.length_squared();
        if len2.v > 1e-20 {
            let len = len2.sqrt();
            DualPoint {
                x: self.x / len,
                y: self.y / len,
                z: self.z / len,
            }
        } else {
            DualPoint::constant(fallback)
        }
    }

    /// The point `g(self)` of a map g known only at points, differentiated by
    /// central differences of spacing `h` at `self`'s value and composed with
    /// `self`'s Jacobian (the chain rule).
    pub fn through(&self, h: f32, g: impl Fn(Vec3) -> Vec3) -> DualPoint {
        let p = self.value();
        let centre = g(p);
        let inv = 0.5 / h;
        // Columns of g's Jacobian: ∂g/∂p_x, ∂g/∂p_y, ∂g/∂p_z.
        let column = |e: Vec3| (g(p + e * h) - g(p - e * h)) * inv;
        let (cx, cy, cz) = (column(Vec3::X), column(Vec3::Y), column(Vec3::Z));
        let row = |value: f32, a: f32, b: f32, c: f32| Dual {
            v: value,
            d: self.x.d * a + self.y.d * b + self.z.d * c,
        };
        DualPoint {
            x: row(centre.x, cx.x, cy.x, cz.x),
            y: row(centre.y, cx.y, cy.y, cz.y),
            z: row(centre.z, cx.z, cy.z, cz.z),
        }
    }

    /// `f(self)` of a function known only at points, differentiated by central
    /// differences of spacing `h` and composed with `self`'s Jacobian.
    pub fn apply(&self, h: f32, f: impl Fn(Vec3) -> f32) -> Dual {
        let p = self.value();
        let inv = 0.5 / h;
        let slope = |e: Vec3| (f(p + e * h) - f(p - e * h)) * inv;
        Dual {
            v: f(p),
            d: self.x.d * slope(Vec3::X) + self.y.d * slope(Vec3::Y) + self.z.d * slope(Vec3::Z),
        }
    }

    /// `g(self)` given `g`'s value and gradient at `self`'s value (the chain rule).
    #[inline(always)]
    pub fn compose(&self, value: f32, gradient: Vec3) -> Dual {
        Dual {
            v: value,
            d: self.x.d * gradient.x + self.y.d * gradient.y + self.z.d * gradient.z,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn products_and_quotients_follow_the_rules() {
        let p = DualPoint::at(Vec3::new(2.0, 3.0, 5.0));
        // f = x·y / z: ∇f = (y/z, x/z, −xy/z²).
        let f = p.x * p.y / p.z;
        assert!((f.v - 1.2).abs() < 1e-6);
        assert!((f.d - Vec3::new(0.6, 0.4, -0.24)).length() < 1e-6);
        // |p|: ∇ = p/|p|.
        let r = p.length_squared().sqrt();
        assert!((r.d - p.value() / r.v).length() < 1e-6);
    }

    #[test]
    fn finite_difference_fallbacks_compose() {
        // g(p) = 2p, then f(q) = q·(1, 0, 0): ∇(f∘g) = (2, 0, 0).
        let p = DualPoint::at(Vec3::new(0.5, -1.0, 0.25)).through(1e-2, |q| q * 2.0);
        let f = p.apply(1e-2, |q| q.x);
        assert!(
            (f.d - Vec3::new(2.0, 0.0, 0.0)).length() < 1e-4,
            "{:?}",
            f.d
        );
    }
}
