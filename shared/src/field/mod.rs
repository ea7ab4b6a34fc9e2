//! Density fields: the paper's soft objects and what shapes them, each built
//! from its part of the description ([`crate::desc`]).
//!
//! - [`noise`], [`shaping`]: the base functions noise, turbulence, bias, gain.
//! - [`soft`]: soft objects and their hard cores, primitives and meshes
//!   (the triangles from [`crate::mesh`]).
//! - [`domain`]: where and when the density is evaluated ([`domain::Field`],
//!   [`domain::Points`]) and where it can be non-zero ([`domain::Support`]).
//! - [`density`]: the density chain, generalized booleans and the DMFs.
//! - [`distortion`], [`motion`]: Gilet & Dischler's shape transfer functions
//!   and vector fields, and motion over frames.
//! - [`curve`]: maps from density to colour, alpha and refractive index.

pub mod curve;
pub mod density;
pub mod distortion;
pub mod domain;
pub mod motion;
pub mod noise;
pub mod shaping;
pub mod soft;
