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

/// The sRGB transfer function (IEC 61966-2-1) of a linear value in [0, 1].
/// `libm::powf`, not the platform's, so every machine writes the same bytes.
pub fn linear_to_srgb(c: f32) -> f32 {
    if c <= 0.003_130_8 {
        12.92 * c
    } else {
        1.055 * libm::powf(c, 1.0 / 2.4) - 0.055
    }
}

/// A value in [0, 1] (clamped) as a byte, rounded to nearest.
pub fn to_byte(v: f32) -> u8 {
    let v = if v > 0.0 { v.min(1.0) } else { 0.0 };
    (v * 255.0 + 0.5) as u8
}

/// `to_byte(linear_to_srgb(c))`, the 8-bit sRGB code of a linear value in [0, 1],
/// without a `powf`: the code only ever steps up as `c` grows (checked for every
/// `f32` in [0, 1] by `examples/srgb_check.rs`), so it is the number of thresholds at or
/// below `c`. A linear bucket of `c` gives the code at the bucket's start, and at
/// most two thresholds lie inside a bucket.
pub fn srgb_byte(c: f32) -> u8 {
    srgb_table().code(c)
}

/// Buckets of the linear range in [`srgb_byte`]'s table (a power of two, so that a
/// bucket's start is an exact `f32`).
const SRGB_BUCKETS: usize = 4096;

struct SrgbTable {
    /// `threshold[k]`: the least `c` in [0, 1] whose code is at least `k`;
    /// `threshold[256]` and `threshold[257]` are infinite, so that two steps
    /// past code 255 stay there.
    threshold: [f32; 258],
    /// `bucket[i]`: the code of `i / SRGB_BUCKETS`.
    bucket: [u8; SRGB_BUCKETS + 1],
}

impl SrgbTable {
    /// [`srgb_byte`] with the table in hand.
    #[inline]
    fn code(&self, c: f32) -> u8 {
        let c = c.clamp(0.0, 1.0);
        // At most two thresholds lie inside a bucket: two steps without a
        // branch, which random colours would mispredict.
        let mut code = usize::from(self.bucket[(c * SRGB_BUCKETS as f32) as usize]);
        code += usize::from(self.threshold[code + 1] <= c);
        code += usize::from(self.threshold[code + 1] <= c);
        code as u8
    }

    /// [`srgb8`] with the table in hand.
    #[inline]
    fn rgba(&self, sample: &Sample) -> [u8; 4] {
        let [r, g, b, a] = sample.rgba;
        let unpremultiply = if a > 0.0 && a < 1.0 { 1.0 / a } else { 1.0 };
        let code = |c: f32| self.code((c * unpremultiply).clamp(0.0, 1.0));
        [code(r), code(g), code(b), to_byte(a)]
    }
}

fn srgb_table() -> &'static SrgbTable {
    static TABLE: std::sync::OnceLock<Box<SrgbTable>> = std::sync::OnceLock::new();
    TABLE.get_or_init(|| {
        let code = |c: f32| to_byte(linear_to_srgb(c));
        let mut threshold = [f32::INFINITY; 258];
        threshold[0] = 0.0;
        for (k, t) in threshold.iter_mut().enumerate().take(256).skip(1) {
            // Non-negative floats order like their bits: bisect on the bits.
            let (mut lo, mut hi) = (0u32, 1.0f32.to_bits());
            while lo < hi {
                let mid = lo + (hi - lo) / 2;
                if code(f32::from_bits(mid)) as usize >= k {
                    hi = mid;
                } else {
                    lo = mid + 1;
                }
            }
            *t = f32::from_bits(lo);
        }
        let mut bucket = [0u8; SRGB_BUCKETS + 1];
        for (i, b) in bucket.iter_mut().enumerate() {
            *b = code(i as f32 / SRGB_BUCKETS as f32);
        }
        Box::new(SrgbTable { threshold, bucket })
    })
}

/// A sample as straight-alpha 8-bit sRGB RGBA, the way a PNG stores it.
pub fn srgb8(sample: &Sample) -> [u8; 4] {
    srgb_table().rgba(sample)
}

impl Film {
    /// The film as straight-alpha 8-bit sRGB RGBA bytes, row-major.
    pub fn to_srgb8(&self) -> Vec<u8> {
        PixelFormat::Srgb8.encode(&self.pixels)
    }
}

/// What a tile carries for each pixel: every channel, or only what a PNG keeps.
///
/// The layouts are little-endian and row-major, so a tile's bytes go straight
/// into an image of the same format.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum PixelFormat {
    /// The whole [`Sample`], 9 `f32` (36 bytes) in the order of
    /// [`Sample::to_array`]: what an OpenEXR output needs.
    Samples,
    /// [`srgb8`]: straight-alpha 8-bit sRGB RGBA (4 bytes), all a PNG keeps.
    Srgb8,
}

impl PixelFormat {
    /// Bytes per pixel.
    pub const fn bytes_per_pixel(self) -> usize {
        match self {
            PixelFormat::Samples => Sample::CHANNELS * 4,
            PixelFormat::Srgb8 => 4,
        }
    }

    /// The samples in this format.
    pub fn encode(self, samples: &[Sample]) -> Vec<u8> {
        let mut bytes = Vec::with_capacity(samples.len() * self.bytes_per_pixel());
        match self {
            PixelFormat::Samples => {
                for s in samples {
                    for v in s.to_array() {
                        bytes.extend_from_slice(&v.to_le_bytes());
                    }
                }
            }
            PixelFormat::Srgb8 => {
                let table = srgb_table();
                bytes.resize(samples.len() * 4, 0);
                for (out, s) in bytes.chunks_exact_mut(4).zip(samples) {
                    out.copy_from_slice(&table.rgba(s));
                }
            }
        }
        bytes
    }
}

impl Sample {
    /// A sample from its [`PixelFormat::Samples`] bytes (36 of them).
    pub fn from_le_bytes(bytes: &[u8]) -> Sample {
        let mut a = [0.0f32; Sample::CHANNELS];
        for (v, c) in a.iter_mut().zip(bytes.chunks_exact(4)) {
            *v = f32::from_le_bytes([c[0], c[1], c[2], c[3]]);
        }
        Sample::from_array(a)
    }
}

impl Film {
    /// A film from `width × height` pixels of [`PixelFormat::Samples`] bytes;
    /// `None` when the length is not that.
    pub fn from_sample_bytes(width: u32, height: u32, bytes: &[u8]) -> Option<Film> {
        let size = PixelFormat::Samples.bytes_per_pixel();
        (bytes.len() == width as usize * height as usize * size).then(|| Film {
            width,
            height,
            pixels: bytes
                .chunks_exact(size)
                .map(Sample::from_le_bytes)
                .collect(),
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn direct(c: f32) -> u8 {
        to_byte(linear_to_srgb(c.clamp(0.0, 1.0)))
    }

    #[test]
    fn srgb_transfer() {
        assert_eq!(linear_to_srgb(0.0), 0.0);
        assert!((linear_to_srgb(1.0) - 1.0).abs() < 1e-6);
        assert!((linear_to_srgb(0.003_130_8) - 0.040_449_9).abs() < 1e-5);
        assert_eq!(to_byte(linear_to_srgb(0.5)), 188);
        assert_eq!(srgb_byte(0.5), 188);
        assert_eq!(srgb_byte(-1.0), 0);
        assert_eq!(srgb_byte(2.0), 255);
    }

    /// The table gives `powf`'s code around every threshold and bucket edge, and
    /// on a sweep through all of [0, 1].
    #[test]
    fn srgb_table_matches_powf() {
        let t = srgb_table();
        let mut edges: Vec<u32> = t.threshold.iter().map(|v| v.to_bits()).collect();
        edges.extend((0..=SRGB_BUCKETS).map(|i| (i as f32 / SRGB_BUCKETS as f32).to_bits()));
        for edge in edges {
            for bits in edge.saturating_sub(64)..=(edge + 64).min(1.0f32.to_bits()) {
                let c = f32::from_bits(bits);
                assert_eq!(srgb_byte(c), direct(c), "{c:e}");
            }
        }
        for bits in (0..=1.0f32.to_bits()).step_by(4099) {
            let c = f32::from_bits(bits);
            assert_eq!(srgb_byte(c), direct(c), "{c:e}");
        }
    }

    #[test]
    fn srgb8_unpremultiplies() {
        let s = Sample {
            rgba: [0.25, 0.0, 0.5, 0.5],
            ..Sample::default()
        };
        assert_eq!(srgb8(&s), [direct(0.5), 0, 255, 128]);
    }
}
