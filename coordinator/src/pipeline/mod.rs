//! The one-shot pipeline: what `coordinator render`, `bake`, `recolor`,
//! `grid` and `bench` do once and end, on top of the farm.
//!
//! - [`destination`]: where a job's images may go: output patterns and roots.
//! - [`run`]: a scene rendered on the farm or in this process, written as
//!   an image or a numbered sequence.
//! - [`bake`], [`vdb`]: H(x) sampled on a lattice and written as OpenVDB.
//! - [`recolor`]: an EXR's density channel mapped through new curves.
//! - [`grid`]: a painted PNG as a 2D shape transfer function.
//! - [`bench`]: the farm's measured speedup, and larger farms simulated.

pub mod bake;
pub mod bench;
pub mod destination;
pub mod grid;
pub mod recolor;
pub mod run;
pub mod vdb;
