//! `coordinator grid`: a greyscale PNG painted as a 2D shape transfer function
//! (Gilet & Dischler paint T2D with image tools) turned into the scene's inline
//! `Grid(rows: [...])`.
//!
//! The grid is written into the scene text, not referenced by path, because farm
//! workers receive only the scene text: a path would not resolve on them.

use std::fmt::Write as _;
use std::path::Path;

use hypertexture::desc::distortion::MAX_GRID_SIDE;

use crate::CoordinatorError;

/// The RON `Grid(rows: [...])` of the greyscale image at `path`, resampled (box
/// filter) to at most `side × side` values: columns over the noise index (left 0,
/// right 1), rows over the object density (top row 0, bottom row 1), white = 1.
pub fn png_to_grid(path: &Path, side: usize) -> Result<String, CoordinatorError> {
    let bad = |message: String| CoordinatorError::TransferImage {
        path: path.to_path_buf(),
        message,
    };
    let bytes = crate::files::read_capped(
        path,
        crate::files::MAX_GRID_IMAGE_BYTES,
        "transfer-function image",
    )?;
    let image = image::load_from_memory(&bytes)
        .map_err(|e| bad(e.to_string()))?
        .to_luma8();
    let (w, h) = (image.width() as usize, image.height() as usize);
    if w < 2 || h < 2 {
        return Err(bad(format!(
            "the image is {w}×{h}; a transfer function needs at least 2×2"
        )));
    }
    let luma: Vec<f32> = image.pixels().map(|p| f32::from(p.0[0]) / 255.0).collect();
    Ok(grid_text(&luma, w, h, side))
}

/// The grid text of a `w × h` image of values in [0, 1] (row-major, top row first),
/// box-filtered down to at most `side` (clamped to 2..=64) a side.
pub fn grid_text(values: &[f32], w: usize, h: usize, side: usize) -> String {
    let side = side.clamp(2, MAX_GRID_SIDE);
    let (cols, rows) = (w.min(side), h.min(side));
    let mut out = String::from("Grid(rows: [\n");
    for j in 0..rows {
        let (y0, y1) = (j * h / rows, ((j + 1) * h / rows).max(j * h / rows + 1));
        out.push_str("    [");
        for i in 0..cols {
            let (x0, x1) = (i * w / cols, ((i + 1) * w / cols).max(i * w / cols + 1));
            let mut sum = 0.0f64;
            for y in y0..y1 {
                for x in x0..x1 {
                    sum += f64::from(values[y * w + x]);
                }
            }
            let mean = sum / ((y1 - y0) * (x1 - x0)) as f64;
            let sep = if i == 0 { "" } else { ", " };
            let _ = write!(out, "{sep}{mean:.3}");
        }
        out.push_str("],\n");
    }
    out.push_str("])");
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn box_filters_down_and_keeps_orientation() {
        // 4×2: left half black, right half white; the bottom row all grey.
        let v = [0.0, 0.0, 1.0, 1.0, 0.5, 0.5, 0.5, 0.5];
        assert_eq!(
            grid_text(&v, 4, 2, 2),
            "Grid(rows: [\n    [0.000, 1.000],\n    [0.500, 0.500],\n])"
        );
        // Small images are kept as they are.
        assert_eq!(grid_text(&v, 4, 2, 64).matches(", ").count(), 6);
    }

    #[test]
    fn the_text_is_a_scene_grid() {
        let v: Vec<f32> = (0..100).map(|i| (i % 10) as f32 / 9.0).collect();
        let grid = grid_text(&v, 10, 10, 5);
        let scene = format!(
            "Scene(image: (width: 4, height: 4),
              camera: (eye: (0.0, 0.0, 5.0), look_at: (0.0, 0.0, 0.0), projection: Perspective(fov_y: 30.0)),
              march: (bounds: (min: (-2.0, -2.0, -2.0), max: (2.0, 2.0, 2.0)), step: Diagonal(50), opacity: 20.0),
              object: Sphere(radius: 0.5, softness: 1.0),
              distortion: (terms: [(amplitude: 0.2, frequency: 3.0, transfer: {grid})]))"
        );
        hypertexture::Scene::from_text(&scene, "grid", hypertexture::Overrides::default())
            .unwrap_or_else(|e| panic!("{e}\n{grid}"));
    }
}
