//! The wire protocol of the render farm (package `hypertexture.v1`), and the one
//! place where wire types and the program's own types meet ([`convert`], and
//! [`request`] for a render request).
//!
//! Only this crate knows the wire format: the coordinator and worker speak in
//! `hypertexture` types and convert at the gRPC edge.

pub mod convert;
pub mod request;

/// A tile's pixels on the wire (a slice of the received buffer, not a copy).
pub use prost::bytes::Bytes;

/// The code generated from `hypertexture.proto`.
#[allow(clippy::all, clippy::pedantic, missing_docs)]
pub mod pb {
    tonic::include_proto!("hypertexture.v1");
}

/// Bumped whenever the protocol changes incompatibly; checked at registration.
/// 2: SubmitTile can hand out the next unit; assignments omit the scene text a
/// worker already has. 3: ReportFailure (a worker gives back a unit it cannot
/// render, with the reason). 4: jobs name the tiles' pixel format (8-bit sRGB
/// when only PNGs are written). 5: SubmitTiles (a worker's tiles on one stream).
/// 6: workers register with the digest of their known-answer probe.
pub const PROTOCOL_VERSION: u32 = 6;

/// Why a worker could not render an assignment (the program's side of
/// `pb::FailureKind`; see [`convert::failure_kind_to_wire`]).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum FailureKind {
    /// The scene does not build on this worker: every unit of the job would fail
    /// there too (deterministic), so the worker gets no more of them.
    Scene,
    /// The assignment itself was unusable; another try may succeed.
    Assignment,
    /// Rendering the unit failed (a panic caught by the worker).
    Render,
}

impl std::fmt::Display for FailureKind {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            FailureKind::Scene => "scene",
            FailureKind::Assignment => "assignment",
            FailureKind::Render => "render",
        })
    }
}

/// The largest message either side accepts (tonic's default is 4 MiB). A tile is
/// at most [`hypertexture::render::interleave::DEFAULT_MAX_UNIT_PIXELS`] pixels
/// (~150 KB of samples); anything near this limit is malformed and refused with
/// RESOURCE_EXHAUSTED rather than silently truncated.
pub const MAX_MESSAGE_BYTES: usize = 16 * 1024 * 1024;

/// The metadata key carrying `Bearer <token>`.
pub const AUTHORIZATION: &str = "authorization";
