//! The one-shot coordinator binary: the CLI, the gallery's golden images,
//! the pixel stream editor, meshes, OpenVDB bakes and OpenEXR headers read
//! by other programs.

#[path = "../support/mod.rs"]
mod support;

mod cli;
mod golden;
mod interop;
mod mesh;
mod pse_cli;
mod vdb;
