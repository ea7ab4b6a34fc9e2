//! The film: what the ray marcher records for every pixel.
//!
//! A [`Sample`] is everything a pixel produces: its colour and coverage plus the
//! arbitrary output variables (AOVs) the OpenEXR output carries. A [`Film`] is a
//! whole image of them in row-major order, top row first.

/// What the marcher records for one pixel.
///
/// Every field is finite (never NaN or infinite): the farm rejects tiles that are not.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Sample {
    /// Linear RGB, premultiplied by alpha, with the background already composited.
    pub rgba: [f32; 4],
    /// The opacity-weighted mean density along the ray: the scalar field value that
    /// produced this pixel's colour (0 where the ray met nothing). Recolouring maps it
    /// through a colour map again without re-rendering.
    pub density: f32,
    /// Distance from the eye to the first sample with non-zero density (0 = none).
    pub depth: f32,
    /// Unit shading normal at the first sample where a gradient was taken
    /// (zero where none was).
    pub normal: [f32; 3],
}

impl Sample {
    /// Number of `f32` values in a sample, in the order of [`Sample::to_array`].
    pub const CHANNELS: usize = 9;

    /// The sample as a flat array: r, g, b, a, density, depth, normal x, y, z.
    pub fn to_array(&self) -> [f32; Self::CHANNELS] {
        let [r, g, b, a] = self.rgba;
        let [nx, ny, nz] = self.normal;
        [r, g, b, a, self.density, self.depth, nx, ny, nz]
    }

    /// The inverse of [`Sample::to_array`].
    pub fn from_array(v: [f32; Self::CHANNELS]) -> Self {
        Sample {
            rgba: [v[0], v[1], v[2], v[3]],
            density: v[4],
            depth: v[5],
            normal: [v[6], v[7], v[8]],
        }
    }

    /// Whether every channel is finite (the farm's first sanity check on a tile).
    pub fn is_finite(&self) -> bool {
        self.to_array().iter().all(|v| v.is_finite())
    }
}

/// A whole image of samples, row-major, top row first.
#[derive(Clone, Debug, PartialEq)]
pub struct Film {
    width: u32,
    height: u32,
    pixels: Vec<Sample>,
}

impl Film {
    /// A film of `width × height` empty (transparent black) samples.
    pub fn new(width: u32, height: u32) -> Self {
        Film {
            width,
            height,
            pixels: vec![Sample::default(); width as usize * height as usize],
        }
    }

    /// Image width in pixels.
    pub fn width(&self) -> u32 {
        self.width
    }

    /// Image height in pixels.
    pub fn height(&self) -> u32 {
        self.height
    }

    /// All samples, row-major.
    pub fn pixels(&self) -> &[Sample] {
        &self.pixels
    }

    /// All samples, row-major, mutable.
    pub fn pixels_mut(&mut self) -> &mut [Sample] {
        &mut self.pixels
    }

    /// The sample at pixel (x, y); panics when out of range (a programming error).
    pub fn get(&self, x: u32, y: u32) -> Sample {
        self.pixels[self.index(x, y)]
    }

    /// Store the sample of pixel (x, y); panics when out of range (a programming error).
    pub fn set(&mut self, x: u32, y: u32, sample: Sample) {
        let i = self.index(x, y);
        self.pixels[i] = sample;
    }

    fn index(&self, x: u32, y: u32) -> usize {
        assert!(
            x < self.width && y < self.height,
            "pixel ({x}, {y}) outside the film"
        );
        y as usize * self.width as usize + x as usize
    }
}
