//! Teddy, the head of a toy bear written the way an artist's tool exports a
//! model: seven objects of quads with n-gon caps, the ears, muzzle and nose
//! pushed into the head (they overlap it and one another), and the two eyes
//! half-spheres set into it with their rims open. It is the source of
//! `scenes/mesh/meshes/teddy.obj`; `HYPERTEXTURE_BLESS=1 cargo test -p
//! hypertexture --lib mesh::tests::teddy` writes that file again.

use glam::Vec3;

/// The open rim of each eye has this many edges.
pub(crate) const EYE_SEGMENTS: usize = 16;

/// One part: an ellipsoid of semi-axes `radii` (along `u`, `v` and `axis`)
/// about `centre`, cut into `rings` bands from the pole on `axis` and
/// `segments` slices about it; `hemisphere` keeps the bands above the
/// equator only and leaves the equator open.
struct Part {
    name: &'static str,
    centre: Vec3,
    axis: Vec3,
    u: Vec3,
    radii: Vec3,
    rings: usize,
    segments: usize,
    hemisphere: bool,
}

impl Part {
    /// The ring of vertices at `i` bands from the pole, `segments` of them,
    /// counter-clockwise seen from the pole.
    fn ring(&self, i: usize) -> impl Iterator<Item = Vec3> + '_ {
        let axis = self.axis.normalize();
        let u = (self.u - axis * self.u.dot(axis)).normalize();
        let v = axis.cross(u);
        let theta = std::f32::consts::PI * i as f32 / self.rings as f32;
        (0..self.segments).map(move |j| {
            let phi = std::f32::consts::TAU * j as f32 / self.segments as f32;
            let local = Vec3::new(
                theta.sin() * phi.cos(),
                theta.sin() * phi.sin(),
                theta.cos(),
            ) * self.radii;
            self.centre + u * local.x + v * local.y + axis * local.z
        })
    }

    /// The part as OBJ statements whose vertex numbers start after `base`
    /// vertices; returns the text and how many vertices it adds.
    fn obj(&self, base: usize) -> (String, usize) {
        let last = if self.hemisphere {
            self.rings / 2
        } else {
            self.rings - 1
        };
        let mut s = format!("o {}\nusemtl fur\ns 1\n", self.name);
        for i in 1..=last {
            for p in self.ring(i) {
                s += &format!("v {:.5} {:.5} {:.5}\n", p.x, p.y, p.z);
            }
        }
        let n = self.segments;
        let index = |i: usize, j: usize| base + (i - 1) * n + j % n + 1;
        // The cap round the pole: one n-gon, counter-clockwise from outside.
        let cap: Vec<String> = (0..n).map(|j| index(1, j).to_string()).collect();
        s += &format!("f {}\n", cap.join(" "));
        // Bands of quads: down from the pole, then round it.
        for i in 1..last {
            for j in 0..n {
                s += &format!(
                    "f {} {} {} {}\n",
                    index(i, j),
                    index(i + 1, j),
                    index(i + 1, j + 1),
                    index(i, j + 1)
                );
            }
        }
        if !self.hemisphere {
            let cap: Vec<String> = (0..n).rev().map(|j| index(last, j).to_string()).collect();
            s += &format!("f {}\n", cap.join(" "));
        }
        (s, last * n)
    }
}

/// The head's semi-axes: the head is the ellipsoid through these about the
/// origin.
const HEAD: Vec3 = Vec3::new(0.5, 0.46, 0.46);

/// Where the ray from the head's centre along `d` leaves the head.
fn on_head(d: Vec3) -> Vec3 {
    let d = d.normalize();
    d / (d / HEAD).length()
}

/// Where the left (`side` = 1) or right (-1) eye's axis leaves the head,
/// and the axis (a unit vector out of the head).
pub(crate) fn eye_axis(side: f32) -> (Vec3, Vec3) {
    let d = on_head(Vec3::new(0.19 * side, 0.1, 0.42));
    (d, d.normalize())
}

fn parts() -> Vec<Part> {
    let (y, z) = (Vec3::Y, Vec3::Z);
    let eye = |name, side: f32| {
        let (d, outward) = eye_axis(side);
        Part {
            name,
            // Sunk 0.02 into the head so that the open rim is inside it.
            centre: d - outward * 0.02,
            axis: outward,
            u: y,
            radii: Vec3::splat(0.07),
            rings: 8,
            segments: EYE_SEGMENTS,
            hemisphere: true,
        }
    };
    // Name, centre, pole axis, u, semi-axes along (u, v, axis), bands, slices.
    #[rustfmt::skip]
    let solids = [
        ("Head", Vec3::ZERO, y, z, Vec3::new(HEAD.z, HEAD.x, HEAD.y), 16, 32),
        ("Ear.L", Vec3::new(0.33, 0.36, -0.04), z, y, Vec3::new(0.15, 0.16, 0.07), 10, 20),
        ("Ear.R", Vec3::new(-0.33, 0.36, -0.04), z, y, Vec3::new(0.15, 0.16, 0.07), 10, 20),
        ("Muzzle", Vec3::new(0.0, -0.12, 0.38), z, y, Vec3::new(0.16, 0.21, 0.21), 10, 20),
        ("Nose", Vec3::new(0.0, -0.04, 0.58), z, y, Vec3::new(0.06, 0.09, 0.06), 8, 14),
    ];
    let mut parts: Vec<Part> = solids
        .into_iter()
        .map(|(name, centre, axis, u, radii, rings, segments)| Part {
            name,
            centre,
            axis,
            u,
            radii,
            rings,
            segments,
            hemisphere: false,
        })
        .collect();
    parts.extend([eye("Eye.L", 1.0), eye("Eye.R", -1.0)]);
    parts
}

/// The whole file.
pub(crate) fn teddy_obj() -> String {
    let mut s = String::from(
        "# Teddy, a toy bear's head: seven objects of quads and n-gons, written by\n\
         # shared/src/mesh/tests/teddy.rs (CC0 1.0, public domain dedication).\n\
         mtllib teddy.mtl\n",
    );
    let mut base = 0;
    for part in parts() {
        let (text, added) = part.obj(base);
        s += &text;
        base += added;
    }
    s
}
