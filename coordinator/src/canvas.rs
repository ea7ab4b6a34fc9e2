//! The image a farm collects: tiles stored as they arrive, in the job's pixel
//! format, and handed out as a [`FrameImage`] when the frame is complete.
//!
//! The format is chosen by what the outputs need ([`PixelFormat`]): every
//! sample for an EXR, only 8-bit sRGB for a PNG. Storing a tile is a copy of
//! each pixel's bytes to its place in the frame; nothing is decoded on the
//! thread that serves the workers.

use hypertexture::interleave::WorkUnit;
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
pub struct Canvas {
    width: u32,
    height: u32,
    format: PixelFormat,
    /// Row-major pixels in `format`; zero bytes are an empty (transparent black)
    /// pixel in both formats.
    bytes: Vec<u8>,
    /// Per pixel: stored yet (for previews).
    rendered: Vec<bool>,
}

impl Canvas {
    /// An empty canvas.
    pub fn new(width: u32, height: u32, format: PixelFormat) -> Canvas {
        let pixels = width as usize * height as usize;
        Canvas {
            width,
            height,
            format,
            // Zeroed memory comes from the OS untouched: nothing to clear.
            bytes: vec![0; pixels * format.bytes_per_pixel()],
            rendered: vec![false; pixels],
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

    /// Stores a tile of `unit`, already checked to hold its pixel count in this
    /// canvas's format.
    pub fn store(&mut self, unit: &WorkUnit, tile: &[u8]) {
        debug_assert_eq!(
            tile.len(),
            unit.pixel_count(self.width) * self.format.bytes_per_pixel()
        );
        // A pixel's size known at compile time: each copy is a move or two, not
        // a call to memcpy (36 instructions a pixel before, for 4 bytes).
        match self.format {
            PixelFormat::Samples => {
                self.store_as::<{ PixelFormat::Samples.bytes_per_pixel() }>(unit, tile)
            }
            PixelFormat::Srgb8 => {
                self.store_as::<{ PixelFormat::Srgb8.bytes_per_pixel() }>(unit, tile)
            }
        }
    }

    /// [`Canvas::store`] for `N` bytes a pixel, row by row of the unit, in the
    /// order of [`WorkUnit::pixels`].
    fn store_as<const N: usize>(&mut self, unit: &WorkUnit, tile: &[u8]) {
        let width = self.width as usize;
        let b = unit.set.interleave as usize;
        let (ox, oy) = unit.set.offset();
        let (ox, oy) = (ox as usize, oy as usize);
        let columns = unit.set.columns(self.width) as usize;
        if columns == 0 {
            return;
        }
        for (i, row_tile) in tile.chunks_exact(columns * N).enumerate() {
            let r = unit.first_row as usize + i * unit.row_stride as usize;
            let y = oy + r * b;
            let row = &mut self.bytes[y * width * N..(y + 1) * width * N];
            let rendered = &mut self.rendered[y * width..(y + 1) * width];
            for (c, pixel) in row_tile.chunks_exact(N).enumerate() {
                let x = ox + c * b;
                row[x * N..(x + 1) * N].copy_from_slice(pixel);
                rendered[x] = true;
            }
        }
    }

    /// The complete image; the canvas is empty again for the next frame.
    pub fn take(&mut self) -> FrameImage {
        let blank = Canvas::new(self.width, self.height, self.format);
        let full = std::mem::replace(self, blank);
        full.into_image()
    }

    fn into_image(self) -> FrameImage {
        match self.format {
            PixelFormat::Samples => FrameImage::Film(
                Film::from_sample_bytes(self.width, self.height, &self.bytes)
                    .expect("a canvas holds width × height samples"),
            ),
            PixelFormat::Srgb8 => FrameImage::Srgb8 {
                width: self.width,
                height: self.height,
                bytes: self.bytes,
            },
        }
    }

    /// The image so far with each missing pixel filled from the nearest stored
    /// pixel of a coarser lattice (units arrive coarse to fine, so after the first
    /// pixel set the whole picture is there at low resolution).
    pub fn preview(&self) -> FrameImage {
        let size = self.format.bytes_per_pixel();
        let mut bytes = self.bytes.clone();
        let (w, h) = (self.width, self.height);
        for y in 0..h {
            for x in 0..w {
                let i = (y * w + x) as usize;
                if self.rendered[i] {
                    continue;
                }
                let mut spacing = 2;
                while spacing <= 64 {
                    let (px, py) = (x - x % spacing, y - y % spacing);
                    let j = (py * w + px) as usize;
                    if self.rendered[j] {
                        bytes[i * size..(i + 1) * size]
                            .copy_from_slice(&self.bytes[j * size..(j + 1) * size]);
                        break;
                    }
                    spacing *= 2;
                }
            }
        }
        Canvas {
            bytes,
            rendered: Vec::new(),
            ..*self
        }
        .into_image()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use hypertexture::Sample;
    use hypertexture::interleave::work_units;

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
            let mut canvas = Canvas::new(w, h, format);
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
        let mut canvas = Canvas::new(4, 4, PixelFormat::Srgb8);
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
