//! Jittered supersampling and motion blur, the extensions the 1989 paper names as
//! future work.
//!
//! Sample `s` of pixel (x, y) draws its random numbers from a generator seeded by
//! `hash(x, y, s, scene seed)`, never from a thread or an order, so any pixel can
//! be re-rendered alone and a farm renders the same bytes as one process. Sample
//! `s < m²` (m = ⌊√spp⌋) lies in stratum `(s mod m, s div m)` of the pixel; each
//! sample also shifts the phase of its marching steps (so the fixed step does not
//! band) and, with a shutter, its time within `[frame, frame + shutter)` (so noise
//! drifting with `flow` blurs). The samples are averaged in index order.
//! With one sample per pixel nothing is jittered: the ray goes through the pixel
//! centre at the frame's time, exactly as without supersampling.

use crate::math::random::{SplitMix64, hash};
use crate::render::film::Sample;
use crate::render::march;
use crate::scene::Scene;
use crate::scene::camera::Ray;

/// Where and when one sample of a pixel looks.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PixelSample {
    /// Position within the pixel, each in [0, 1) ((0.5, 0.5) is the centre).
    pub jitter: (f32, f32),
    /// Phase of the marching steps, in [0, 1): samples at `t0 + (k + phase)·step`.
    pub phase: f32,
    /// Time in frames.
    pub time: f32,
}

/// Sample `s` of pixel (x, y) of `frame` for a scene with `spp` samples per
/// pixel, `shutter` and `seed`.
pub fn pixel_sample(
    x: u32,
    y: u32,
    s: u32,
    frame: u32,
    spp: u32,
    shutter: f32,
    seed: u64,
) -> PixelSample {
    if spp <= 1 {
        return PixelSample {
            jitter: (0.5, 0.5),
            phase: 0.0,
            time: frame as f32,
        };
    }
    let mut rng = SplitMix64::new(hash(&[u64::from(x), u64::from(y), u64::from(s), seed]));
    let (u, v) = (rng.next_f32(), rng.next_f32());
    let m = spp.isqrt();
    let jitter = if s < m * m {
        let inv = 1.0 / m as f32;
        (((s % m) as f32 + u) * inv, ((s / m) as f32 + v) * inv)
    } else {
        (u, v)
    };
    let phase = rng.next_f32();
    // Stratified in time as well: sample s opens in the s-th slice of the shutter.
    let slice = (s as f32 + rng.next_f32()) / spp as f32;
    PixelSample {
        jitter,
        phase,
        time: frame as f32 + shutter * slice,
    }
}

/// The value of pixel (x, y) of `frame`: the mean of the scene's samples.
pub fn render_pixel(scene: &Scene, x: u32, y: u32, frame: u32) -> Sample {
    let spp = scene.spp;
    if spp <= 1 {
        let field = scene.field(frame);
        return march::trace(scene, scene.camera.ray(x, y, (0.5, 0.5)), &field);
    }
    let mut sum = [0.0f32; Sample::CHANNELS];
    for s in 0..spp {
        let p = pixel_sample(x, y, s, frame, spp, scene.shutter, scene.seed);
        let field = scene.field_at(p.time);
        let sample =
            march::trace_with_phase(scene, scene.camera.ray(x, y, p.jitter), &field, p.phase);
        for (acc, v) in sum.iter_mut().zip(sample.to_array()) {
            *acc += v;
        }
    }
    let n = spp as f32;
    Sample::from_array(sum.map(|v| v / n))
}

/// [`render_pixel`] of each of `pixels` into `out` (as many), the same
/// samples: with one sample per pixel, [`march::GROUP`] rays at a time
/// ([`march::trace_group`]).
pub fn render_pixels_into(scene: &Scene, pixels: &[(u32, u32)], frame: u32, out: &mut [Sample]) {
    assert_eq!(pixels.len(), out.len());
    if scene.spp > 1 {
        for (&(x, y), out) in pixels.iter().zip(out) {
            *out = render_pixel(scene, x, y, frame);
        }
        return;
    }
    let field = scene.field(frame);
    for (pixels, out) in pixels
        .chunks(march::GROUP)
        .zip(out.chunks_mut(march::GROUP))
    {
        let rays: [Ray; march::GROUP] = scene.camera.centre_rays(pixels);
        march::trace_group(scene, &rays[..pixels.len()], &field, out);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::{Overrides, Scene};

    const SCENE: &str = "Scene(image: (width: 24, height: 24),
        camera: (eye: (0.0, 0.0, 3.4), look_at: (0.0, 0.0, 0.0), projection: Perspective(fov_y: 40.0)),
        march: (bounds: (min: (-1.05, -1.05, -1.05), max: (1.05, 1.05, 1.05)), step: Length(0.02), opacity: 40.0),
        object: Sphere(radius: 0.5, softness: 1.0),
        distortion: (terms: [(amplitude: 0.26, frequency: 4.0, shift: 0.5,
            transfer: Curve(interpolation: Spline, points: [(0.0, 0.0), (0.22, 1.0), (0.78, 1.0), (1.0, 0.0)]))]),
        alpha_map: (interpolation: Step, points: [(0.0, 0.0), (0.5, 1.0)]),
        flow: (0.0, 0.3, 0.0),
        sampling: (spp: 4, shutter: 0.5))";

    fn scene(spp: u32) -> Scene {
        let overrides = Overrides {
            spp: Some(spp),
            ..Overrides::default()
        };
        Scene::from_text(SCENE, "test", overrides).unwrap()
    }

    #[test]
    fn one_sample_per_pixel_is_the_unsampled_render() {
        let s = scene(1);
        for frame in [0, 3] {
            let film = crate::render::render(&s, frame, &|_| {});
            let field = s.field(frame);
            for y in 0..24 {
                for x in 0..24 {
                    let plain = march::trace(&s, s.camera.ray(x, y, (0.5, 0.5)), &field);
                    assert_eq!(
                        film.get(x, y).to_array().map(f32::to_bits),
                        plain.to_array().map(f32::to_bits)
                    );
                }
            }
        }
    }

    #[test]
    fn supersampling_averages_jittered_samples() {
        let (one, four) = (scene(1), scene(4));
        let a = crate::render::render(&one, 2, &|_| {});
        let b = crate::render::render(&four, 2, &|_| {});
        let mut differ = 0;
        for y in 0..24 {
            for x in 0..24 {
                let (p, q) = (a.get(x, y), b.get(x, y));
                assert!(q.is_finite());
                assert!((0.0..=1.0 + 1e-6).contains(&q.rgba[3]));
                differ += usize::from(p != q);
            }
        }
        // Edges and the blurred texture change; the empty corners do not.
        assert!(differ > 24 && differ < 24 * 24, "{differ}");
        // Pixel (x, y) alone equals the same pixel of the whole image.
        assert_eq!(render_pixel(&four, 11, 13, 2), b.get(11, 13));
    }

    #[test]
    fn one_sample_is_the_pixel_centre_at_the_frame() {
        let p = pixel_sample(3, 4, 0, 7, 1, 0.5, 1);
        assert_eq!(
            p,
            PixelSample {
                jitter: (0.5, 0.5),
                phase: 0.0,
                time: 7.0
            }
        );
    }

    #[test]
    fn samples_are_stratified_reproducible_and_within_the_shutter() {
        let spp = 16;
        let mut cells = std::collections::HashSet::new();
        for s in 0..spp {
            let p = pixel_sample(10, 20, s, 3, spp, 0.5, 99);
            assert_eq!(p, pixel_sample(10, 20, s, 3, spp, 0.5, 99));
            assert!((0.0..1.0).contains(&p.jitter.0) && (0.0..1.0).contains(&p.jitter.1));
            assert!((0.0..1.0).contains(&p.phase));
            assert!((3.0..3.5).contains(&p.time), "{}", p.time);
            cells.insert(((p.jitter.0 * 4.0) as u32, (p.jitter.1 * 4.0) as u32));
        }
        // One sample in each of the 4×4 strata.
        assert_eq!(cells.len(), 16);
        // Another pixel or seed draws other numbers.
        assert_ne!(
            pixel_sample(10, 20, 0, 3, spp, 0.5, 99),
            pixel_sample(11, 20, 0, 3, spp, 0.5, 99)
        );
        assert_ne!(
            pixel_sample(10, 20, 0, 3, spp, 0.5, 99),
            pixel_sample(10, 20, 0, 3, spp, 0.5, 98)
        );
        // No shutter: every sample at the frame's time.
        assert_eq!(pixel_sample(1, 2, 5, 3, spp, 0.0, 99).time, 3.0);
    }
}
