//! The lowest layer: arithmetic that knows nothing of densities or scenes.
//!
//! - [`simd`]: the instruction-set paths and the lane width.
//! - [`fastmath`]: approximations of pow, exp and friends, scalar and in lanes.
//! - [`random`]: hashing and the seeded generators (FNV-1a, SplitMix64).
//! - [`dual`]: dual numbers, a value with its gradient.

pub mod dual;
pub mod fastmath;
pub mod random;
pub mod simd;
