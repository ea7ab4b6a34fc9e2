//! `hypertexture`: Perlin & Hoffert's *Hypertexture* (SIGGRAPH 1989) as a library.
//!
//! Pure: a scene goes in, pixels come out. No network, no file output, no threads
//! of its own (the caller's rayon pool does the work), no global random state. A
//! pixel's value is a function of (scene, pixel, frame, sample) only.
//!
//! - [`scene`]: RON scene files → a checked description → a runtime [`Scene`].
//! - [`soft`], [`density`]: soft objects, generalized booleans, the DMFs.
//! - [`noise`], [`shaping`]: the base functions noise, turbulence, bias, gain.
//! - [`march`], [`render`]: the ray marcher and the image/pixel drivers.
//! - [`film`]: what each pixel records.
//! - [`pse`]: the Pixel Stream Editor, expressions compiled to register code.
//! - [`probe`]: the known-answer probe, a digest of this build's arithmetic.

pub mod bake;
pub mod camera;
pub mod curve;
pub mod density;
pub mod distortion;
pub mod dual;
pub mod fastmath;
pub mod film;
pub mod interleave;
pub mod lighting;
pub mod march;
pub mod mesh;
pub mod motion;
pub mod noise;
pub mod probe;
pub mod pse;
pub mod random;
pub mod render;
pub mod sampling;
pub mod scene;
pub mod shaping;
pub mod simd;
pub mod soft;

pub use film::{Film, PixelFormat, Sample};
pub use scene::{Overrides, Quality, Scene, SceneError};
