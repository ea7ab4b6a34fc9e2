//! Maps through control points: colour, alpha and refractive index over density.
//!
//! The paper maps density to colour and opacity with colour and alpha maps;
//! "step functions or splines may be appropriate". A [`Curve`] is piecewise
//! linear or a Catmull–Rom spline through its control points, and constant
//! beyond the first and last key.

use crate::desc::{CurveDesc, Interpolation};

/// A map from [0, 1] to `N` values through control points.
#[derive(Clone, Debug, PartialEq)]
pub struct Curve<const N: usize> {
    /// Keys, strictly increasing (validated at load).
    keys: Vec<f32>,
    /// The value at each key.
    values: Vec<[f32; N]>,
    /// Linear or spline.
    interpolation: Interpolation,
    /// `keys[i + 1] − keys[i]` and `values[i + 1] − values[i]` of each
    /// segment, computed once: the same bits as at each evaluation.
    widths: Vec<f32>,
    deltas: Vec<[f32; N]>,
    /// The Catmull–Rom polynomial of each segment, 2p₁, p₂ − p₀,
    /// 2p₀ − 5p₁ + 4p₂ − p₃ and 3p₁ − p₀ − 3p₂ + p₃ (p₀ and p₃ the
    /// neighbouring values, repeated at the ends), computed once: the same
    /// bits as at each evaluation.
    spline: Vec<[glam::Vec4; 4]>,
    /// The one value of a linear or step curve whose points all hold it
    /// (none −0 or NaN): what every evaluation gives, `p₁ + 0·u = p₁`.
    flat: Option<[f32; N]>,
}

impl<const N: usize> Curve<N> {
    /// A curve through `points` (keys strictly increasing, at least one point).
    pub fn new(
        interpolation: Interpolation,
        points: impl IntoIterator<Item = (f32, [f32; N])>,
    ) -> Self {
        let (keys, values): (Vec<f32>, Vec<[f32; N]>) = points.into_iter().unzip();
        assert!(!keys.is_empty(), "a curve needs a control point");
        let widths = keys.windows(2).map(|k| k[1] - k[0]).collect();
        let deltas = values
            .windows(2)
            .map(|v| std::array::from_fn(|c| v[1][c] - v[0][c]))
            .collect();
        let n = values.len();
        const { assert!(N <= 4, "a curve has at most four channels (one Vec4)") };
        let spline = (0..n.saturating_sub(1))
            .map(|i| {
                let (p0, p1) = (values[i.saturating_sub(1)], values[i]);
                let (p2, p3) = (values[i + 1], values[(i + 2).min(n - 1)]);
                let mut c = [[0.0; 4]; 4];
                for ch in 0..N {
                    let (a, b, d, e) = (p0[ch], p1[ch], p2[ch], p3[ch]);
                    c[0][ch] = 2.0 * b;
                    c[1][ch] = d - a;
                    c[2][ch] = 2.0 * a - 5.0 * b + 4.0 * d - e;
                    c[3][ch] = 3.0 * b - a - 3.0 * d + e;
                }
                c.map(glam::Vec4::from_array)
            })
            .collect();
        let same = |v: &[f32; N]| v.map(f32::to_bits) == values[0].map(f32::to_bits);
        let plain = |x: f32| !x.is_nan() && x.to_bits() != (-0.0f32).to_bits();
        let flat = (interpolation != Interpolation::Spline
            && values.iter().all(same)
            && values[0].iter().all(|&x| plain(x)))
        .then_some(values[0]);
        Curve {
            keys,
            values,
            interpolation,
            widths,
            deltas,
            spline,
            flat,
        }
    }

    /// The constant curve.
    pub fn constant(value: [f32; N]) -> Self {
        Curve::new(Interpolation::Linear, [(0.0, value)])
    }

    /// The value at `t`.
    #[inline(always)]
    pub fn eval(&self, t: f32) -> [f32; N] {
        if let Some(value) = self.flat {
            return value;
        }
        let n = self.keys.len();
        // At or below the first key, or NaN; at or past the last (a single
        // point is both).
        if t.is_nan() || t <= self.keys[0] {
            return self.values[0];
        }
        if t >= self.keys[n - 1] {
            return self.values[n - 1];
        }
        // The segment [keys[i], keys[i + 1]] holding t: the last key ≤ t,
        // which is not the last key (t is below it). Maps have few keys.
        let mut i = 0;
        while i + 2 < n && self.keys[i + 1] <= t {
            i += 1;
        }
        let u = (t - self.keys[i]) / self.widths[i];
        let p1 = self.values[i];
        let mut out = [0.0; N];
        match self.interpolation {
            Interpolation::Step => out = p1,
            Interpolation::Linear => {
                let delta = self.deltas[i];
                for c in 0..N {
                    out[c] = p1[c] + delta[c] * u;
                }
            }
            Interpolation::Spline => {
                // Four channels at once (the unused ones 0), so that the
                // channels share one register.
                let [c0, c1, c2, c3] = &self.spline[i];
                let (u2, u3) = (u * u, u * u * u);
                let v = 0.5 * (*c0 + *c1 * u + *c2 * u2 + *c3 * u3);
                out.copy_from_slice(&v.to_array()[..N]);
            }
        }
        out
    }
}

impl Curve<3> {
    /// A colour map from its description.
    pub fn colours(desc: &CurveDesc<crate::desc::Rgb>) -> Self {
        Curve::new(
            desc.interpolation,
            desc.points.iter().map(|(k, v)| (*k, v.0)),
        )
    }
}

impl Curve<1> {
    /// A scalar map from its description.
    pub fn scalars<T: Copy + Into<f32>>(desc: &CurveDesc<T>) -> Self {
        Curve::new(
            desc.interpolation,
            desc.points.iter().map(|(k, v)| (*k, [(*v).into()])),
        )
    }

    /// The scalar value at `t`.
    #[inline]
    pub fn eval1(&self, t: f32) -> f32 {
        self.eval(t)[0]
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn linear_hits_control_points_and_interpolates() {
        let c = Curve::new(
            Interpolation::Linear,
            [(0.0, [0.0]), (0.5, [1.0]), (1.0, [0.0])],
        );
        assert_eq!(c.eval1(0.0), 0.0);
        assert_eq!(c.eval1(0.5), 1.0);
        assert_eq!(c.eval1(1.0), 0.0);
        assert_eq!(c.eval1(0.25), 0.5);
        assert_eq!(c.eval1(-1.0), 0.0);
        assert_eq!(c.eval1(2.0), 0.0);
        assert_eq!(c.eval1(f32::NAN), 0.0);
    }

    /// The segments' widths and differences kept from construction give the
    /// bits of computing them at each evaluation, found by a binary search.
    #[test]
    fn kept_segments_give_the_bits_of_computing_them() {
        let pts = [
            (0.0, [0.1, 0.7, 0.3]),
            (0.13, [0.9, 0.2, 0.35]),
            (0.4, [0.45, 0.45, 0.0]),
            (0.41, [0.3, 1.0, 0.6]),
            (0.77, [0.05, 0.6, 0.95]),
            (1.0, [0.8, 0.1, 0.2]),
        ];
        let c = Curve::new(Interpolation::Linear, pts);
        let (keys, values): (Vec<f32>, Vec<[f32; 3]>) = pts.into_iter().unzip();
        for j in 0..=4096 {
            // Just below each 4096th, so that the keys' neighbours are met.
            let t = (j as f32 / 4096.0).next_down().max(0.0);
            let got = c.eval(t);
            let i = keys.partition_point(|&k| k <= t).clamp(1, keys.len() - 1) - 1;
            let u = (t - keys[i]) / (keys[i + 1] - keys[i]);
            for ch in 0..3 {
                let (p1, p2) = (values[i][ch], values[i + 1][ch]);
                let want = if t <= keys[0] { p1 } else { p1 + (p2 - p1) * u };
                assert_eq!(got[ch].to_bits(), want.to_bits(), "at {t}, channel {ch}");
            }
        }
        // The spline's kept polynomials, against the Catmull–Rom formula
        // through the neighbouring values (repeated at the ends).
        let c = Curve::new(Interpolation::Spline, pts);
        let n = keys.len();
        for j in 0..=4096 {
            let t = (j as f32 / 4096.0).next_down().max(0.0);
            let got = c.eval(t);
            let i = keys.partition_point(|&k| k <= t).clamp(1, n - 1) - 1;
            let u = (t - keys[i]) / (keys[i + 1] - keys[i]);
            let (u2, u3) = (u * u, u * u * u);
            for ch in 0..3 {
                let a = values[i.saturating_sub(1)][ch];
                let (b, d) = (values[i][ch], values[i + 1][ch]);
                let e = values[(i + 2).min(n - 1)][ch];
                let want = if t <= keys[0] {
                    b
                } else {
                    0.5 * (2.0 * b
                        + (d - a) * u
                        + (2.0 * a - 5.0 * b + 4.0 * d - e) * u2
                        + (3.0 * b - a - 3.0 * d + e) * u3)
                };
                assert_eq!(
                    got[ch].to_bits(),
                    want.to_bits(),
                    "spline at {t}, channel {ch}"
                );
            }
        }
    }

    /// A flat map gives its value everywhere, as evaluating it would.
    #[test]
    fn flat_maps_give_the_bits_of_evaluating_them() {
        for interpolation in [Interpolation::Linear, Interpolation::Step] {
            let v = [0.85, 0.8, 0.72];
            let c = Curve::new(interpolation, [(0.0, v), (0.4, v), (1.0, v)]);
            assert_eq!(c.flat, Some(v));
            let mut general = c.clone();
            general.flat = None;
            for j in 0..=1024 {
                let t = j as f32 / 1000.0 - 0.01;
                assert_eq!(
                    c.eval(t).map(f32::to_bits),
                    general.eval(t).map(f32::to_bits)
                );
            }
        }
        let zero = [-0.0, 0.5, 0.5];
        assert_eq!(
            Curve::new(Interpolation::Linear, [(0.0, zero), (1.0, zero)]).flat,
            None
        );
        let v = [0.5; 3];
        assert_eq!(
            Curve::new(Interpolation::Spline, [(0.0, v), (1.0, v)]).flat,
            None
        );
        assert_eq!(
            Curve::new(Interpolation::Linear, [(0.0, v), (1.0, [0.6; 3])]).flat,
            None
        );
    }

    #[test]
    fn spline_passes_through_control_points() {
        let pts = [
            (0.0, [0.0, 1.0, 0.0]),
            (0.3, [1.0, 0.0, 0.5]),
            (0.6, [0.2, 0.2, 0.2]),
            (1.0, [1.0, 1.0, 1.0]),
        ];
        let c = Curve::new(Interpolation::Spline, pts);
        for (k, v) in pts {
            let got = c.eval(k);
            for i in 0..3 {
                assert!((got[i] - v[i]).abs() < 1e-6, "at {k}: {got:?} vs {v:?}");
            }
        }
        // Smooth in between: the midpoint lies between neighbours' extremes.
        let mid = c.eval(0.15)[0];
        assert!(mid > 0.0 && mid < 1.0);
    }
}
