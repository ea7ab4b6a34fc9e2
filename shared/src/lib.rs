//! `hypertexture`: Perlin & Hoffert's *Hypertexture* (SIGGRAPH 1989) as a library.
//!
//! Pure: a scene goes in, pixels come out. No network, no file output, no threads
//! of its own (the caller's rayon pool does the work), no global random state. A
//! pixel's value is a function of (scene, pixel, frame, sample) only.
//!
//! The layers, each a folder that uses only the ones below it:
//!
//! - [`math`]: SIMD paths, fast approximations, hashing, dual numbers.
//! - [`mesh`]: triangle meshes read from OBJ files, closest points through a BVH.
//! - [`desc`]: the scene as written, plain data checked while it is read.
//! - [`field`]: noise, bias and gain, soft objects, the density chain, each
//!   built from its description.
//! - [`pse`]: the Pixel Stream Editor, expressions compiled to register code.
//! - [`scene`]: RON scene files → a checked description → a runtime [`Scene`],
//!   with its camera.
//! - [`render`]: ray marcher, lighting, sampling, film, the drivers.

pub mod desc;
pub mod field;
pub mod math;
pub mod mesh;
pub mod pse;
pub mod render;
pub mod scene;

pub use render::film::{Film, PixelFormat, Sample};
pub use render::request::{FrameRange, RenderRequest};
pub use scene::{Overrides, Quality, Scene, SceneError};
