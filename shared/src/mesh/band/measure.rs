//! What a field is measured by: its error against the exact queries, and a
//! large mesh to build it on.

use glam::Vec3;

use super::Band;
use crate::math::random::SplitMix64;
use crate::mesh::{Mesh, Sample};

/// A field's error against the exact queries over a mesh's soft region
/// (`0 < d < s`), as fractions of the softness s.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct FieldError {
    /// The points of the soft region measured.
    pub points: usize,
    /// Those the field does not place in its band (none, when it covers the
    /// soft region).
    pub missed: usize,
    /// Max and RMS of |d_field − d_exact| / s.
    pub distance: [f32; 2],
    /// Max and RMS of |closest_field − closest_exact| / s: the error of
    /// `project()`.
    pub point: [f32; 2],
}

impl Band {
    /// The field's error against `mesh` (the mesh it was built from) over
    /// `points` random points of the soft region of width `softness`,
    /// drawn from `seed`.
    pub fn error(&self, mesh: &Mesh, softness: f32, points: usize, seed: u64) -> FieldError {
        let (lo, hi) = mesh.bounds();
        let (lo, span) = (
            lo - Vec3::splat(softness),
            hi - lo + Vec3::splat(2.0 * softness),
        );
        let mut rng = SplitMix64::new(seed);
        let mut e = FieldError::default();
        let (mut d2, mut p2) = (0f64, 0f64);
        // Each draw lands in the soft region with a probability of a few
        // per cent for any closed mesh; the bound ends a degenerate one.
        for _ in 0..points.saturating_mul(1000) {
            if e.points + e.missed >= points {
                break;
            }
            let x = lo + Vec3::new(rng.next_f32(), rng.next_f32(), rng.next_f32()) * span;
            let exact = mesh.closest(x);
            if !(exact.distance > 0.0 && exact.distance < softness) {
                continue;
            }
            let Sample::Near { distance, point } = self.sample(x) else {
                e.missed += 1;
                continue;
            };
            let de = (distance - exact.distance).abs() / softness;
            let pe = (point - exact.point).length() / softness;
            e.distance[0] = e.distance[0].max(de);
            e.point[0] = e.point[0].max(pe);
            d2 += f64::from(de * de);
            p2 += f64::from(pe * pe);
            e.points += 1;
        }
        let rms = |sum: f64| (sum / e.points.max(1) as f64).sqrt() as f32;
        e.distance[1] = rms(d2);
        e.point[1] = rms(p2);
        e
    }
}

/// An icosphere of radius about 1 subdivided `levels` times (20·4^levels
/// triangles), displaced along its radius by a few waves so that its
/// surface is not a sphere's, as OBJ text: a large mesh for measuring fields.
#[doc(hidden)]
pub fn displaced_icosphere_obj(levels: u32) -> String {
    let obj = crate::mesh::icosphere_obj(Vec3::ZERO, 1.0, levels);
    let mut out = String::with_capacity(obj.len() + obj.len() / 4);
    for line in obj.lines() {
        let p: Vec<f32> = match line.strip_prefix("v ") {
            Some(v) => v
                .split_whitespace()
                .filter_map(|c| c.parse().ok())
                .collect(),
            None => Vec::new(),
        };
        if let [x, y, z] = p[..] {
            let bump = 1.0 + 0.08 * (5.0 * x).sin() * (4.0 * y).sin() * (3.0 * z).cos();
            out += &format!("v {} {} {}\n", x * bump, y * bump, z * bump);
        } else {
            out += line;
            out.push('\n');
        }
    }
    out
}
