//! The image a farm collects: tiles stored as they arrive, in the job's pixel
//! format, and handed out as a [`FrameImage`] when the frame is complete.
//!
//! The format is chosen by what the outputs need ([`PixelFormat`]): every
//! sample for an EXR, only 8-bit sRGB for a PNG. Pixels are kept set by set,
//! as the tiles bring them: storing a tile is one contiguous copy per row of
//! the unit, nothing is decoded on the thread that serves the workers, and
//! the frame is de-interleaved once, when it is complete (or previewed).

use hypertexture::render::interleave::WorkUnit;
use hypertexture::{Film, PixelFormat};

/// A finished (or, for a preview, partial) image.
#[derive(Clone, Debug, PartialEq)]
pub enum FrameImage {
    /// Every sample: writes a PNG or an EXR.
    Film(Film),
    /// Straight-alpha 8-bit sRGB RGBA, row-major: writes a PNG only.
    Srgb8 {
        /// Width in pixels.
        width: u32,
        /// Height in pixels.
        height: u32,
        /// 4 bytes per pixel.
        bytes: Vec<u8>,
    },
}

impl FrameImage {
    /// The image as 8-bit sRGB RGBA bytes, as a PNG stores them.
    pub fn srgb8(&self) -> std::borrow::Cow<'_, [u8]> {
        match self {
            FrameImage::Film(film) => film.to_srgb8().into(),
            FrameImage::Srgb8 { bytes, .. } => bytes.as_slice().into(),
        }
    }

    /// Width and height in pixels.
    pub fn size(&self) -> (u32, u32) {
        match self {
            FrameImage::Film(film) => (film.width(), film.height()),
            FrameImage::Srgb8 { width, height, .. } => (*width, *height),
        }
    }
}

/// A frame being collected.
///
/// Tiles are kept set by set, each pixel set as its own small row-major image,
/// so storing a tile is one contiguous copy per row of the unit: the canvas is
/// touched where the tile goes and nowhere else. The frame is put together
/// (de-interleaved) once, when it is taken or previewed.
pub struct Canvas {
    width: u32,
    height: u32,
    /// The interleave B of the job's pixel sets.
    interleave: u32,
    format: PixelFormat,
    /// Per set (by index): where its pixels start in `bytes`, its columns, and
    /// where its rows start in `rendered`.
    sets: Vec<SetLayout>,
    /// Set after set, each row-major in `format`; zero bytes are an empty
    /// (transparent black) pixel in both formats.
    bytes: Vec<u8>,
    /// Per set row: stored yet (for previews).
    rendered: Vec<bool>,
}

/// Where one pixel set lives in a [`Canvas`].
#[derive(Clone, Copy, Debug)]
struct SetLayout {
    /// First byte.
    offset: usize,
    /// Pixels per set row.
    columns: usize,
    /// First entry in `rendered`.
    first_row: usize,
}

impl Canvas {
    /// An empty canvas for pixel sets of a B×B `interleave`.
    pub fn new(width: u32, height: u32, interleave: u32, format: PixelFormat) -> Canvas {
        let b = interleave.max(1);
        let n = format.bytes_per_pixel();
        let (mut offset, mut first_row) = (0, 0);
        let sets = (0..b * b)
            .map(|index| {
                let set = hypertexture::render::interleave::PixelSet {
                    interleave: b,
                    index,
                };
                let (columns, rows) = (set.columns(width) as usize, set.rows(height) as usize);
                let layout = SetLayout {
                    offset,
                    columns,
                    first_row,
                };
                offset += columns * rows * n;
                first_row += rows;
                layout
            })
            .collect();
        Canvas {
            width,
            height,
            interleave: b,
            format,
            sets,
            // Zeroed memory comes from the OS untouched: nothing to clear.
            bytes: vec![0; offset],
            rendered: vec![false; first_row],
        }
    }

    /// Width in pixels.
    pub fn width(&self) -> u32 {
        self.width
    }

    /// Height in pixels.
    pub fn height(&self) -> u32 {
        self.height
    }

    /// What each pixel's bytes are.
    pub fn format(&self) -> PixelFormat {
        self.format
    }

    /// Stores a tile of `unit` (a unit of this canvas's interleave), already
    /// checked to hold its pixel count in this canvas's format.
    pub fn store(&mut self, unit: &WorkUnit, tile: &[u8]) {
        let n = self.format.bytes_per_pixel();
        debug_assert_eq!(tile.len(), unit.pixel_count(self.width) * n);
        debug_assert_eq!(unit.set.interleave, self.interleave);
        let Some(&set) = self.sets.get(unit.set.index as usize) else {
            return;
        };
        let row_bytes = set.columns * n;
        if row_bytes == 0 {
            return;
        }
        for (i, row_tile) in tile.chunks_exact(row_bytes).enumerate() {
            let r = unit.first_row as usize + i * unit.row_stride as usize;
            let start = set.offset + r * row_bytes;
            self.bytes[start..start + row_bytes].copy_from_slice(row_tile);
            self.rendered[set.first_row + r] = true;
        }
    }

    /// The complete image; the canvas is empty again for the next frame.
    pub fn take(&mut self) -> FrameImage {
        let blank = Canvas::new(self.width, self.height, self.interleave, self.format);
        let full = std::mem::replace(self, blank);
        full.image(full.frame_bytes())
    }

    /// The frame's pixels row-major (each set's pixels put in their places).
    fn frame_bytes(&self) -> Vec<u8> {
        // A pixel's size known at compile time: each copy is a move or two, not
        // a call to memcpy.
        match self.format {
            PixelFormat::Samples => {
                self.frame_bytes_as::<{ PixelFormat::Samples.bytes_per_pixel() }>()
            }
            PixelFormat::Srgb8 => self.frame_bytes_as::<{ PixelFormat::Srgb8.bytes_per_pixel() }>(),
        }
    }

    fn frame_bytes_as<const N: usize>(&self) -> Vec<u8> {
        let (w, h, b) = (
            self.width as usize,
            self.height as usize,
            self.interleave as usize,
        );
        let mut out = vec![0; w * h * N];
        for (y, row) in out.chunks_exact_mut(w * N).enumerate() {
            let (oy, r) = (y % b, y / b);
            for ox in 0..b.min(w) {
                let set = self.sets[oy * b + ox];
                let start = set.offset + r * set.columns * N;
                let source = &self.bytes[start..start + set.columns * N];
                for (c, pixel) in source.chunks_exact(N).enumerate() {
                    let x = ox + c * b;
                    row[x * N..(x + 1) * N].copy_from_slice(pixel);
                }
            }
        }
        out
    }

    /// Whether pixel (x, y) has been stored.
    fn is_rendered(&self, x: u32, y: u32) -> bool {
        let b = self.interleave;
        let set = self.sets[((y % b) * b + x % b) as usize];
        self.rendered[set.first_row + (y / b) as usize]
    }

    fn image(&self, bytes: Vec<u8>) -> FrameImage {
        match self.format {
            PixelFormat::Samples => FrameImage::Film(
                Film::from_sample_bytes(self.width, self.height, &bytes)
                    .expect("a canvas holds width × height samples"),
            ),
            PixelFormat::Srgb8 => FrameImage::Srgb8 {
                width: self.width,
                height: self.height,
                bytes,
            },
        }
    }

    /// The image so far with each missing pixel filled from the nearest stored
    /// pixel of a coarser lattice (units arrive coarse to fine, so after the first
    /// pixel set the whole picture is there at low resolution).
    pub fn preview(&self) -> FrameImage {
        let size = self.format.bytes_per_pixel();
        let stored = self.frame_bytes();
        let mut bytes = stored.clone();
        let (w, h) = (self.width, self.height);
        for y in 0..h {
            for x in 0..w {
                if self.is_rendered(x, y) {
                    continue;
                }
                let i = (y * w + x) as usize;
                let mut spacing = 2;
                while spacing <= 64 {
                    let (px, py) = (x - x % spacing, y - y % spacing);
                    if self.is_rendered(px, py) {
                        let j = (py * w + px) as usize;
                        bytes[i * size..(i + 1) * size]
                            .copy_from_slice(&stored[j * size..(j + 1) * size]);
                        break;
                    }
                    spacing *= 2;
                }
            }
        }
        self.image(bytes)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use hypertexture::Sample;
    use hypertexture::render::interleave::work_units;

    #[test]
    fn tiles_land_on_their_pixels_in_either_format() {
        let (w, h) = (19, 13);
        let mut film = Film::new(w, h);
        for y in 0..h {
            for x in 0..w {
                let v = (y * w + x) as f32 / 256.0;
                film.set(x, y, Sample::from_array([v; Sample::CHANNELS]));
            }
        }
        for format in [PixelFormat::Samples, PixelFormat::Srgb8] {
            let mut canvas = Canvas::new(w, h, 4, format);
            for unit in work_units(w, h, 4, 7) {
                let samples: Vec<Sample> = unit.pixels(w).map(|(x, y)| film.get(x, y)).collect();
                canvas.store(&unit, &format.encode(&samples));
            }
            let image = canvas.take();
            assert_eq!(image.srgb8(), film.to_srgb8());
            if format == PixelFormat::Samples {
                assert_eq!(image, FrameImage::Film(film.clone()));
            }
            assert_eq!(
                canvas.take().srgb8(),
                Film::new(w, h).to_srgb8(),
                "empty again"
            );
        }
    }

    #[test]
    fn a_preview_fills_gaps_from_the_coarse_lattice() {
        let mut canvas = Canvas::new(4, 4, 2, PixelFormat::Srgb8);
        // The set of (0, 0) in a 2×2 interleave: pixels (0,0), (2,0), (0,2), (2,2).
        let unit = work_units(4, 4, 2, 4096)
            .into_iter()
            .find(|u| u.set.index == 0)
            .unwrap();
        let tile: Vec<u8> = (0..4).flat_map(|i| [i * 10, 0, 0, 255]).collect();
        canvas.store(&unit, &tile);
        let FrameImage::Srgb8 { bytes, .. } = canvas.preview() else {
            panic!("an sRGB canvas previews as sRGB");
        };
        let red = |x: usize, y: usize| bytes[(y * 4 + x) * 4];
        assert_eq!([red(0, 0), red(1, 0), red(1, 1)], [0, 0, 0]);
        assert_eq!([red(2, 0), red(3, 1)], [10, 10]);
        assert_eq!([red(0, 2), red(3, 3)], [20, 30]);
    }
}
