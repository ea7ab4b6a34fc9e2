//! The ray marcher of section 3.1.
//!
//! Each ray is clipped to the bounding parallelepiped (slab test), then sampled at
//! `x = x0 + k·Δx_μ` for k = 0, 1, 2, … At each sample the hypertexture f(x) is
//! evaluated; inside the soft region (0 < f < 1) the gradient is estimated by the
//! paper's finite differences along the ray basis (Δx_μ, Δx_ν, Δx_ω) and used as
//! the shading normal. Samples are composited front to back,
//! `t = α_k(1 - α); colour += t·colour_k; α += t`, with
//! `α_k = 1 - (1 - density)^(c·step)` so that the picture does not depend on the
//! step. Where the refractive index changes between samples the ray bends by
//! Snell's law.
//!
//! # What is skipped and what is batched
//!
//! Every shortcut below gives the bits of the plain loop above
//! (`shared/tests/render.rs` renders every scene with skipping off and on
//! every instruction set):
//!
//! - **Chunks.** A ray's samples are evaluated 16 at a time (`Chunk`) by the
//!   lane code, filled in a `#[target_feature]` copy per instruction set
//!   (`x86`); a run of +0 samples after a +0 one is stepped over at once.
//! - **Empty space.** Samples outside the density's support box and ball
//!   (`Support`) are 0 for certain and are not evaluated; lanes past the ray's
//!   end are evaluated at a point outside it, where D = 0.
//! - **Two copies of the loop.** `march::<COMMON, WAIT>`: `COMMON` (the scene's
//!   `common_case`: no refraction, motion, colour or normal expressions,
//!   shadows or strata) drops what such scenes never need; `WAIT` (directional
//!   lights only, no refraction, normal expression or shadows) lets a sample's
//!   gradient and light wait.
//! - **Waiting samples.** A waiting sample (`Deferred`) keeps its point, f and
//!   weight; its gradient neighbours are evaluated 8 samples a call, across
//!   chunk boundaries, and its light 16 at a time (`shade_lanes`); colours are
//!   then added in sample order. `trace_group` marches up to `GROUP` rays and
//!   evaluates their waiting samples together, so the coarse interactive step
//!   still fills the lanes.
//! - **Reuse.** A transparent sample (α_k = 0) adds no colour and is passed
//!   without shading (`latest_normal` finds the normal a later sample falls
//!   back on); where colour depends only on f, the normal and the ray
//!   (`position_free_shading`), a sample with the f and normal of the latest
//!   one shaded takes its colour.
//!
//! What each one saved is in docs/benchmark-log.md.

use glam::Vec3;

use crate::field::domain::{Field, Points, Support};
use crate::field::shaping::clamp01;
use crate::math::fastmath;
use crate::math::simd::{Isa, lane_mask};
use crate::math::simd::{LANES, Lanes};
use crate::pse::surface as pse;
use crate::render::film::Sample;
use crate::scene::camera::{Ray, slab};
use crate::scene::{ColourIndex, Gradient, Light, Scene};

/// The parameters where `ray` enters and leaves the ball of `radius` about
/// `centre` (either may be negative), or `None` when it misses.
#[inline]
fn ball(ray: &Ray, centre: Vec3, radius: f32) -> Option<(f32, f32)> {
    let o = ray.origin - centre;
    let a = ray.direction.length_squared();
    let b = ray.direction.dot(o);
    let disc = b * b - a * (o.length_squared() - radius * radius);
    if !(disc >= 0.0 && a > 0.0) {
        return None;
    }
    let root = disc.sqrt();
    Some(((-b - root) / a, (-b + root) / a))
}

/// Two vectors perpendicular to the unit vector `d` and to each other, each of
/// length `step`: Δx_ν and Δx_ω of the paper.
#[inline]
fn perpendiculars(d: Vec3, step: f32) -> (Vec3, Vec3) {
    let helper = if d.x.abs() < 0.9 { Vec3::X } else { Vec3::Y };
    let v = d.cross(helper).normalize();
    let w = d.cross(v);
    (v * step, w * step)
}

/// The marching state along one (possibly bent) ray.
#[derive(Clone, Copy)]
struct Basis {
    ray: Ray,
    /// Δx_μ, Δx_ν, Δx_ω.
    du: Vec3,
    dv: Vec3,
    dw: Vec3,
    /// Entry and exit parameters.
    t0: f32,
    t1: f32,
    /// Samples before this index lie outside the support of the density
    /// (where it is 0 for certain) and need not be evaluated.
    first: u32,
    /// Samples past this parameter lie outside the support too.
    last: f32,
    /// Sample k lies at `t0 + (k + phase)·step` (jittered supersampling).
    phase: f32,
    /// Blinn's half vector `(l − d)/|l − d|` of each of the first
    /// [`HALVES`] lights that is directional, where the scene has specular
    /// highlights (the other entries unused): the same at every sample of
    /// the segment, of direction d.
    halves: [Vec3; HALVES],
}

/// The lights whose half vectors a [`Basis`] holds; [`shade`] computes the
/// others' at each sample.
const HALVES: usize = 4;

impl Basis {
    fn new(
        ray: Ray,
        step: f32,
        (t0, t1): (f32, f32),
        phase: f32,
        support: Option<Support>,
        scene: &Scene,
    ) -> Basis {
        // Empty-space skipping: only the samples inside the (widened) support are
        // evaluated; the others are 0, exactly what evaluating them would give.
        // The ball first: a ray that misses it needs no slab.
        let inside = |s: Support| {
            let ball = match s.ball {
                Some((centre, r)) => Some(ball(&ray, centre, r)?),
                None => None,
            };
            let (a, b) = slab(&ray, s.aabb.0, s.aabb.1)?;
            let (c, d) = ball.unwrap_or((a, b));
            let (a, b) = (a.max(c), b.min(d));
            (a <= b).then_some((a, b))
        };
        let (first, last) = match support {
            None => (0, t1),
            Some(s) => match inside(s) {
                None => {
                    // No sample is evaluated: the ray's offsets and half
                    // vectors are never read.
                    return Basis {
                        ray,
                        du: Vec3::ZERO,
                        dv: Vec3::ZERO,
                        dw: Vec3::ZERO,
                        t0,
                        t1,
                        first: u32::MAX,
                        last: t0 - 1.0,
                        phase,
                        halves: [Vec3::ZERO; HALVES],
                    };
                }
                Some((a, b)) => {
                    // (`fastmath::floor`, not libm's call: −0 gives +0,
                    // and either skips nothing.)
                    let skip = fastmath::floor((a - t0) / step - phase) - 1.0;
                    let first = if skip > 0.0 { skip as u32 } else { 0 };
                    (first, b)
                }
            },
        };
        let (dv, dw) = perpendiculars(ray.direction, step);
        let halves = std::array::from_fn(|i| match scene.lights.get(i) {
            Some(&Light::Directional { direction, .. }) if scene.specular > 0.0 => {
                (direction - ray.direction).normalize_or_zero()
            }
            _ => Vec3::ZERO,
        });
        Basis {
            ray,
            du: ray.direction * step,
            dv,
            dw,
            t0,
            t1,
            first,
            last,
            phase,
            halves,
        }
    }

    /// The parameter of sample k.
    #[inline(always)]
    fn t(&self, k: u32, step: f32) -> f32 {
        self.t0 + (k as f32 + self.phase) * step
    }
}

/// The densities of [`LANES`] consecutive samples of one segment, evaluated
/// together, and the gradient neighbours of those that need them.
struct Chunk {
    /// Whether any samples are held.
    full: bool,
    /// Index of the first sample held.
    start: u32,
    /// The points of samples `start + l` (past the ray's end, a point
    /// outside the support: see [`sample_points`]).
    x: Points,
    /// f at samples `start + l`.
    f: Lanes,
    /// The opacity α_k = 1 − (1 − ρ)^(c·step) of samples `start + l`.
    alpha: Lanes,
    /// f(x + Δx_ν), f(x + Δx_ω) of samples `start + l`, where `has_gradient`.
    neighbours: [(f32, f32); LANES],
    has_gradient: u32,
    /// Bit l: f at sample `start + l` is not +0.
    nonzero: u32,
}

impl Chunk {
    fn empty() -> Chunk {
        Chunk {
            full: false,
            start: 0,
            x: Points::default(),
            f: [0.0; LANES],
            alpha: [0.0; LANES],
            neighbours: [(0.0, 0.0); LANES],
            has_gradient: 0,
            nonzero: 0,
        }
    }

    /// f and α_k at sample k of `basis`, evaluating the next [`LANES`] samples
    /// when k is not held.
    #[inline(always)]
    fn density(&mut self, k: u32, basis: &Basis, scene: &Scene, field: &Field) -> (f32, f32) {
        let held = k.wrapping_sub(self.start);
        if self.full && (held as usize) < LANES {
            return (self.f[held as usize], self.alpha[held as usize]);
        }
        self.fill(k, basis, scene, field)
    }

    /// Evaluates samples k .. k + [`LANES`]; f and α_k at k.
    #[inline(never)]
    fn fill(&mut self, k: u32, basis: &Basis, scene: &Scene, field: &Field) -> (f32, f32) {
        crate::math::simd::per_isa!(scene.isa, (
            chunk: &mut Chunk = self, k: u32 = k, basis: &Basis = basis, scene: &Scene = scene,
            field: &Field = field,
        ) -> () {
            scalar => chunk.fill_on(k, basis, scene, field, false),
            _lanes => chunk.fill_on(k, basis, scene, field, true),
        });
        (self.f[0], self.alpha[0])
    }

    /// [`Chunk::fill`]'s work; with `simd` (a constant where it is inlined:
    /// into the copies per instruction set that `per_isa!` writes) the points, the
    /// density tree's lane code, the powers and the masks are all compiled
    /// for that set, and the points go to the density in registers.
    #[inline(always)]
    fn fill_on(&mut self, k: u32, basis: &Basis, scene: &Scene, field: &Field, simd: bool) {
        self.full = true;
        self.start = k;
        // The density reads the points where they were just written, not
        // from the chunk's copy.
        let x = sample_points(scene, basis, k, field);
        (self.f, self.alpha) = samples(scene, &x, field, simd);
        self.x = x;
        self.has_gradient = 0;
        self.nonzero = if simd {
            crate::math::simd::nonzero_mask(scene.isa, &self.f)
        } else {
            lane_mask(|l| self.f[l].to_bits() != 0)
        };
    }

    /// f(x + Δx_ν) and f(x + Δx_ω) at sample k (held): for it and the held
    /// samples after it in the soft region, [`LANES`] / 2 at most, evaluated
    /// together, at the offsets of the chunk's own points. `alpha` is the
    /// opacity gathered before sample k (or less): the samples after the one
    /// where the held α_k take it to the scene's threshold, which the marcher
    /// never reaches, are left out.
    #[inline(always)]
    fn neighbours(
        &mut self,
        k: u32,
        basis: &Basis,
        scene: &Scene,
        field: &Field,
        alpha: f32,
    ) -> (f32, f32) {
        let j = (k - self.start) as usize;
        if self.has_gradient & (1 << j) == 0 {
            self.evaluate_neighbours(j, basis, scene, field, alpha);
        }
        self.neighbours[j]
    }

    /// The neighbours of held sample j and of the soft samples after it.
    #[inline(never)]
    fn evaluate_neighbours(
        &mut self,
        j: usize,
        basis: &Basis,
        scene: &Scene,
        field: &Field,
        alpha: f32,
    ) {
        let mut x = Points::default();
        let mut which = [usize::MAX; LANES / 2];
        let mut n = 0;
        let mut gathered = alpha;
        for l in j..LANES {
            if n == LANES / 2 || gathered >= scene.threshold {
                break;
            }
            let f = self.f[l];
            if l == j || (f > 0.0 && f < 1.0) {
                // A sample read or in the soft region is before the
                // ray's end: its point is its own.
                let p = self.x.get(l);
                x.set(2 * n, p + basis.dv);
                x.set(2 * n + 1, p + basis.dw);
                which[n] = l;
                n += 1;
            }
            // The marcher's compositing: opacity only grows, so a sample
            // left out here is one it stops before (or, should it read it
            // after all, one evaluated then).
            if f > 0.0 {
                gathered += self.alpha[l] * (1.0 - gathered);
            }
        }
        // Unused lanes (discarded) take a point outside the support, where
        // the modulation is skipped, or else repeat the first point.
        for l in 2 * n..LANES {
            x.set(l, outside(field).unwrap_or(x.get(l % 2)));
        }
        let v = scene.density.eval_lanes(&x, field, scene.isa);
        for (i, &l) in which[..n].iter().enumerate() {
            self.neighbours[l] = (v[2 * i], v[2 * i + 1]);
            self.has_gradient |= 1 << l;
        }
    }
}

/// The points of samples k .. k + [`LANES`] of `basis`. Samples past the
/// ray's end (`t1`, or the end of the support), which the marcher never
/// reads, get a point outside the support: 0 at once, and the modulation's
/// noise is skipped where a register holds only such lanes.
#[inline(always)]
fn sample_points(scene: &Scene, basis: &Basis, k: u32, field: &Field) -> Points {
    // Branch-free, so that the lanes vectorise: t of every lane, then its
    // point, or the point outside where t is past the end (never, with no
    // point outside: no t exceeds +∞).
    let (outside, end) = match outside(field) {
        Some(p) => (p, basis.t1.min(basis.last)),
        None => (Vec3::ZERO, f32::INFINITY),
    };
    let step = scene.step;
    // (k + l) as f32 by the signed conversion, which vectorises (the same
    // value, so the same bits, below 2^31).
    let t: Lanes = match i32::try_from(k) {
        Ok(k) if k < i32::MAX - LANES as i32 => {
            std::array::from_fn(|l| basis.t0 + ((k + l as i32) as f32 + basis.phase) * step)
        }
        _ => std::array::from_fn(|l| basis.t(k + l as u32, step)),
    };
    let (o, d) = (basis.ray.origin, basis.ray.direction);
    let mut x = Points::default();
    for (l, &t) in t.iter().enumerate() {
        // `Ray::at`, coordinate by coordinate.
        let past = t > end;
        x.x[l] = if past { outside.x } else { o.x + d.x * t };
        x.y[l] = if past { outside.y } else { o.y + d.y * t };
        x.z[l] = if past { outside.z } else { o.z + d.z * t };
    }
    x
}

/// f and the opacity α_k = 1 − (1 − ρ)^(c·step) at the points `x` of a
/// chunk. With `simd` (a constant where it is inlined: into the copies per
/// instruction set of [`Chunk::fill`]) the density tree's lane code and the powers are
/// inlined here too, so the points go to the powers in registers.
#[inline(always)]
fn samples(scene: &Scene, x: &Points, field: &Field, simd: bool) -> (Lanes, Lanes) {
    let f = if simd {
        scene.density.eval_lanes_simd(x, field, scene.isa)
    } else {
        scene.density.eval_lanes(x, field, Isa::Scalar)
    };
    let mut transmit = [0.0; LANES];
    match &scene.alpha_map {
        None => {
            for l in 0..LANES {
                transmit[l] = 1.0 - clamp01(f[l]);
            }
        }
        Some(m) => {
            // α_k is read only where f > 0 (an empty lane's is left 0), and
            // the hard region's f = 1 takes the map once per chunk.
            let hard = 1.0 - clamp01(m.eval1(1.0));
            for l in 0..LANES {
                transmit[l] = if f[l] == 0.0 {
                    1.0
                } else if f[l] == 1.0 {
                    hard
                } else {
                    1.0 - clamp01(m.eval1(f[l]))
                };
            }
        }
    }
    // 1^e = 1 (`pow01`): empty samples are transparent without the power,
    // and a block of them goes without it.
    let opaque = if simd {
        crate::math::simd::below_mask(scene.isa, &transmit, 1.0)
    } else {
        lane_mask(|l| transmit[l] < 1.0)
    };
    if opaque == 0 {
        return (f, [0.0; LANES]);
    }
    let e = scene.opacity_exponent;
    let p = if simd {
        crate::math::fastmath::pow01_lanes_live(&transmit, e, opaque)
    } else {
        fastmath::pow01_on(Isa::Scalar, &transmit, e)
    };
    let mut alpha = [0.0; LANES];
    for l in 0..LANES {
        alpha[l] = 1.0 - p[l];
    }
    (f, alpha)
}

/// A point outside the support of the density (where it and every object's
/// D are 0 for certain), when the scene has one: what the lanes the marcher
/// discards are evaluated at.
#[inline(always)]
fn outside(field: &Field) -> Option<Vec3> {
    field.support.map(|s| s.aabb.1 + Vec3::ONE)
}

/// Marches one ray through the scene and returns what the pixel records.
pub fn trace(scene: &Scene, ray: Ray, field: &Field) -> Sample {
    trace_with_phase(scene, ray, field, 0.0)
}

/// [`trace`] with the samples shifted by `phase` steps (in [0, 1)) along the ray:
/// at `t0 + (k + phase)·step` (jittered supersampling, [`crate::render::sampling`]).
pub fn trace_with_phase(scene: &Scene, ray: Ray, field: &Field, phase: f32) -> Sample {
    let (mut deferred, mut waiting) = (None, None);
    let done = march_any(scene, ray, field, phase, &mut deferred, &mut waiting);
    match (done, &waiting) {
        (Some(sample), _) => sample,
        (None, Some(w)) => finish(w, scene, field, &mut deferred),
        (None, None) => unreachable!("a ray that is not done waits"),
    }
}

/// The rays that [`trace_group`] traces together, at most.
pub const GROUP: usize = 8;

/// [`trace`] of each of `rays` (at most [`GROUP`]) into `out`, the same
/// samples: the rays are marched one after another, and the gradient
/// neighbours of the samples whose light waits (a `Deferred` batch) at their
/// ends are evaluated together, [`LANES`] / 2 samples a call across the
/// rays, before each ray's colour is found.
///
/// # Panics
/// If `rays` are more than [`GROUP`], or `out` is not as long.
pub fn trace_group(scene: &Scene, rays: &[Ray], field: &Field, out: &mut [Sample]) {
    assert!(rays.len() <= GROUP && out.len() == rays.len());
    let mut deferred: [Option<Deferred>; GROUP] = std::array::from_fn(|_| None);
    let mut waiting: [Option<Waiting>; GROUP] = [None; GROUP];
    for (i, &ray) in rays.iter().enumerate() {
        if let Some(sample) = march_any(scene, ray, field, 0.0, &mut deferred[i], &mut waiting[i]) {
            out[i] = sample;
        }
    }
    let mut batches: [Option<(&Basis, &mut Deferred)>; GROUP] = Default::default();
    for ((batch, waiting), deferred) in batches.iter_mut().zip(&waiting).zip(&mut deferred) {
        if let (Some(w), Some(d)) = (waiting, deferred) {
            *batch = Some((&w.basis, d));
        }
    }
    find_waiting(&mut batches, scene, field);
    for (i, out) in out.iter_mut().enumerate() {
        if let Some(w) = &waiting[i] {
            *out = finish(w, scene, field, &mut deferred[i]);
        }
    }
}

/// [`march`] in the copy the scene's `common_case` chooses.
#[inline(always)]
fn march_any(
    scene: &Scene,
    ray: Ray,
    field: &Field,
    phase: f32,
    deferred: &mut Option<Deferred>,
    waiting: &mut Option<Waiting>,
) -> Option<Sample> {
    if scene.common_case {
        march_waits::<true>(scene, ray, field, phase, true, deferred, waiting)
    } else {
        march_waits::<false>(scene, ray, field, phase, true, deferred, waiting)
    }
}

/// [`march`] in the copy where the samples' gradients and light wait
/// ([`Deferred`]) when they do with `shortcuts`: under directional lights
/// only, with no refraction, normal expression or shadows, and the paper's
/// forward differences.
#[inline(always)]
fn march_waits<const COMMON: bool>(
    scene: &Scene,
    ray: Ray,
    field: &Field,
    phase: f32,
    shortcuts: bool,
    deferred: &mut Option<Deferred>,
    waiting: &mut Option<Waiting>,
) -> Option<Sample> {
    if shortcuts && scene.light_waits && matches!(scene.gradient, Gradient::Forward) {
        march::<COMMON, true>(scene, ray, field, phase, shortcuts, deferred, waiting)
    } else {
        march::<COMMON, false>(scene, ray, field, phase, shortcuts, deferred, waiting)
    }
}

/// What a ray marched to its end holds until its colour is found
/// ([`finish`]), with the samples whose light waits: its basis
/// and what it gathered.
#[derive(Clone, Copy)]
struct Waiting {
    basis: Basis,
    colour: Vec3,
    alpha: f32,
    weighted_density: f32,
    depth: f32,
    first_normal: Option<Normal>,
}

/// The sample of a ray that `w` holds ([`march`]'s): the light of
/// the samples waiting in `deferred` added to its colour, then the
/// background behind it.
#[inline(always)]
fn finish(w: &Waiting, scene: &Scene, field: &Field, deferred: &mut Option<Deferred>) -> Sample {
    let mut colour = w.colour;
    let mut first_normal = w.first_normal;
    let alpha = w.alpha;
    if let Some(deferred) = deferred {
        deferred.flush(scene, &w.basis, field, &mut colour);
        if deferred.resolves {
            first_normal = deferred.first;
        }
    }
    let (bg, bg_alpha) = scene.background.sample(w.basis.ray.direction);
    let rgb = colour + bg * (1.0 - alpha);
    let normal = first_normal.map_or(Vec3::ZERO, Normal::unit);
    Sample {
        rgba: [rgb.x, rgb.y, rgb.z, alpha + bg_alpha * (1.0 - alpha)],
        density: if alpha > 0.0 {
            w.weighted_density / alpha
        } else {
            0.0
        },
        depth: w.depth,
        normal: normal.to_array(),
    }
}

/// The own normals of the samples waiting in `batches` (each with its
/// ray's basis): [`gradient_normal`]'s differences, their neighbours
/// evaluated [`LANES`] / 2 samples a call, across the batches (the other
/// lanes at a point outside the support, or else the first point again);
/// then the hard regions' central differences of the object's D, two
/// stencils a call.
fn find_waiting(batches: &mut [Option<(&Basis, &mut Deferred)>], scene: &Scene, field: &Field) {
    let mut x = Points::default();
    gather(
        batches,
        &mut x,
        |d| &mut d.waiting,
        LANES / 2,
        |x, n, (dv, dw), p| {
            x.set(2 * n, p + dv);
            x.set(2 * n + 1, p + dw);
        },
        |batches, x, which| {
            #[cfg(test)]
            if which.iter().any(|&(r, _)| r != which[0].0) {
                tests::ACROSS.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
            }
            let eval = |x: &Points| scene.density.eval_lanes(x, field, scene.isa);
            hold_normals(batches, x, which, 2, field, eval, |basis, d, l, v| {
                let (f, fv, fw) = (d.f[l], v[0], v[1]);
                let g = basis.du * (f - d.behind[l]) + basis.dv * (fv - f) + basis.dw * (fw - f);
                Normal::of_gradient(g)
            })
        },
    );
    let h = 2.0 * scene.step;
    gather(
        batches,
        &mut x,
        |d| &mut d.hard,
        2,
        |x, n, _, p| {
            for (i, q) in stencil(p, h).into_iter().enumerate() {
                x.set(6 * n + i, q);
            }
        },
        |batches, x, which| {
            let eval = |x: &Points| scene.object.eval_object_lanes(x, field, scene.isa);
            hold_normals(batches, x, which, 6, field, eval, |_, _, _, v| {
                central_normal_of(v)
            })
        },
    );
}

/// The samples of `batches` whose bits are set in the mask that `mask`
/// picks (the bits cleared), `per` a call (at most [`LANES`] / 2): `place`
/// sets in `x` the lanes of the n-th of a call from its batch's offsets
/// (Δx_ν, Δx_ω) and its point; `hold` evaluates those placed.
#[inline(always)]
fn gather(
    batches: &mut [Option<(&Basis, &mut Deferred)>],
    x: &mut Points,
    mask: fn(&mut Deferred) -> &mut u32,
    per: usize,
    mut place: impl FnMut(&mut Points, usize, (Vec3, Vec3), Vec3),
    mut hold: impl FnMut(&mut [Option<(&Basis, &mut Deferred)>], &mut Points, &[(usize, usize)]),
) {
    let mut which = [(0, 0); LANES / 2];
    let mut n = 0;
    for r in 0..batches.len() {
        let Some((basis, d)) = &mut batches[r] else {
            continue;
        };
        let offsets = (basis.dv, basis.dw);
        let mut bits = std::mem::take(mask(d));
        while bits != 0 {
            let l = bits.trailing_zeros() as usize;
            bits &= bits - 1;
            let Some((_, d)) = &batches[r] else {
                unreachable!("the batch taken above")
            };
            place(x, n, offsets, d.x.get(l));
            which[n] = (r, l);
            n += 1;
            if n == per {
                hold(batches, x, &which[..n]);
                n = 0;
            }
        }
    }
    if n > 0 {
        hold(batches, x, &which[..n]);
    }
}

/// Evaluates with `eval` the points `x` of the samples `which` (batch,
/// lane), `per` lanes each (the lanes after them at the point outside the
/// support, or else repeating the first sample's), and holds the normal
/// that `normal` finds from each sample's batch, lane and values.
#[inline(always)]
fn hold_normals(
    batches: &mut [Option<(&Basis, &mut Deferred)>],
    x: &mut Points,
    which: &[(usize, usize)],
    per: usize,
    field: &Field,
    eval: impl FnOnce(&Points) -> Lanes,
    normal: impl Fn(&Basis, &Deferred, usize, &[f32]) -> Option<Normal>,
) {
    for l in per * which.len()..LANES {
        x.set(l, outside(field).unwrap_or(x.get(l % per)));
    }
    let v = eval(x);
    for (i, &(r, l)) in which.iter().enumerate() {
        let Some((basis, d)) = &mut batches[r] else {
            unreachable!("only the batches' samples are held")
        };
        if let Some(n) = normal(basis, d, l, &v[per * i..per * (i + 1)]) {
            d.hold(l, n);
        }
    }
}

/// The choices of [`march`] made once per ray, from the scene and
/// `shortcuts`.
#[derive(Clone, Copy)]
struct Policy {
    /// The scene has lights. Without, the shading ignores the normal: only
    /// the first one is recorded (the normal AOV), and refraction asks for
    /// its own.
    lit: bool,
    /// A transparent sample (α_k = 0, where an alpha map gives its density
    /// no opacity) adds nothing to the colour. Where its normal is a
    /// function of its point alone (central differences, dual numbers) and
    /// no ray bends, such a soft sample after the first normal is passed
    /// without its normal or shading: [`Gathered::passed`] holds the first
    /// and last of them since the last normal, whose normals are found only
    /// where a later sample's normal vanishes and falls back on the last one
    /// ([`latest_normal`]).
    lazy: bool,
    /// Under directional lights only, with no refraction, normal expression
    /// or shadows, the samples' light waits and is found [`LANES`] samples
    /// at a time ([`Deferred`]); their base colours are found as they come.
    /// The batch is set up at the ray's first sample that adds colour.
    defers: bool,
    /// With the paper's forward differences, the gradients wait too: a
    /// shaded soft sample's neighbours f(x + Δx_ν), f(x + Δx_ω) are
    /// evaluated with the other waiting samples', [`LANES`] / 2 samples a
    /// call across the chunks, and the normals (and the last one, which a
    /// sample without its own takes) are found in the order of the samples
    /// ([`Deferred::resolves`]).
    gradients_wait: bool,
    /// The strata's keys wait too, where no colour expression stands in for
    /// the colour map.
    keys_wait: bool,
}

impl Policy {
    #[inline(always)]
    fn new<const COMMON: bool, const WAIT: bool>(scene: &Scene, shortcuts: bool) -> Policy {
        let lazy = !WAIT
            && shortcuts
            && scene.refraction.is_none()
            && matches!(scene.gradient, Gradient::Central | Gradient::Dual);
        let defers = WAIT || (shortcuts && scene.light_waits);
        let gradients_wait = WAIT || (defers && matches!(scene.gradient, Gradient::Forward));
        let keys_wait = !COMMON
            && defers
            && matches!(scene.colour_index, ColourIndex::Strata { .. })
            && scene.expressions.colour.is_none();
        Policy {
            lit: !scene.lights.is_empty(),
            lazy,
            defers,
            gradients_wait,
            keys_wait,
        }
    }

    /// An empty batch of waiting samples.
    #[inline(always)]
    fn batch(self) -> Deferred {
        Deferred {
            resolves: self.gradients_wait,
            keys_wait: self.keys_wait,
            ..Deferred::default()
        }
    }
}

/// A ray's current segment (a refracted ray starts another) and the chunk
/// of samples held along it: what the kernels read by reference.
struct Segment {
    basis: Basis,
    chunk: Chunk,
}

/// Where a ray's march is along its [`Segment`]: the sample k, f at the
/// previous sample when it lay on the segment, the distance travelled
/// before the segment, the index of the medium, and the samples left in
/// the budget. (Apart from the segment, whose address the kernels take, so
/// that these stay in registers.)
struct Walk {
    k: u32,
    /// f(x − Δx_μ): the previous sample, when it lay on the current segment.
    previous: Option<f32>,
    path: f32,
    medium_index: Option<f32>,
    /// Every sample costs a step of the budget, so a ray bent back and forth
    /// inside the volume (total internal reflection) still terminates.
    budget: u64,
}

impl Walk {
    /// Passes samples k .. first, which are empty: they would cost budget
    /// and leave f(x − Δx_μ) = 0, and nothing else. False when the ray ends
    /// or the budget runs out among them.
    #[inline(always)]
    fn skip_empty(&mut self, basis: &Basis, step: f32) -> bool {
        if self.k < basis.first {
            let skipped = u64::from(basis.first.min(u32::MAX - 1) - self.k);
            if skipped >= self.budget || basis.t(basis.first, step) > basis.t1 {
                return false;
            }
            self.budget -= skipped;
            self.k = basis.first;
            self.previous = Some(0.0);
        }
        true
    }

    /// After sample k − 1 of density `f`: where it is +0 and went through
    /// the loop without effect (no colour; no bend, and after it none at
    /// f = 0 either), so would the held +0 samples after it, costing budget
    /// and leaving f(x − Δx_μ) = 0. They are passed at once, to the next
    /// held sample that is not +0 or the chunk's end. Should the ray end or
    /// the budget run out among them, the loop ends at that sample (t grows
    /// with k).
    #[inline(always)]
    fn skip_zeros(&mut self, chunk: &Chunk, f: f32) {
        if f.to_bits() == 0 && chunk.full {
            let j = self.k - chunk.start;
            let ahead = chunk.nonzero.checked_shr(j).unwrap_or(0);
            let next = if ahead == 0 {
                LANES as u32
            } else {
                j + ahead.trailing_zeros()
            };
            self.budget = self.budget.saturating_sub(u64::from(next - j));
            self.k = chunk.start + next;
        }
    }
}

/// What a ray has gathered so far, front to back, besides its colour
/// (whose address the batch of waiting samples takes).
#[derive(Default)]
struct Gathered {
    alpha: f32,
    weighted_density: f32,
    depth: f32,
    first_normal: Option<Normal>,
    last_normal: Option<Normal>,
    /// The first and last transparent samples passed since the last normal
    /// ([`Policy::lazy`]).
    passed: Option<(u32, u32)>,
    /// With `position_free_shading`, the colour of the latest sample shaded
    /// without a normal of its own, and what it was a function of: f and the
    /// shading normal (as bits), on the current segment. A run of samples
    /// with the same f and normal (a hard region, where f = 1 and the normal
    /// stays the last one) reuses it.
    shaded: Option<((u32, [u32; 3]), Vec3)>,
}

/// A sample's normal as [`sample_normal`] finds it.
struct SampleNormal {
    /// The normal found now.
    normal: Option<Normal>,
    /// f(x − Δx_μ) of a soft sample whose gradient waits.
    waits: Option<f32>,
    /// Whether the normal of a hard region's first sample waits.
    hard_waits: bool,
    /// A transparent soft sample passed without its normal or shading.
    pass: bool,
}

/// The sample loop of [`trace_with_phase`]. `COMMON` is the scene's
/// `common_case`, chosen once per scene: no refraction, no motion, no colour
/// or normal expressions, no shadows, the density as the colour key. Its
/// copy of the loop leaves those out (the object point is the world point,
/// the colour the colour map at f, the normal unperturbed, a ray never
/// bends), computing what the general copy computes in that case.
/// `shortcuts` lets it pass transparent samples without their normals,
/// reuse a sample's colour along a run of samples of the same f and normal,
/// skip the refraction map where f repeats, and let the samples' light wait
/// ([`Deferred`]) (the same result; off only to test that). `WAIT`
/// ([`march_waits`]) is chosen once per scene too: its copy leaves out the normals
/// found and the samples shaded in the loop.
///
/// Each sample: its density ([`Chunk::density`]), its normal
/// ([`sample_normal`]), its colour and opacity added ([`accumulate`]), the
/// ray bent where the index of refraction changes ([`bend`]).
fn march<const COMMON: bool, const WAIT: bool>(
    scene: &Scene,
    ray: Ray,
    field: &Field,
    phase: f32,
    shortcuts: bool,
    deferred: &mut Option<Deferred>,
    waiting: &mut Option<Waiting>,
) -> Option<Sample> {
    let (min, max) = scene.bounds;
    let Some((t0, t1)) = slab(&ray, min, max) else {
        let (bg, bg_alpha) = scene.background.sample(ray.direction);
        return Some(Sample {
            rgba: [bg.x, bg.y, bg.z, bg_alpha],
            ..Sample::default()
        });
    };
    let step = scene.step;
    let basis = Basis::new(ray, step, (t0, t1), phase, field.support, scene);
    if basis.first == u32::MAX {
        return Some(missing_support(scene, &basis));
    }
    let mut seg = Segment {
        basis,
        chunk: Chunk::empty(),
    };
    let mut w = Walk {
        k: 0,
        previous: None,
        path: 0.0,
        medium_index: if COMMON {
            None
        } else {
            scene.refraction.as_ref().map(|c| c.eval1(0.0))
        },
        budget: scene.budget,
    };
    let mut colour = Vec3::ZERO;
    let mut g = Gathered::default();
    let policy = Policy::new::<COMMON, WAIT>(scene, shortcuts);

    loop {
        if !w.skip_empty(&seg.basis, step) {
            break;
        }
        let t = seg.basis.t(w.k, step);
        if t > seg.basis.t1 || w.budget == 0 || t > seg.basis.last {
            break;
        }
        w.budget -= 1;
        let x = seg.basis.ray.at(t);
        let (f, alpha_k) = seg.chunk.density(w.k, &seg.basis, scene, field);
        let found = sample_normal(scene, field, policy, &mut seg, &w, &mut g, (x, f, alpha_k));
        if f > 0.0 && g.depth == 0.0 {
            g.depth = w.path + t;
        }
        let (sample, gathered) = ((x, f, alpha_k), (&mut g, &mut colour));
        if accumulate::<COMMON>(
            scene, field, policy, shortcuts, &seg, &w, gathered, sample, &found, deferred,
        ) {
            break;
        }
        let at = (t, x, f);
        if !COMMON
            && bend(
                scene,
                field,
                phase,
                shortcuts,
                &mut seg,
                &mut w,
                &mut g,
                at,
                found.normal,
            )
        {
            continue;
        }
        w.previous = Some(f);
        w.k += 1;
        w.skip_zeros(&seg.chunk, f);
    }

    *waiting = Some(Waiting {
        basis: seg.basis,
        colour,
        alpha: g.alpha,
        weighted_density: g.weighted_density,
        depth: g.depth,
        first_normal: g.first_normal,
    });
    None
}

/// What a ray that misses the support records: no sample would be
/// evaluated, and the loop of [`march`] would end at once; what it would
/// return, without setting up its chunk and batch.
#[inline(always)]
fn missing_support(scene: &Scene, basis: &Basis) -> Sample {
    let (bg, bg_alpha) = scene.background.sample(basis.ray.direction);
    let (colour, alpha) = (Vec3::ZERO, 0.0f32);
    let rgb = colour + bg * (1.0 - alpha);
    Sample {
        rgba: [rgb.x, rgb.y, rgb.z, alpha + bg_alpha * (1.0 - alpha)],
        ..Sample::default()
    }
}

/// The normal of sample k at `x` of density `f` and opacity `alpha_k`:
/// passed (a transparent soft sample, [`Policy::lazy`]), waiting (the
/// gradients wait, [`Policy::gradients_wait`]), or found now by the scene's
/// gradient; at a hard region's first sample, from the object's own D.
#[inline(always)]
#[allow(clippy::too_many_arguments)]
fn sample_normal(
    scene: &Scene,
    field: &Field,
    policy: Policy,
    seg: &mut Segment,
    w: &Walk,
    g: &mut Gathered,
    (x, f, alpha_k): (Vec3, f32, f32),
) -> SampleNormal {
    let step = scene.step;
    let f_at = |x: Vec3| scene.density.eval(x, field);
    let (basis, k, previous, lit) = (&seg.basis, w.k, w.previous, policy.lit);
    let mut found = SampleNormal {
        normal: None,
        waits: None,
        hard_waits: false,
        pass: false,
    };
    let soft = f > 0.0 && f < 1.0;
    found.pass = policy.lazy && soft && alpha_k == 0.0 && g.first_normal.is_some();
    if found.pass {
        if lit {
            g.passed = Some((g.passed.map_or(k, |(a, _)| a), k));
        }
    } else if policy.gradients_wait && soft {
        found.waits = Some(previous.unwrap_or_else(|| f_at(x - basis.du)));
    } else if soft && (lit || g.first_normal.is_none()) {
        found.normal = match scene.gradient {
            Gradient::Forward => {
                // Unlit, a ray reads only its first normal: that
                // sample's two neighbours, without the chunk's others.
                let (fv, fw) = if lit {
                    seg.chunk.neighbours(k, basis, scene, field, g.alpha)
                } else {
                    let mut p = Points::default();
                    let spare = outside(field).unwrap_or(x);
                    for l in 2..LANES {
                        p.set(l, spare);
                    }
                    p.set(0, x + basis.dv);
                    p.set(1, x + basis.dw);
                    let f = scene.density.eval_lanes(&p, field, scene.isa);
                    (f[0], f[1])
                };
                gradient_normal(&f_at, x, f, previous, fv, fw, basis)
            }
            Gradient::Central => central_normal_lanes(x, step, field, |p| {
                scene.density.eval_lanes(p, field, scene.isa)
            }),
            Gradient::Dual => dual_normal(scene, x, field),
        };
    } else if f >= 1.0 && previous.is_none_or(|p| p < 1.0) && (lit || g.first_normal.is_none()) {
        // The ray reaches a hard region, where f = 1 and ∇f = 0: the
        // object's own D gives the normal, over a stencil wide enough to
        // reach the soft region from a sample up to a step inside.
        // Where the gradients wait, so does this one.
        if policy.gradients_wait {
            found.hard_waits = true;
        } else {
            found.normal = central_normal_lanes(x, 2.0 * step, field, |p| {
                scene.object.eval_object_lanes(p, field, scene.isa)
            });
        }
    }
    found
}

/// Adds sample k (`sample`: its point, f and α_k) to what the ray has
/// gathered: into the batch of waiting samples, or shaded now. True when
/// the ray is opaque enough to stop.
#[inline(always)]
#[allow(clippy::too_many_arguments)]
fn accumulate<const COMMON: bool>(
    scene: &Scene,
    field: &Field,
    policy: Policy,
    shortcuts: bool,
    seg: &Segment,
    w: &Walk,
    (g, colour): (&mut Gathered, &mut Vec3),
    (x, f, alpha_k): (Vec3, f32, f32),
    found: &SampleNormal,
    deferred: &mut Option<Deferred>,
) -> bool {
    let (basis, chunk, k) = (&seg.basis, &seg.chunk, w.k);
    let keys_wait = policy.keys_wait;
    if f > 0.0 && policy.gradients_wait {
        let deferred = deferred.get_or_insert_with(|| policy.batch());
        let weight = alpha_k * (1.0 - g.alpha);
        let own = match (found.waits, found.hard_waits) {
            (Some(behind), _) => Own::Waiting {
                x: chunk.x.get((k - chunk.start) as usize),
                behind,
            },
            (None, true) => Own::Hard { x },
            (None, false) => Own::Found(found.normal),
        };
        let base = waiting_base::<COMMON>(scene, x, f, field, keys_wait);
        deferred.push(own, f, base, weight, scene, basis, field, colour);
        g.alpha += weight;
        g.weighted_density += f * weight;
        if g.alpha >= scene.threshold {
            return true;
        }
    } else if f > 0.0 && !found.pass {
        let normal = found.normal;
        if normal.is_some() {
            g.last_normal = normal;
            g.passed = None;
            if g.first_normal.is_none() {
                g.first_normal = normal;
            }
        } else if let Some(range) = g.passed.take()
            && let Some(n) = latest_normal(scene, basis, range, field)
        {
            g.last_normal = Some(n);
        }
        let shading_normal = normal
            .or(g.last_normal)
            .unwrap_or(Normal::of_unit(-basis.ray.direction));
        let weight = alpha_k * (1.0 - g.alpha);
        if policy.defers {
            let deferred = deferred.get_or_insert_with(|| policy.batch());
            let own = Own::Found(Some(shading_normal));
            let base = waiting_base::<COMMON>(scene, x, f, field, keys_wait);
            deferred.push(own, f, base, weight, scene, basis, field, colour);
        } else {
            let reuse = !COMMON && shortcuts && normal.is_none() && scene.position_free_shading;
            let sample_colour = shade_now::<COMMON>(
                scene,
                field,
                basis,
                g,
                (x, f),
                shading_normal,
                reuse,
                policy.lit,
            );
            *colour += sample_colour * weight;
        }
        g.alpha += weight;
        g.weighted_density += f * weight;
        if g.alpha >= scene.threshold {
            return true;
        }
    }
    false
}

/// The colour of a sample at x of density f shaded now with
/// `shading_normal`. Without a normal of its own (`reuse`) a sample takes
/// the last one, and perhaps the latest such sample's colour (in the
/// general copy: the common case's rays stop at a hard region, where the
/// runs are, unless an alpha map makes it transparent).
#[inline(always)]
#[allow(clippy::too_many_arguments)]
fn shade_now<const COMMON: bool>(
    scene: &Scene,
    field: &Field,
    basis: &Basis,
    g: &mut Gathered,
    (x, f): (Vec3, f32),
    shading_normal: Normal,
    reuse: bool,
    lit: bool,
) -> Vec3 {
    let shading_normal = shading_normal.unit();
    let key = reuse.then(|| (f.to_bits(), shading_normal.to_array().map(f32::to_bits)));
    match (key, g.shaded) {
        (Some(key), Some((held, colour))) if key == held => {
            #[cfg(test)]
            tests::REUSED.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
            colour
        }
        _ => {
            let colour = sample_colour::<COMMON>(scene, x, f, shading_normal, basis, field, lit);
            if let Some(key) = key {
                g.shaded = Some((key, colour));
            }
            colour
        }
    }
}

/// Bends the ray at sample (t, x, f) where the index of refraction
/// changes: the index at the previous sample's f was compared with (or
/// became) n1, so the same f changes nothing. True when the ray goes on
/// along a new segment (from sample 1 of it).
#[inline(always)]
#[allow(clippy::too_many_arguments)]
fn bend(
    scene: &Scene,
    field: &Field,
    phase: f32,
    shortcuts: bool,
    seg: &mut Segment,
    w: &mut Walk,
    g: &mut Gathered,
    (t, x, f): (f32, Vec3, f32),
    normal: Option<Normal>,
) -> bool {
    let (Some(refraction), Some(n1)) = (scene.refraction.as_ref(), w.medium_index) else {
        return false;
    };
    let same = shortcuts && w.previous.is_some_and(|p| p.to_bits() == f.to_bits());
    let n2 = if same { n1 } else { refraction.eval1(f) };
    if (n2 - n1).abs() > 1e-6 {
        w.medium_index = Some(n2);
        let f_at = |x: Vec3| scene.density.eval(x, field);
        let n = normal.or_else(|| match scene.gradient {
            Gradient::Dual => dual_normal(scene, x, field),
            _ => {
                let (fv, fw) = seg.chunk.neighbours(w.k, &seg.basis, scene, field, 0.0);
                gradient_normal(&f_at, x, f, w.previous, fv, fw, &seg.basis)
            }
        });
        if let Some(n) = n {
            let bent = refract(seg.basis.ray.direction, n.unit(), n1 / n2);
            let ray = Ray {
                origin: x,
                direction: bent,
            };
            let (min, max) = scene.bounds;
            if let Some((_, exit)) = slab(&ray, min, max) {
                w.path += t;
                seg.basis = Basis::new(ray, scene.step, (0.0, exit), phase, field.support, scene);
                seg.chunk = Chunk::empty();
                w.previous = None;
                g.shaded = None;
                w.k = 1;
                return true;
            }
        }
    }
    false
}

/// The colour a sample at x of density f contributes per unit of opacity:
/// its base colour (the colour map at its key, or the colour expression)
/// lit by [`shade`] with `shading_normal` (perturbed by the normal
/// expression). `COMMON`: see [`march`]'s copies.
#[inline(always)]
fn sample_colour<const COMMON: bool>(
    scene: &Scene,
    x: Vec3,
    f: f32,
    shading_normal: Vec3,
    basis: &Basis,
    field: &Field,
    lit: bool,
) -> Vec3 {
    let (shading_normal, base) = if COMMON {
        (shading_normal, base_colour::<true>(scene, x, f, field))
    } else {
        // Colours and textures belong to the object: its point, not the world's.
        let object_x = field.object_point(x);
        let shading_normal = if lit {
            pse::perturb_normal(&scene.expressions, object_x, f, shading_normal, field)
        } else {
            shading_normal // `shade` reads it only for lights
        };
        (shading_normal, object_colour(scene, object_x, f, field))
    };
    base * shade::<COMMON>(scene, x, shading_normal, basis, field)
}

/// The base colour of a sample at x of density f: the colour map at its
/// key, or the colour expression. `COMMON`: the key is f.
#[inline(always)]
fn base_colour<const COMMON: bool>(scene: &Scene, x: Vec3, f: f32, field: &Field) -> Vec3 {
    if COMMON {
        Vec3::from_array(scene.colour_map.eval(f))
    } else {
        object_colour(scene, field.object_point(x), f, field)
    }
}

/// What a waiting sample holds as its base colour ([`Deferred::base`]):
/// [`base_colour`], or where `keys_wait` the object's point, whose colour
/// the flush finds. (A function, always inlined: as a closure it was left
/// a call in the common copy.)
#[inline(always)]
fn waiting_base<const COMMON: bool>(
    scene: &Scene,
    x: Vec3,
    f: f32,
    field: &Field,
    keys_wait: bool,
) -> Vec3 {
    if keys_wait {
        field.object_point(x)
    } else {
        base_colour::<COMMON>(scene, x, f, field)
    }
}

/// [`base_colour`] at the object's point `object_x`.
#[inline(always)]
fn object_colour(scene: &Scene, object_x: Vec3, f: f32, field: &Field) -> Vec3 {
    let key = scene.colour_key(object_x, f, field);
    pse::surface_colour(
        &scene.expressions,
        &scene.colour_map,
        object_x,
        f,
        key,
        field,
    )
}

/// The normal of the latest soft sample in `first ..= last` of `basis` whose
/// normal does not vanish: what the marcher would have recorded as its last
/// normal had it not passed those samples (central differences or dual
/// numbers, functions of the point alone; f again from the scalar path, the
/// bits of the lanes).
#[cold]
fn latest_normal(
    scene: &Scene,
    basis: &Basis,
    (first, last): (u32, u32),
    field: &Field,
) -> Option<Normal> {
    #[cfg(test)]
    tests::FALLBACKS.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
    let f_at = |x: Vec3| scene.density.eval(x, field);
    (first..=last).rev().find_map(|k| {
        let x = basis.ray.at(basis.t(k, scene.step));
        let f = f_at(x);
        if !(f > 0.0 && f < 1.0) {
            return None;
        }
        match scene.gradient {
            Gradient::Central => {
                crate::render::lighting::central_normal(&f_at, x, scene.step).map(Normal::of_unit)
            }
            Gradient::Dual => dual_normal(scene, x, field),
            Gradient::Forward => None,
        }
    })
}

/// The unit outward normal at x from the paper's finite differences
/// `[f(x) - f(x - Δx_μ), f(x + Δx_ν) - f(x), f(x + Δx_ω) - f(x)]`, converted to
/// xyz by the matrix whose rows are the ray basis, negated (density grows inwards).
/// `fv = f(x + Δx_ν)` and `fw = f(x + Δx_ω)` come evaluated with their
/// neighbours'; `f(x − Δx_μ)` is the previous sample when there is one.
#[inline]
fn gradient_normal(
    f_at: &impl Fn(Vec3) -> f32,
    x: Vec3,
    f: f32,
    previous: Option<f32>,
    fv: f32,
    fw: f32,
    basis: &Basis,
) -> Option<Normal> {
    let behind = previous.unwrap_or_else(|| f_at(x - basis.du));
    let g = basis.du * (f - behind) + basis.dv * (fv - f) + basis.dw * (fw - f);
    Normal::of_gradient(g)
}

/// [`crate::render::lighting::central_normal`] of a field evaluated `LANES` points
/// at a time (the scene's density, or the objects' own D), its six points
/// evaluated together in one call of the lane code (the other lanes at a
/// point outside the support): the same bits.
#[inline]
fn central_normal_lanes(
    x: Vec3,
    h: f32,
    field: &Field,
    eval: impl Fn(&Points) -> Lanes,
) -> Option<Normal> {
    let mut p = Points::default();
    let spare = outside(field).unwrap_or(x);
    for l in 6..LANES {
        p.set(l, spare);
    }
    for (l, q) in stencil(x, h).into_iter().enumerate() {
        p.set(l, q);
    }
    let f = eval(&p);
    central_normal_of(&f[..6])
}

/// The six points of [`central_normal_lanes`]' stencil: x ± h along x, y
/// and z in turn.
#[inline(always)]
fn stencil(x: Vec3, h: f32) -> [Vec3; 6] {
    let [a, b, c] = [Vec3::X, Vec3::Y, Vec3::Z];
    [
        x + a * h,
        x - a * h,
        x + b * h,
        x - b * h,
        x + c * h,
        x - c * h,
    ]
}

/// The normal of the central differences of the field at the six points of
/// a [`stencil`].
#[inline(always)]
fn central_normal_of(f: &[f32]) -> Option<Normal> {
    Normal::of_gradient(Vec3::new(f[0] - f[1], f[2] - f[3], f[4] - f[5]))
}

/// The unit outward normal at x from the derivative of the density
/// (forward-mode differentiation, [`crate::math::dual`]), or `None` where the
/// gradient vanishes.
#[inline]
fn dual_normal(scene: &Scene, x: Vec3, field: &Field) -> Option<Normal> {
    let g = scene
        .density
        .eval_dual(
            &crate::math::dual::DualPoint::at(x),
            field,
            crate::math::dual::spacing(scene.step),
        )
        .d;
    Normal::of_gradient(g)
}

/// A unit outward normal as the density gradient g it comes from and
/// |g|²: the normal is `−g / √|g|²` ([`Normal::unit`]), found where it is
/// read, so that the samples whose light waits ([`Deferred`]) find theirs
/// together.
#[derive(Clone, Copy, Debug)]
struct Normal {
    g: Vec3,
    len2: f32,
}

impl Normal {
    /// The normal of the gradient g, `None` where g vanishes.
    #[inline(always)]
    fn of_gradient(g: Vec3) -> Option<Normal> {
        let len2 = g.length_squared();
        (len2 > 1e-30).then_some(Normal { g, len2 })
    }

    /// The unit vector n: −(−n) / √1 has the bits of n.
    #[inline(always)]
    fn of_unit(n: Vec3) -> Normal {
        Normal { g: -n, len2: 1.0 }
    }

    /// The unit normal, `−g / √|g|²`.
    #[inline(always)]
    fn unit(self) -> Vec3 {
        -self.g / self.len2.sqrt()
    }
}

/// Light reaching the eye from a unit of material at x with unit normal n, seen
/// along the direction of `basis`: ambient plus diffuse and Blinn–Phong
/// specular from every light (`COMMON`: a scene without shadows).
#[inline]
fn shade<const COMMON: bool>(
    scene: &Scene,
    x: Vec3,
    n: Vec3,
    basis: &Basis,
    field: &Field,
) -> Vec3 {
    let dir = basis.ray.direction;
    let mut light = scene.ambient;
    for (i, source) in scene.lights.iter().enumerate() {
        // The half vector where the basis holds it.
        let (l, colour, distance, half) = match *source {
            Light::Directional { direction, colour } => {
                (direction, colour, f32::INFINITY, basis.halves.get(i))
            }
            Light::Point { position, colour } => {
                let to = position - x;
                let d2 = to.length_squared().max(1e-4);
                let d = d2.sqrt();
                (to / d, colour / d2, d, None)
            }
        };
        let lambert = n.dot(l);
        if lambert <= 0.0 {
            continue;
        }
        let colour = if !COMMON && scene.shadows {
            colour * crate::render::lighting::transmittance(scene, field, x, n, l, distance)
        } else {
            colour
        };
        let mut response = scene.diffuse * lambert;
        if scene.specular > 0.0 {
            let h = half
                .copied()
                .unwrap_or_else(|| (l - dir).normalize_or_zero());
            let nh = n.dot(h);
            if nh > 0.0 {
                response += scene.specular * fastmath::pow01(nh, scene.shininess);
            }
        }
        light += colour * response;
    }
    light
}

/// Samples of one ray whose colour waits for their light: the shading
/// normal, density and compositing weight of each, up to [`LANES`]. The
/// light of all of them is found at once ([`shade_lanes`]), and their colours
/// are added in the order of the samples, `colour += (base · light) · weight`
/// as [`march`] adds them one by one: the same bits.
///
/// Where it `resolves`, each sample comes with its own normal or none
/// ([`Own`]), or with what its gradient needs: the neighbours of the
/// waiting samples are evaluated together at the flush, and each sample
/// takes its own normal, else the last one found before it (kept from
/// flush to flush), else −d, as [`march`] would have.
struct Deferred {
    /// The gradients g and |g|² of the shading normals ([`Normal`]).
    gradient: Points,
    len2: Lanes,
    /// f and the base colour ([`base_colour`]) of each sample; where
    /// `keys_wait`, its object point until the flush finds its colour.
    f: Lanes,
    base: Points,
    /// Whether the colour map's keys (the strata) wait for the flush, to
    /// be found together ([`Scene::colour_keys`]).
    keys_wait: bool,
    weight: Lanes,
    len: usize,
    /// Whether samples come with their own normals, to be resolved here.
    resolves: bool,
    /// Where it resolves: bit l of `found` says that sample l has its own
    /// normal (in `gradient` and `len2`); bit l of `waiting`, that it is
    /// found from the point x and f(x − Δx_μ) held for it.
    found: u32,
    waiting: u32,
    /// Bit l: sample l's normal is found from the central differences of
    /// the object's D about its point x ([`Own::Hard`]).
    hard: u32,
    x: Points,
    behind: Lanes,
    /// The first and the last normal found on the ray.
    first: Option<Normal>,
    last: Option<Normal>,
}

/// A sample's own normal, as the marcher hands it to a [`Deferred`].
enum Own {
    /// Found already (or none: the sample takes the last one).
    Found(Option<Normal>),
    /// From the forward differences at point x, f(x − Δx_μ) being `behind`.
    Waiting { x: Vec3, behind: f32 },
    /// From the central differences of the object's D about point x, where
    /// the ray reaches a hard region ([`central_normal_lanes`]).
    Hard { x: Vec3 },
}

impl Default for Deferred {
    fn default() -> Deferred {
        Deferred {
            gradient: Points::default(),
            // Lanes not yet held are normalised too (and not read).
            len2: [1.0; LANES],
            f: [0.0; LANES],
            base: Points::default(),
            keys_wait: false,
            weight: [0.0; LANES],
            len: 0,
            resolves: false,
            found: 0,
            waiting: 0,
            hard: 0,
            x: Points::default(),
            behind: [0.0; LANES],
            first: None,
            last: None,
        }
    }
}

impl Deferred {
    /// Adds a sample with its own normal (where it does not `resolve`, the
    /// shading normal the marcher resolved), flushing into `colour` when
    /// full.
    #[inline(always)]
    #[allow(clippy::too_many_arguments)]
    fn push(
        &mut self,
        own: Own,
        f: f32,
        base: Vec3,
        weight: f32,
        scene: &Scene,
        basis: &Basis,
        field: &Field,
        colour: &mut Vec3,
    ) {
        match own {
            Own::Found(None) => {}
            Own::Found(Some(normal)) => self.hold(self.len, normal),
            Own::Waiting { x, behind } => {
                self.x.set(self.len, x);
                self.behind[self.len] = behind;
                self.waiting |= 1 << self.len;
            }
            Own::Hard { x } => {
                self.x.set(self.len, x);
                self.hard |= 1 << self.len;
            }
        }
        self.f[self.len] = f;
        self.base.set(self.len, base);
        self.weight[self.len] = weight;
        self.len += 1;
        if self.len == LANES {
            self.flush(scene, basis, field, colour);
        }
    }

    /// Holds `normal` as sample l's.
    #[inline(always)]
    fn hold(&mut self, l: usize, normal: Normal) {
        self.gradient.set(l, normal.g);
        self.len2[l] = normal.len2;
        self.found |= 1 << l;
    }

    /// Adds the held samples' colours to `colour`, in order.
    #[inline(never)]
    fn flush(&mut self, scene: &Scene, basis: &Basis, field: &Field, colour: &mut Vec3) {
        if self.len == 0 {
            return;
        }
        crate::math::simd::per_isa!(scene.isa, (
            batch: &mut Deferred = self, scene: &Scene = scene, basis: &Basis = basis,
            field: &Field = field, colour: &mut Vec3 = colour,
        ) -> () {
            scalar => batch.flush_on(scene, basis, field, colour, false),
            _lanes => batch.flush_on(scene, basis, field, colour, true),
        })
    }

    /// [`Deferred::flush`]'s work; with `simd` (a constant where it is
    /// inlined: into the copies per instruction set that `per_isa!` writes) the
    /// normals, the light and the highlights' powers are compiled for that
    /// set.
    #[inline(always)]
    fn flush_on(
        &mut self,
        scene: &Scene,
        basis: &Basis,
        field: &Field,
        colour: &mut Vec3,
        simd: bool,
    ) {
        if self.resolves {
            if self.waiting | self.hard != 0 {
                find_waiting(&mut [Some((basis, self))], scene, field);
            }
            for l in 0..self.len {
                if self.found & (1 << l) != 0 {
                    let own = Normal {
                        g: self.gradient.get(l),
                        len2: self.len2[l],
                    };
                    self.last = Some(own);
                    if self.first.is_none() {
                        self.first = Some(own);
                    }
                } else {
                    #[cfg(test)]
                    tests::TOOK_LAST.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
                    let normal = self.last.unwrap_or(Normal::of_unit(-basis.ray.direction));
                    self.gradient.set(l, normal.g);
                    self.len2[l] = normal.len2;
                }
            }
        }
        self.found = 0;
        if self.keys_wait {
            let keys = scene.colour_keys(&self.base, &self.f, self.len, field);
            for (l, &key) in keys[..self.len].iter().enumerate() {
                let object_x = self.base.get(l);
                let base = pse::surface_colour(
                    &scene.expressions,
                    &scene.colour_map,
                    object_x,
                    self.f[l],
                    key,
                    field,
                );
                self.base.set(l, base);
            }
        }
        if self.len <= LANES / 2 {
            self.shade::<{ LANES / 2 }>(scene, basis, colour, simd);
        } else {
            self.shade::<LANES>(scene, basis, colour, simd);
        }
        self.len = 0;
    }

    /// Adds the colours of the held samples (at most W) to `colour`, in
    /// order, their normals and light found W lanes at a time.
    #[inline(always)]
    fn shade<const W: usize>(&self, scene: &Scene, basis: &Basis, colour: &mut Vec3, simd: bool) {
        // `Normal::unit` lane by lane: the same operations, so the same bits.
        let mut normal = [[0.0; W]; 3];
        #[allow(clippy::needless_range_loop)] // lane l of four arrays
        for l in 0..W {
            let length = self.len2[l].sqrt();
            normal[0][l] = -self.gradient.x[l] / length;
            normal[1][l] = -self.gradient.y[l] / length;
            normal[2][l] = -self.gradient.z[l] / length;
        }
        let [r, g, b] = shade_lanes(scene, &normal, basis, simd);
        for l in 0..self.len {
            *colour += (self.base.get(l) * Vec3::new(r[l], g[l], b[l])) * self.weight[l];
        }
    }
}

/// [`shade`] (the common case: no shadows) of W samples at once (at most
/// [`LANES`]) along the direction of `basis`, under directional lights
/// only: each lane's red, green and blue have the bits `shade` gives, the
/// powers of the highlights taken on the scene's instruction-set path.
#[inline(always)]
fn shade_lanes<const W: usize>(
    scene: &Scene,
    n: &[[f32; W]; 3],
    basis: &Basis,
    simd: bool,
) -> [[f32; W]; 3] {
    let mut light = scene.ambient.to_array().map(|a| [a; W]);
    for (i, source) in scene.lights.iter().enumerate() {
        let Light::Directional {
            direction: l,
            colour,
        } = *source
        else {
            unreachable!("`Deferred` is used under directional lights only")
        };
        let lambert: [f32; W] =
            std::array::from_fn(|j| (n[0][j] * l.x) + (n[1][j] * l.y) + (n[2][j] * l.z));
        let mut response = lambert.map(|lambert| scene.diffuse * lambert);
        if scene.specular > 0.0 {
            let h = basis
                .halves
                .get(i)
                .copied()
                .unwrap_or_else(|| (l - basis.ray.direction).normalize_or_zero());
            let mut nh = [0.0; LANES];
            for j in 0..W {
                nh[j] = (n[0][j] * h.x) + (n[1][j] * h.y) + (n[2][j] * h.z);
            }
            let live = u32::MAX >> (32 - W);
            let power = if simd {
                fastmath::pow01_lanes_live(&nh, scene.shininess, live)
            } else {
                fastmath::pow01_on_live(scene.isa, &nh, scene.shininess, live)
            };
            for j in 0..W {
                if nh[j] > 0.0 {
                    response[j] += scene.specular * power[j];
                }
            }
        }
        for (c, light) in light.iter_mut().enumerate() {
            for j in 0..W {
                if lambert[j] > 0.0 {
                    light[j] += colour[c] * response[j];
                }
            }
        }
    }
    light
}

/// Snell's law: `d` bent at a surface of unit normal `n` from index n1 to n2
/// (`eta = n1 / n2`); total internal reflection mirrors it.
#[inline]
fn refract(d: Vec3, n: Vec3, eta: f32) -> Vec3 {
    let mut n = n;
    let mut cos_i = -n.dot(d);
    if cos_i < 0.0 {
        n = -n;
        cos_i = -cos_i;
    }
    let k = 1.0 - eta * eta * (1.0 - cos_i * cos_i);
    if k < 0.0 {
        (d + n * (2.0 * cos_i)).normalize()
    } else {
        (d * eta + n * (eta * cos_i - k.sqrt())).normalize()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// [`march`]'s sample of one ray.
    fn sample<const COMMON: bool>(
        scene: &Scene,
        ray: Ray,
        field: &Field,
        phase: f32,
        shortcuts: bool,
    ) -> Sample {
        let (mut deferred, mut waiting) = (None, None);
        let done = march_waits::<COMMON>(
            scene,
            ray,
            field,
            phase,
            shortcuts,
            &mut deferred,
            &mut waiting,
        );
        match (done, &waiting) {
            (Some(sample), _) => sample,
            (None, Some(w)) => finish(w, scene, field, &mut deferred),
            (None, None) => unreachable!("a ray that is not done waits"),
        }
    }
    use std::sync::atomic::{AtomicUsize, Ordering};

    /// How often a vanishing normal fell back on samples passed without one.
    pub(super) static FALLBACKS: AtomicUsize = AtomicUsize::new(0);

    /// The general loop's pixels of `scene` (24×24), each checked to have
    /// the same bits with the loop's shortcuts and without them.
    fn same_with_and_without_shortcuts(scene: &Scene, what: &str) -> Vec<Sample> {
        let field = scene.field(0);
        let mut pixels = Vec::new();
        for y in 0..24 {
            for x in 0..24 {
                let ray = scene.camera.ray(x, y, (0.5, 0.5));
                let fast = sample::<false>(scene, ray, &field, 0.25, true);
                let every = sample::<false>(scene, ray, &field, 0.25, false);
                assert_eq!(
                    fast.to_array().map(f32::to_bits),
                    every.to_array().map(f32::to_bits),
                    "{what}: pixel ({x}, {y})"
                );
                pixels.push(fast);
            }
        }
        pixels
    }

    /// How many samples took the colour of the one before.
    pub(super) static REUSED: AtomicUsize = AtomicUsize::new(0);

    /// How many calls evaluated the neighbours of more than one ray's
    /// waiting samples.
    pub(super) static ACROSS: AtomicUsize = AtomicUsize::new(0);

    #[test]
    fn a_group_of_rays_gives_each_ray_its_own_sample() {
        // Fur at a coarse step (a few soft samples a ray, the hard region
        // solid) and faint noisy matter (rays that flush on their own),
        // each row traced in groups of every size up to GROUP.
        let fur = "Scene(image: (width: 24, height: 24),
              camera: (eye: (0.0, 2.3, 2.9), look_at: (0.0, -0.15, 0.0), projection: Perspective(fov_y: 50.0)),
              lights: (ambient: (0.12, 0.12, 0.12), sources: [Directional(direction: (0.4, 0.9, 0.5), colour: (1.0, 1.0, 1.0))]),
              march: (bounds: (min: (-1.6, -0.6, -1.6), max: (1.6, 0.6, 1.6)), step: Diagonal(50), opacity: 40.0, threshold: 0.99),
              object: Torus(major_radius: 1.0, minor_radius: 0.475, softness: 0.25),
              modulation: [Fur(frequency: 40.0, bias: 0.3, gain: 0.9)],
              colour_map: (points: [(0.0, (0.55, 0.38, 0.22)), (1.0, (0.95, 0.85, 0.70))]))";
        let faint = "Scene(image: (width: 24, height: 24),
              camera: (eye: (0.0, 0.0, 3.0), look_at: (0.0, 0.0, 0.0), projection: Perspective(fov_y: 40.0)),
              lights: (ambient: (0.1, 0.1, 0.1), sources: [Directional(direction: (-0.5, 0.7, 0.6), colour: (0.8, 0.8, 0.8))]),
              march: (bounds: (min: (-1.2, -1.2, -1.2), max: (1.2, 1.2, 1.2)), step: Diagonal(120), opacity: 2.0),
              object: Sphere(radius: 0.6, softness: 0.8),
              modulation: [NoisyRadius(frequency: 3.0, amplitude: 0.15)],
              shading: (specular: 0.4, shininess: 20.0))";
        for (what, text) in [("fur", fur), ("faint", faint)] {
            let mut scene = Scene::from_text(text, "test", crate::Overrides::default()).unwrap();
            assert!(scene.light_waits, "{what}");
            let before = ACROSS.load(Ordering::Relaxed);
            for isa in Isa::available() {
                assert!(scene.set_isa(isa));
                let field = scene.field(0);
                for y in 0..24 {
                    let rays: Vec<Ray> = (0..24)
                        .map(|x| scene.camera.ray(x, y, (0.5, 0.5)))
                        .collect();
                    let alone: Vec<Sample> =
                        rays.iter().map(|&r| trace(&scene, r, &field)).collect();
                    for size in 1..=GROUP {
                        let mut grouped = vec![Sample::default(); rays.len()];
                        for (rays, out) in rays.chunks(size).zip(grouped.chunks_mut(size)) {
                            trace_group(&scene, rays, &field, out);
                        }
                        for (x, (a, b)) in alone.iter().zip(&grouped).enumerate() {
                            assert_eq!(
                                a.to_array().map(f32::to_bits),
                                b.to_array().map(f32::to_bits),
                                "{what}, {isa:?}, groups of {size}: pixel ({x}, {y})"
                            );
                        }
                    }
                }
            }
            assert!(
                ACROSS.load(Ordering::Relaxed) > before,
                "{what}: some call held more than one ray's samples"
            );
        }
    }

    /// How many samples whose normal was resolved by a [`Deferred`] took the
    /// last one (or −d).
    pub(super) static TOOK_LAST: AtomicUsize = AtomicUsize::new(0);

    #[test]
    fn reusing_a_run_of_samples_colour_changes_no_pixel() {
        // Blue glass in small: the hard region transparent by the alpha
        // map, the rays bent by the refraction map, lit by one light (runs
        // of f = 1) or by none (every sample after the first without a
        // normal of its own, f varying along the soft region).
        for lights in [
            "[Directional(direction: (-0.5, 0.7, 0.6), colour: (1.0, 1.0, 1.0))]",
            "[]",
        ] {
            let text = format!(
                "Scene(image: (width: 24, height: 24),
                  camera: (eye: (0.0, 0.0, 3.0), look_at: (0.0, 0.0, 0.0), projection: Perspective(fov_y: 40.0)),
                  lights: (ambient: (0.4, 0.4, 0.4), sources: {lights}),
                  march: (bounds: (min: (-1.2, -1.2, -1.2), max: (1.2, 1.2, 1.2)), step: Diagonal(120), opacity: 40.0),
                  object: Sphere(radius: 0.8, softness: 0.3),
                  modulation: [NoisyRadius(frequency: 3.0, amplitude: 0.15)],
                  colour_map: (points: [(0.0, (0.1, 0.2, 0.9)), (1.0, (0.9, 0.9, 1.0))]),
                  alpha_map: (points: [(0.0, 0.0), (1.0, 0.06)]),
                  refraction: (points: [(0.0, 1.0), (0.5, 1.0), (0.51, 1.5), (1.0, 1.5)]),
                  shading: (specular: 0.3))"
            );
            let scene = Scene::from_text(&text, "test", crate::Overrides::default()).unwrap();
            assert!(scene.position_free_shading && !scene.common_case);
            let before = REUSED.load(Ordering::Relaxed);
            let pixels = same_with_and_without_shortcuts(&scene, &format!("lights {lights}"));
            let seen = pixels.iter().filter(|p| p.density > 0.0).count();
            assert!(seen > 100, "the glass covers the image ({seen})");
            assert!(
                REUSED.load(Ordering::Relaxed) > before + 1000,
                "lights {lights}: runs of samples reused their colour"
            );
        }
    }

    #[test]
    fn deferred_light_changes_no_pixel() {
        // The light of up to LANES samples is found at once, and with
        // forward differences their gradients too (`Deferred`), in the
        // common copy and, for a scene with a colour index or expression,
        // in the general one; without shortcuts the general copy shades
        // each sample as it comes. Faint matter (many
        // samples a ray, so a ray flushes more than once, gradients waiting
        // across chunks), a hard region (its normal found at once), terraces
        // of constant density (their samples' gradients vanish and they take
        // the last normal), highlights, and more directional lights than a
        // basis holds half vectors for.
        let light = "Directional(direction: (-0.5, 0.7, 0.6), colour: (0.3, 0.3, 0.3))";
        let lights = format!(
            "lights: (ambient: (0.1, 0.1, 0.1), sources: [{light}, {light}, {light}, {light},
                Directional(direction: (0.6, -0.2, 0.7), colour: (0.2, 0.5, 0.9))])"
        );
        let noisy = format!(
            "Scene(image: (width: 24, height: 24),
              camera: (eye: (0.0, 0.0, 3.0), look_at: (0.0, 0.0, 0.0), projection: Perspective(fov_y: 40.0)),
              {lights},
              march: (bounds: (min: (-1.2, -1.2, -1.2), max: (1.2, 1.2, 1.2)), step: Diagonal(120), opacity: 2.0),
              object: Sphere(radius: 0.6, softness: 0.8),
              modulation: [NoisyRadius(frequency: 3.0, amplitude: 0.15)],
              colour_map: (points: [(0.0, (0.1, 0.2, 0.9)), (1.0, (0.9, 0.9, 1.0))]),
              shading: (specular: 0.4, shininess: 20.0))"
        );
        let terraces = format!(
            "Scene(image: (width: 24, height: 24),
              camera: (eye: (0.0, 0.0, 3.0), look_at: (0.0, 0.0, 0.0), projection: Perspective(fov_y: 40.0)),
              {lights},
              march: (bounds: (min: (-1.3, -1.3, -1.3), max: (1.3, 1.3, 1.3)), step: Diagonal(120), opacity: 1.0),
              object: Sphere(radius: 0.6, softness: 1.2),
              density: \"floor(D(x) * 4) / 4\",
              colour_map: (points: [(0.0, (0.1, 0.2, 0.9)), (1.0, (0.9, 0.9, 1.0))]),
              shading: (specular: 0.4, shininess: 20.0))"
        );
        // Strata keyed by noise and a colour expression: the general copy.
        let strata = noisy.replace(
            "colour_map:",
            "colour_index: Strata(frequency: 6.0, amplitude: 3.0, octaves: 3), colour_map:",
        );
        let expression = noisy.replace(
            "colour_map:",
            "colour: \"[0.5 + 0.5 * noise(4 * x), 0.6, d]\", colour_map:",
        );
        for (what, text, common) in [
            ("noisy", noisy, true),
            ("terraces", terraces, true),
            ("strata", strata, false),
            ("expression", expression, false),
        ] {
            let mut scene = Scene::from_text(&text, "test", crate::Overrides::default()).unwrap();
            assert_eq!(scene.common_case, common, "{what}");
            assert!(scene.light_waits, "{what}");
            let before = TOOK_LAST.load(Ordering::Relaxed);
            for isa in Isa::available() {
                assert!(scene.set_isa(isa));
                let field = scene.field(0);
                let mut long = 0;
                for y in 0..24 {
                    for x in 0..24 {
                        let ray = scene.camera.ray(x, y, (0.5, 0.5));
                        let deferred = if common {
                            sample::<true>(&scene, ray, &field, 0.25, true)
                        } else {
                            sample::<false>(&scene, ray, &field, 0.25, true)
                        };
                        let each = sample::<false>(&scene, ray, &field, 0.25, false);
                        assert_eq!(
                            deferred.to_array().map(f32::to_bits),
                            each.to_array().map(f32::to_bits),
                            "{what}, {isa:?}: pixel ({x}, {y})"
                        );
                        long += usize::from(deferred.rgba[3] > 0.0 && deferred.rgba[3] < 0.9);
                    }
                }
                assert!(
                    long > 20,
                    "{what}, {isa:?}: rays through faint matter ({long})"
                );
            }
            if what == "terraces" {
                assert!(
                    TOOK_LAST.load(Ordering::Relaxed) > before,
                    "{what}: some sample took the last normal"
                );
            }
        }
    }

    #[test]
    fn the_strata_keys_found_together_are_each_points_key() {
        // `Scene::colour_keys` packs every point's octaves into the noise
        // kernel's lanes; each key must have the bits of `colour_key`, for
        // any count of points and octaves, on every path.
        let mut r = crate::math::random::SplitMix64::new(5);
        for octaves in [1, 3, 5, 8, 13, 16] {
            let text = format!(
                "Scene(image: (width: 8, height: 8),
                  camera: (eye: (0.0, 0.0, 3.0), look_at: (0.0, 0.0, 0.0), projection: Perspective(fov_y: 40.0)),
                  march: (bounds: (min: (-1.2, -1.2, -1.2), max: (1.2, 1.2, 1.2)), step: Diagonal(120), opacity: 2.0),
                  object: Sphere(radius: 0.6, softness: 0.8),
                  colour_index: Strata(frequency: 9.0, amplitude: 4.0, octaves: {octaves}),
                  colour_map: (points: [(0.0, (0.1, 0.2, 0.9)), (1.0, (0.9, 0.9, 1.0))]),
                  flow: (0.1, 0.2, 0.0))"
            );
            let mut scene = Scene::from_text(&text, "test", crate::Overrides::default()).unwrap();
            for isa in Isa::available() {
                assert!(scene.set_isa(isa));
                let field = scene.field(3);
                for len in 1..=LANES {
                    let mut x = Points::default();
                    let mut f = [0.0; LANES];
                    for (l, f) in f[..len].iter_mut().enumerate() {
                        let p = Vec3::new(r.next_f32(), r.next_f32(), r.next_f32()) * 6.0 - 3.0;
                        x.set(l, p);
                        *f = r.next_f32();
                    }
                    let keys = scene.colour_keys(&x, &f, len, &field);
                    for l in 0..len {
                        assert_eq!(
                            keys[l].to_bits(),
                            scene.colour_key(x.get(l), f[l], &field).to_bits(),
                            "{octaves} octaves, {isa:?}, point {l} of {len}"
                        );
                    }
                }
            }
        }
    }

    #[test]
    fn passing_transparent_samples_changes_no_pixel() {
        // Terraces of constant density (normals vanish inside each), the
        // lowest transparent: a sample entering the next plateau whose
        // stencil stays on it falls back on the normals of samples passed
        // without one. Seen along the diagonal the terraces' normal is
        // diagonal too, so that stencil reaches only h/√3 across the step.
        for gradient in ["Central", "Dual"] {
            let text = format!(
                "Scene(image: (width: 24, height: 24),
                  camera: (eye: (2.5, 2.5, 2.5), look_at: (0.0, 0.0, 0.0), projection: Perspective(fov_y: 8.0)),
                  lights: (sources: [Directional(direction: (-0.5, 0.7, 0.6), colour: (1.0, 1.0, 1.0))]),
                  march: (bounds: (min: (-1.3, -1.3, -1.3), max: (1.3, 1.3, 1.3)), step: Diagonal(120), opacity: 8.0),
                  object: Sphere(radius: 0.6, softness: 1.2),
                  density: \"floor(D(x) * 4) / 4\",
                  alpha_map: (interpolation: Step, points: [(0.0, 0.0), (0.4, 1.0)]),
                  shading: (gradient: {gradient}, specular: 0.3))"
            );
            let scene = Scene::from_text(&text, "test", crate::Overrides::default()).unwrap();
            let before = FALLBACKS.load(Ordering::Relaxed);
            let pixels = same_with_and_without_shortcuts(&scene, gradient);
            let shaded = pixels.iter().filter(|p| p.rgba[3] > 0.5).count();
            assert!(
                shaded > 100,
                "{gradient}: the sphere covers the image ({shaded})"
            );
            assert!(
                FALLBACKS.load(Ordering::Relaxed) > before,
                "{gradient}: some normal fell back on passed samples"
            );
        }
    }

    #[test]
    fn snell() {
        // Straight through at normal incidence.
        let d = refract(Vec3::NEG_Z, Vec3::Z, 1.0 / 1.5);
        assert!((d - Vec3::NEG_Z).length() < 1e-6);
        // 45° into glass: sin θt = sin 45° / 1.5.
        let d = refract(Vec3::new(1.0, 0.0, -1.0).normalize(), Vec3::Z, 1.0 / 1.5);
        assert!((d.x - std::f32::consts::FRAC_1_SQRT_2 / 1.5).abs() < 1e-6);
        // Total internal reflection leaving glass at a grazing angle.
        let d = refract(Vec3::new(1.0, 0.0, -0.2).normalize(), Vec3::Z, 1.5);
        assert!(d.z > 0.0);
    }

    #[test]
    fn basis_is_orthogonal() {
        for d in [Vec3::X, Vec3::Y, Vec3::new(0.3, -0.4, 0.8).normalize()] {
            let (v, w) = perpendiculars(d, 0.1);
            assert!(v.dot(d).abs() < 1e-6 && w.dot(d).abs() < 1e-6 && v.dot(w).abs() < 1e-6);
            assert!((v.length() - 0.1).abs() < 1e-6 && (w.length() - 0.1).abs() < 1e-6);
        }
    }
}
