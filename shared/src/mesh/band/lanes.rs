//! The field read at [`LANES`] points at once: the same arithmetic as
//! [`Band::sample`], lane by lane and without branches, so the same bits on
//! every instruction set (the caller inlines it into its copy per set).

use glam::Vec3;

use super::{BRICK, Band, INSIDE, OUTSIDE, SAMPLES, SIDE, Sample};
use crate::math::simd::{LANES, Lanes};

/// The field at [`LANES`] points ([`Band::sample_lanes`]).
#[derive(Clone, Copy, Debug)]
pub struct SampleLanes {
    /// Bit l: lane l is [`Sample::Outside`].
    pub outside: u32,
    /// Bit l: lane l is [`Sample::Inside`].
    pub inside: u32,
    /// [`Sample::Near`]'s distance of the other lanes.
    pub distance: Lanes,
    /// [`Sample::Near`]'s point of the other lanes.
    pub point: [Lanes; 3],
}

impl SampleLanes {
    /// Lane `l` as [`Band::sample`] gives it.
    #[inline(always)]
    pub fn get(&self, l: usize) -> Sample {
        if self.outside >> l & 1 != 0 {
            Sample::Outside
        } else if self.inside >> l & 1 != 0 {
            Sample::Inside
        } else {
            Sample::Near {
                distance: self.distance[l],
                point: Vec3::new(self.point[0][l], self.point[1][l], self.point[2][l]),
            }
        }
    }
}

/// Where a lane lies among the slots: its slot's content (a brick's index,
/// [`INSIDE`] or [`OUTSIDE`]; [`OUTSIDE`] beyond the grid) and its lattice
/// coordinates.
#[derive(Clone, Copy)]
struct Slots {
    content: [u32; LANES],
    /// `(p − origin) / voxel`, per axis.
    g: [Lanes; 3],
    /// The slot's coordinates (0 beyond the grid).
    s: [[u32; LANES]; 3],
}

impl Band {
    /// The cell's edge (the mesh's units).
    pub fn voxel(&self) -> f32 {
        f32::from_bits(self.key.lengths[0])
    }

    /// The distance from the surface beyond which a slot holds no brick:
    /// every point of a slot beyond the band lies farther than this from
    /// the surface (the mesh's units).
    pub fn reach(&self) -> f32 {
        super::reach(
            f32::from_bits(self.key.lengths[1]),
            f32::from_bits(self.key.lengths[2]),
        )
    }

    /// The slots of the lanes' points, as [`Band::sample`] finds them.
    #[inline(always)]
    fn slots_lanes(&self, x: &Lanes, y: &Lanes, z: &Lanes) -> Slots {
        let [nx, ny, nz] = self.dims;
        let mut out = Slots {
            content: [OUTSIDE; LANES],
            g: [[0.0; LANES]; 3],
            s: [[0; LANES]; 3],
        };
        let mut index = [0usize; LANES];
        let mut within = [false; LANES];
        for l in 0..LANES {
            // `(p − origin) · inv_voxel`, coordinate by coordinate (glam's
            // `Vec3` arithmetic), then `· (1 / BRICK)`.
            let g = [
                (x[l] - self.origin.x) * self.inv_voxel,
                (y[l] - self.origin.y) * self.inv_voxel,
                (z[l] - self.origin.z) * self.inv_voxel,
            ];
            let s = g.map(|g| g * (1.0 / BRICK as f32));
            // NaN fails every comparison: beyond.
            let inside_grid = s[0] >= 0.0
                && s[1] >= 0.0
                && s[2] >= 0.0
                && s[0] < nx as f32
                && s[1] < ny as f32
                && s[2] < nz as f32;
            let si = s.map(|s| if inside_grid { s as u32 } else { 0 });
            index[l] = si[0] as usize + nx * (si[1] as usize + ny * si[2] as usize);
            within[l] = inside_grid;
            for a in 0..3 {
                out.g[a][l] = g[a];
                out.s[a][l] = si[a];
            }
        }
        for l in 0..LANES {
            if within[l] {
                out.content[l] = self.slots[index[l]];
            }
        }
        out
    }

    /// Bit l: lane l's point lies in a slot wholly outside the band, or
    /// beyond the grid: farther than the outer reach from the surface, where
    /// [`Band::sample`] is [`Sample::Outside`].
    #[inline(always)]
    pub fn beyond_lanes(&self, x: &Lanes, y: &Lanes, z: &Lanes) -> u32 {
        let slots = self.slots_lanes(x, y, z);
        (0..LANES).fold(0, |m, l| m | u32::from(slots.content[l] == OUTSIDE) << l)
    }

    /// [`Band::beyond_lanes`] of one point.
    #[inline]
    pub fn beyond(&self, p: Vec3) -> bool {
        let g = (p - self.origin) * self.inv_voxel;
        let s = g * (1.0 / BRICK as f32);
        let [nx, ny, nz] = self.dims;
        let above = s.x >= 0.0 && s.y >= 0.0 && s.z >= 0.0;
        if !(above && s.x < nx as f32 && s.y < ny as f32 && s.z < nz as f32) {
            return true;
        }
        let (sx, sy, sz) = (s.x as usize, s.y as usize, s.z as usize);
        self.slots[sx + nx * (sy + ny * sz)] == OUTSIDE
    }

    /// [`Band::sample`] at each lane's point (the same bits).
    #[inline(always)]
    pub fn sample_lanes(&self, x: &Lanes, y: &Lanes, z: &Lanes) -> SampleLanes {
        let slots = self.slots_lanes(x, y, z);
        let mut out = SampleLanes {
            outside: 0,
            inside: 0,
            distance: [0.0; LANES],
            point: [[0.0; LANES]; 3],
        };
        let mut in_brick = 0u32;
        for l in 0..LANES {
            let c = slots.content[l];
            out.outside |= u32::from(c == OUTSIDE) << l;
            out.inside |= u32::from(c == INSIDE) << l;
            in_brick |= u32::from(c < INSIDE) << l;
        }
        if in_brick == 0 {
            return out;
        }
        // Every lane is interpolated (the others in the first cell of the
        // first brick, whose values are then dropped): no branch per lane.
        let mut base = [0usize; LANES];
        let mut t = [[0.0f32; LANES]; 3];
        for l in 0..LANES {
            let brick = if in_brick >> l & 1 != 0 {
                slots.content[l] as usize
            } else {
                0
            };
            let mut cell = [0usize; 3];
            for a in 0..3 {
                // `local` of `Band::sample`.
                let local = slots.g[a][l] - (slots.s[a][l] as usize * BRICK) as f32;
                let c = (local as usize).min(BRICK - 1);
                cell[a] = c;
                t[a][l] = (local - c as f32).clamp(0.0, 1.0);
            }
            base[l] = brick * SAMPLES + cell[0] + SIDE * (cell[1] + SIDE * cell[2]);
        }
        let samples = &self.samples[..];
        let last = samples.len() - (2 + SIDE + SIDE * SIDE);
        let mut far = 0u32;
        for l in 0..LANES {
            // In range for a brick's cell; the clamp lets the loads go
            // without bounds checks.
            let b = base[l].min(last);
            let r = super::trilinear(&samples[b..], [t[0][l], t[1][l], t[2][l]]).to_array();
            out.distance[l] = r[0];
            out.point[0][l] = r[1];
            out.point[1][l] = r[2];
            out.point[2][l] = r[3];
            far |= u32::from(!r[0].is_finite()) << l;
        }
        far &= in_brick;
        // A corner beyond the reach: the whole cell is on that corner's side
        // (rare: the band's edge).
        while far != 0 {
            let l = far.trailing_zeros() as usize;
            far &= far - 1;
            let b = base[l];
            let corner = (0..8)
                .map(|k| samples[b + (k & 1) + SIDE * ((k >> 1 & 1) + SIDE * (k >> 2))][0])
                .find(|d| d.is_infinite());
            match corner {
                Some(d) if d < 0.0 => out.inside |= 1 << l,
                _ => out.outside |= 1 << l,
            }
        }
        out
    }
}
