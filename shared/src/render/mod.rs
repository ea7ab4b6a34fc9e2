//! Rendering whole images or any set of pixels.
//!
//! A pixel's value is a function of (scene, pixel, frame, sample) only: each is
//! traced on its own, with nothing shared between pixels but the immutable scene.
//! Parallelism comes from the caller's rayon pool, so the same image comes out of
//! 1 thread or 64, of one machine or a farm.

//!
//! The top layer, above [`crate::scene`]: [`march`] walks the rays of the
//! scene's camera ([`crate::scene::camera`]) through the density, [`lighting`] shades, [`sampling`] jitters and
//! filters, [`film`] records, [`interleave`] cuts images into the farm's
//! units, [`bake`] samples H(x) on a lattice, [`probe`] digests this
//! build's arithmetic and [`request`] says what to render (a scene, its
//! overrides, frames and pixel format).

pub mod bake;
pub mod film;
pub mod interleave;
pub mod lighting;
pub mod march;
pub mod probe;
pub mod request;
pub mod sampling;

use rayon::prelude::*;

use crate::render::film::{Film, Sample};
use crate::render::march::GROUP;
use crate::render::sampling::render_pixels_into;
use crate::scene::Scene;

/// The value of pixel (x, y) of `frame`: one ray through the pixel centre, or the
/// mean of the scene's jittered samples ([`crate::render::sampling`]).
#[inline]
pub fn render_pixel(scene: &Scene, x: u32, y: u32, frame: u32) -> Sample {
    crate::render::sampling::render_pixel(scene, x, y, frame)
}

/// Renders the whole image of `frame` on the current rayon pool, calling
/// `progress(rows)` as rows complete (from any thread, in any order).
pub fn render(scene: &Scene, frame: u32, progress: &(dyn Fn(u64) + Sync)) -> Film {
    let mut film = Film::new(scene.width, scene.height);
    let width = scene.width as usize;
    film.pixels_mut()
        .par_chunks_mut(width)
        .enumerate()
        .for_each(|(y, row)| {
            let mut pixels = [(0, 0); GROUP];
            for (x0, out) in row.chunks_mut(GROUP).enumerate() {
                let pixels = &mut pixels[..out.len()];
                for (i, p) in pixels.iter_mut().enumerate() {
                    *p = ((x0 * GROUP + i) as u32, y as u32);
                }
                render_pixels_into(scene, pixels, frame, out);
            }
            progress(1);
        });
    film
}

/// Renders the listed pixels of `frame` on the current rayon pool, in the
/// order given, [`GROUP`] at a time.
pub fn render_pixels(scene: &Scene, frame: u32, pixels: &[(u32, u32)]) -> Vec<Sample> {
    let mut out = vec![Sample::default(); pixels.len()];
    out.par_chunks_mut(GROUP)
        .zip(pixels.par_chunks(GROUP))
        .for_each(|(out, pixels)| render_pixels_into(scene, pixels, frame, out));
    out
}

/// [`render_pixels`], given up as soon as `stop` is set (checked before each
/// group of [`GROUP`] pixels): `None` then. The pixels it returns are [`render_pixels`]' own.
pub fn render_pixels_until(
    scene: &Scene,
    frame: u32,
    pixels: &[(u32, u32)],
    stop: &std::sync::atomic::AtomicBool,
) -> Option<Vec<Sample>> {
    let mut out = vec![Sample::default(); pixels.len()];
    let done = out
        .par_chunks_mut(GROUP)
        .zip(pixels.par_chunks(GROUP))
        .all(|(out, pixels)| {
            let go = !stop.load(std::sync::atomic::Ordering::Relaxed);
            if go {
                render_pixels_into(scene, pixels, frame, out);
            }
            go
        });
    done.then_some(out)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::{Overrides, Scene};
    use std::sync::atomic::AtomicBool;

    #[test]
    fn a_render_until_stopped_is_render_pixels_or_nothing() {
        let scene = Scene::load(
            concat!(env!("CARGO_MANIFEST_DIR"), "/../scenes/noisy_sphere.ron"),
            Overrides {
                width: Some(16),
                height: Some(16),
                ..Overrides::default()
            },
        )
        .unwrap();
        let pixels: Vec<(u32, u32)> = (0..16).flat_map(|y| (0..16).map(move |x| (x, y))).collect();
        let whole = render_pixels(&scene, 0, &pixels);
        let until = render_pixels_until(&scene, 0, &pixels, &AtomicBool::new(false)).unwrap();
        assert_eq!(format!("{whole:?}"), format!("{until:?}"));
        assert!(render_pixels_until(&scene, 0, &pixels, &AtomicBool::new(true)).is_none());
    }
}
