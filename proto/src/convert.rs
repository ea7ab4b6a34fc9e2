//! Conversions between wire (prost) types and the program's own types, both ways.

use std::fmt::Write as _;

use hypertexture::render::bake::Lattice;
use hypertexture::render::interleave::{PixelSet, WorkUnit};
use hypertexture::{PixelFormat, Quality, Sample};

use crate::{Bytes, FailureKind, pb};

/// Why a wire message could not be turned into a program type.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum WireError {
    /// A required field is absent.
    #[error("missing field {0}")]
    Missing(&'static str),
    /// A unit names a set or rows outside the image.
    #[error("invalid unit: {0}")]
    InvalidUnit(String),
    /// A tile has the wrong length.
    #[error("tile has {got} bytes, expected {expected} ({pixels} pixels × {bytes_per_pixel})")]
    TileLength {
        /// Bytes received.
        got: usize,
        /// Bytes expected.
        expected: usize,
        /// Pixels in the unit.
        pixels: usize,
        /// Bytes per pixel.
        bytes_per_pixel: usize,
    },
    /// A job names a quality this build does not know.
    #[error("unknown quality {0}")]
    UnknownQuality(i32),
    /// A job names no pixel format, or one this build does not know.
    #[error("unknown pixel format {0}")]
    UnknownPixelFormat(i32),
    /// A failure report names no kind, or one this build does not know.
    #[error("unknown failure kind {0}")]
    UnknownFailureKind(i32),
    /// A bake's lattice is unusable or does not fit the job's image.
    #[error("invalid bake lattice: {0}")]
    InvalidLattice(String),
    /// A tile value is NaN or infinite.
    #[error("tile value {index} is not finite ({value})")]
    NotFinite {
        /// Index of the value.
        index: usize,
        /// The value.
        value: f32,
    },
}

/// A unit on the wire.
pub fn unit_to_wire(unit: &WorkUnit) -> pb::Unit {
    pb::Unit {
        interleave: unit.set.interleave,
        set_index: unit.set.index,
        first_row: unit.first_row,
        row_count: unit.row_count,
        row_stride: unit.row_stride,
    }
}

/// A unit from the wire, checked against an image of `width × height`.
pub fn unit_from_wire(unit: &pb::Unit, width: u32, height: u32) -> Result<WorkUnit, WireError> {
    let b = unit.interleave;
    if !(1..=64).contains(&b) || !b.is_power_of_two() {
        return Err(WireError::InvalidUnit(format!("interleave {b}")));
    }
    if unit.set_index >= b * b {
        return Err(WireError::InvalidUnit(format!(
            "set {} of {}",
            unit.set_index,
            b * b
        )));
    }
    let set = PixelSet {
        interleave: b,
        index: unit.set_index,
    };
    let rows = set.rows(height);
    let last = u64::from(unit.first_row)
        + u64::from(unit.row_count.saturating_sub(1)) * u64::from(unit.row_stride);
    if unit.row_count == 0
        || unit.row_stride == 0
        || unit.first_row >= unit.row_stride
        || last >= u64::from(rows)
    {
        return Err(WireError::InvalidUnit(format!(
            "set rows {} + i·{} (i < {}) of a set with {rows} rows",
            unit.first_row, unit.row_stride, unit.row_count
        )));
    }
    if set.columns(width) == 0 {
        return Err(WireError::InvalidUnit(format!(
            "set {} is empty at width {width}",
            unit.set_index
        )));
    }
    Ok(WorkUnit {
        set,
        first_row: unit.first_row,
        row_count: unit.row_count,
        row_stride: unit.row_stride,
    })
}

/// A tile's pixels on the wire: the samples in the job's pixel format.
pub fn tile_to_wire(samples: &[Sample], format: PixelFormat) -> Bytes {
    format.encode(samples).into()
}

/// Checks a tile from the wire: exactly `pixels` pixels of `format`, and for
/// samples every value finite. The whole tile is checked before the caller
/// stores any of it; nothing is copied.
pub fn tile_from_wire(
    bytes: &[u8],
    pixels: usize,
    format: PixelFormat,
) -> Result<&[u8], WireError> {
    let bytes_per_pixel = format.bytes_per_pixel();
    let expected = pixels * bytes_per_pixel;
    if bytes.len() != expected {
        return Err(WireError::TileLength {
            got: bytes.len(),
            expected,
            pixels,
            bytes_per_pixel,
        });
    }
    if format == PixelFormat::Samples {
        let value = |c: &[u8]| f32::from_le_bytes([c[0], c[1], c[2], c[3]]);
        if let Some(index) = bytes.chunks_exact(4).position(|c| !value(c).is_finite()) {
            return Err(WireError::NotFinite {
                index,
                value: value(&bytes[4 * index..]),
            });
        }
    }
    Ok(bytes)
}

/// A bake's lattice on the wire.
pub fn lattice_to_wire(lattice: &Lattice) -> pb::BakeLattice {
    let [nx, ny, nz] = lattice.dims;
    pb::BakeLattice {
        origin_x: lattice.origin.x,
        origin_y: lattice.origin.y,
        origin_z: lattice.origin.z,
        voxel: lattice.voxel,
        nx,
        ny,
        nz,
    }
}

/// A bake's lattice from the wire, checked: finite, voxels of a positive
/// size, and laid out as exactly the job's `width` × `height` image.
pub fn lattice_from_wire(
    lattice: &pb::BakeLattice,
    width: u32,
    height: u32,
) -> Result<Lattice, WireError> {
    let l = Lattice {
        origin: glam::Vec3::new(lattice.origin_x, lattice.origin_y, lattice.origin_z),
        voxel: lattice.voxel,
        dims: [lattice.nx, lattice.ny, lattice.nz],
    };
    if !l.is_usable() {
        return Err(WireError::InvalidLattice(format!(
            "origin {}, voxel {}, {}×{}×{} voxels: expected finite numbers, a positive voxel and no empty axis",
            l.origin, l.voxel, l.dims[0], l.dims[1], l.dims[2]
        )));
    }
    match l.image_size() {
        Some(size) if size == (width, height) => Ok(l),
        size => Err(WireError::InvalidLattice(format!(
            "{}×{}×{} voxels lay out as {} but the job's image is {width}×{height}",
            l.dims[0],
            l.dims[1],
            l.dims[2],
            size.map_or_else(|| "no image".to_string(), |(w, h)| format!("{w}×{h}"))
        ))),
    }
}

/// A pixel format on the wire.
pub fn pixel_format_to_wire(format: PixelFormat) -> pb::PixelFormat {
    match format {
        PixelFormat::Samples => pb::PixelFormat::Samples,
        PixelFormat::Srgb8 => pb::PixelFormat::Srgb8,
    }
}

/// A pixel format from the wire (unspecified or unknown is an error).
pub fn pixel_format_from_wire(format: i32) -> Result<PixelFormat, WireError> {
    match pb::PixelFormat::try_from(format) {
        Ok(pb::PixelFormat::Samples) => Ok(PixelFormat::Samples),
        Ok(pb::PixelFormat::Srgb8) => Ok(PixelFormat::Srgb8),
        _ => Err(WireError::UnknownPixelFormat(format)),
    }
}

/// The content hash of a job: FNV-1a over the scene text, then the size, the
/// samples per pixel, the quality and each knob override (name, a 0 byte, the
/// value's bits): everything that changes the pixels. Stable across machines
/// and builds (workers cache scenes by it).
pub fn scene_hash(
    text: &str,
    width: u32,
    height: u32,
    spp: u32,
    quality: i32,
    knobs: &[(String, f64)],
) -> u64 {
    let mut h = hypertexture::math::random::Fnv1a::default();
    h.write(text.bytes());
    h.write(width.to_le_bytes());
    h.write(height.to_le_bytes());
    h.write(spp.to_le_bytes());
    h.write(quality.to_le_bytes());
    for (name, value) in knobs {
        h.write(name.bytes().chain([0]).chain(value.to_bits().to_le_bytes()));
    }
    h.finish()
}

/// [`scene_hash`] with the files the scene names (path as written and
/// content hash, in path order) hashed in after it; without files, `hash`
/// itself, so a scene that names none keeps its hash.
pub fn scene_hash_with_assets(hash: u64, assets: &[(String, u64)]) -> u64 {
    if assets.is_empty() {
        return hash;
    }
    let mut h = hypertexture::math::random::Fnv1a::default();
    h.write(hash.to_le_bytes());
    for (path, content) in assets {
        h.write(path.bytes().chain([0]).chain(content.to_le_bytes()));
    }
    h.finish()
}

/// The chunk size of `GetAsset`: under gRPC's 4 MiB message limit.
pub const ASSET_CHUNK_BYTES: usize = 1 << 20;

/// A quality preset on the wire.
pub fn quality_to_wire(quality: Option<Quality>) -> pb::Quality {
    match quality {
        None => pb::Quality::Unspecified,
        Some(Quality::Interactive) => pb::Quality::Interactive,
        Some(Quality::High) => pb::Quality::High,
    }
}

/// A quality preset from the wire (`quality` is the raw enum value).
pub fn quality_from_wire(quality: i32) -> Result<Option<Quality>, WireError> {
    match pb::Quality::try_from(quality) {
        Ok(pb::Quality::Unspecified) => Ok(None),
        Ok(pb::Quality::Interactive) => Ok(Some(Quality::Interactive)),
        Ok(pb::Quality::High) => Ok(Some(Quality::High)),
        Err(_) => Err(WireError::UnknownQuality(quality)),
    }
}

/// A failure kind on the wire.
pub fn failure_kind_to_wire(kind: FailureKind) -> pb::FailureKind {
    match kind {
        FailureKind::Scene => pb::FailureKind::Scene,
        FailureKind::Assignment => pb::FailureKind::Assignment,
        FailureKind::Render => pb::FailureKind::Render,
    }
}

/// A failure kind from the wire (`kind` is the raw enum value; unspecified is refused).
pub fn failure_kind_from_wire(kind: i32) -> Result<FailureKind, WireError> {
    match pb::FailureKind::try_from(kind) {
        Ok(pb::FailureKind::Scene) => Ok(FailureKind::Scene),
        Ok(pb::FailureKind::Assignment) => Ok(FailureKind::Assignment),
        Ok(pb::FailureKind::Render) => Ok(FailureKind::Render),
        Ok(pb::FailureKind::Unspecified) | Err(_) => Err(WireError::UnknownFailureKind(kind)),
    }
}

/// The longest failure reason kept (in characters); the rest is cut.
pub const MAX_REASON_CHARS: usize = 512;

/// The longest worker name or id kept (in characters); the rest is cut.
pub const MAX_NAME_CHARS: usize = 64;

/// Whether `c` reorders or hides the text around it when shown: Unicode's
/// bidirectional embeddings, overrides, isolates and marks.
fn is_bidi_control(c: char) -> bool {
    matches!(
        c,
        '\u{202a}'..='\u{202e}' | '\u{2066}'..='\u{2069}' | '\u{200e}' | '\u{200f}' | '\u{61c}'
    )
}

/// A string from the network made safe to log or to echo: control characters
/// (newlines included) and bidirectional controls become escapes (`\n`,
/// `\u{202e}`), so that it cannot start a forged log line or turn the text
/// around it; at most `max_chars` characters of it are kept, and a cut ends
/// with `…`.
pub fn untrusted(s: &str, max_chars: usize) -> String {
    let mut out = String::with_capacity(s.len().min(max_chars * 2));
    for (i, c) in s.chars().enumerate() {
        if i == max_chars {
            out.push('…');
            break;
        }
        match c {
            '\n' => out.push_str("\\n"),
            '\r' => out.push_str("\\r"),
            '\t' => out.push_str("\\t"),
            c if c.is_control() || is_bidi_control(c) => {
                let _ = write!(out, "\\u{{{:x}}}", u32::from(c));
            }
            c => out.push(c),
        }
    }
    out
}

/// A worker name or id from the network, safe to log ([`untrusted`], at most
/// [`MAX_NAME_CHARS`] characters).
pub fn name_from_wire(name: &str) -> String {
    untrusted(name, MAX_NAME_CHARS)
}

/// A failure reason from the wire as one printable line, at most
/// [`MAX_REASON_CHARS`] characters ([`untrusted`]: it goes into logs and
/// error messages).
pub fn reason_from_wire(reason: &str) -> String {
    let line = untrusted(reason.trim(), MAX_REASON_CHARS);
    if line.is_empty() {
        "no reason given".into()
    } else {
        line
    }
}

/// Knob overrides on the wire.
pub fn knobs_to_wire(knobs: &[(String, f64)]) -> Vec<pb::KnobSetting> {
    knobs
        .iter()
        .map(|(name, value)| pb::KnobSetting {
            name: name.clone(),
            value: *value,
        })
        .collect()
}

/// Knob overrides from the wire (checked against the scene when it is built).
pub fn knobs_from_wire(knobs: &[pb::KnobSetting]) -> Vec<(String, f64)> {
    knobs.iter().map(|k| (k.name.clone(), k.value)).collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use hypertexture::render::interleave::work_units;

    #[test]
    fn units_round_trip_and_are_checked() {
        for unit in work_units(37, 29, 8, 10) {
            assert_eq!(unit_from_wire(&unit_to_wire(&unit), 37, 29), Ok(unit));
        }
        let unit = |interleave, set_index, first_row, row_count, row_stride| pb::Unit {
            interleave,
            set_index,
            first_row,
            row_count,
            row_stride,
        };
        let bad = [
            unit(3, 0, 0, 1, 1),
            unit(8, 64, 0, 1, 1),
            unit(8, 0, 4, 2, 1),
            unit(8, 0, 0, 0, 1),
            unit(8, 0, 0, 1, 0),
            unit(8, 0, 2, 1, 2),
            unit(8, 0, 0, 4, 2),
            unit(8, 0, u32::MAX, u32::MAX, u32::MAX),
        ];
        for u in bad {
            assert!(unit_from_wire(&u, 37, 40).is_err(), "{u:?}");
        }
    }

    #[test]
    fn tiles_round_trip_and_reject_garbage() {
        let samples: Vec<Sample> = (0..3)
            .map(|i| Sample::from_array([i as f32; Sample::CHANNELS]))
            .collect();
        let wire = tile_to_wire(&samples, PixelFormat::Samples).to_vec();
        let back = tile_from_wire(&wire, 3, PixelFormat::Samples).unwrap();
        let back: Vec<Sample> = back.chunks_exact(36).map(Sample::from_le_bytes).collect();
        assert_eq!(back, samples);
        let samples_length = |r| matches!(r, Err(WireError::TileLength { .. }));
        assert!(samples_length(tile_from_wire(
            &wire,
            4,
            PixelFormat::Samples
        )));
        let mut nan = wire.clone();
        nan[20..24].copy_from_slice(&f32::NAN.to_le_bytes());
        assert!(matches!(
            tile_from_wire(&nan, 3, PixelFormat::Samples),
            Err(WireError::NotFinite { index: 5, .. })
        ));
        let mut inf = wire.clone();
        inf[..4].copy_from_slice(&f32::INFINITY.to_le_bytes());
        assert!(tile_from_wire(&inf, 3, PixelFormat::Samples).is_err());
        assert!(samples_length(tile_from_wire(
            &wire[..wire.len() - 1],
            3,
            PixelFormat::Samples
        )));
        // 8-bit sRGB: any byte is a colour; only the length can be wrong.
        let srgb = tile_to_wire(&samples, PixelFormat::Srgb8).to_vec();
        assert_eq!(srgb.len(), 12);
        assert_eq!(tile_from_wire(&srgb, 3, PixelFormat::Srgb8), Ok(&srgb[..]));
        assert!(samples_length(tile_from_wire(&srgb, 2, PixelFormat::Srgb8)));
        assert!(samples_length(tile_from_wire(&wire, 3, PixelFormat::Srgb8)));
        for f in [PixelFormat::Samples, PixelFormat::Srgb8] {
            assert_eq!(
                pixel_format_from_wire(pixel_format_to_wire(f) as i32),
                Ok(f)
            );
        }
        assert_eq!(
            pixel_format_from_wire(0),
            Err(WireError::UnknownPixelFormat(0))
        );
        assert_eq!(
            pixel_format_from_wire(3),
            Err(WireError::UnknownPixelFormat(3))
        );
    }

    #[test]
    fn hash_depends_on_text_size_sampling_and_knobs() {
        let h = scene_hash("Scene()", 10, 10, 0, 0, &[]);
        // Stable across builds: FNV-1a of the text and the little-endian fields.
        assert_eq!(h, 0x86af_e915_7ecc_0f58);
        assert_eq!(h, scene_hash("Scene()", 10, 10, 0, 0, &[]));
        assert_ne!(h, scene_hash("Scene( )", 10, 10, 0, 0, &[]));
        assert_ne!(h, scene_hash("Scene()", 10, 11, 0, 0, &[]));
        assert_ne!(h, scene_hash("Scene()", 10, 10, 4, 0, &[]));
        assert_ne!(h, scene_hash("Scene()", 10, 10, 0, 1, &[]));
        // A scene without files keeps its hash; a changed file is a new scene.
        assert_eq!(scene_hash_with_assets(h, &[]), h);
        let mesh = |hash| [("m.obj".to_string(), hash)];
        assert_ne!(scene_hash_with_assets(h, &mesh(1)), h);
        assert_ne!(
            scene_hash_with_assets(h, &mesh(1)),
            scene_hash_with_assets(h, &mesh(2))
        );
        let knob = |v: f64| vec![("curliness".to_string(), v)];
        assert_ne!(h, scene_hash("Scene()", 10, 10, 0, 0, &knob(0.5)));
        assert_ne!(
            scene_hash("Scene()", 10, 10, 0, 0, &knob(0.5)),
            scene_hash("Scene()", 10, 10, 0, 0, &knob(0.6))
        );
        let wire = knobs_to_wire(&knob(0.5));
        assert_eq!(knobs_from_wire(&wire), knob(0.5));
    }

    #[test]
    fn quality_failure_kinds_and_reasons_round_trip() {
        for q in [None, Some(Quality::Interactive), Some(Quality::High)] {
            assert_eq!(quality_from_wire(quality_to_wire(q) as i32), Ok(q));
        }
        assert_eq!(quality_from_wire(7), Err(WireError::UnknownQuality(7)));
        for k in [
            FailureKind::Scene,
            FailureKind::Assignment,
            FailureKind::Render,
        ] {
            assert_eq!(
                failure_kind_from_wire(failure_kind_to_wire(k) as i32),
                Ok(k)
            );
        }
        assert_eq!(
            failure_kind_from_wire(0),
            Err(WireError::UnknownFailureKind(0))
        );
        assert_eq!(
            failure_kind_from_wire(9),
            Err(WireError::UnknownFailureKind(9))
        );
        assert_eq!(reason_from_wire(" a\nb\u{1b} "), "a\\nb\\u{1b}");
        assert_eq!(reason_from_wire(""), "no reason given");
        assert_eq!(
            reason_from_wire(&"x".repeat(5000)).chars().count(),
            MAX_REASON_CHARS + 1
        );
        assert!(reason_from_wire(&"x".repeat(5000)).ends_with('…'));
        assert_eq!(
            name_from_wire("a\u{202e}b\u{2066}c\u{200f}\u{61c}\r\"é"),
            "a\\u{202e}b\\u{2066}c\\u{200f}\\u{61c}\\r\"é"
        );
        assert_eq!(
            name_from_wire(&"y".repeat(65)),
            format!("{}…", "y".repeat(64))
        );
    }

    #[test]
    fn lattices_round_trip_and_are_checked() {
        let lattice = Lattice {
            origin: glam::Vec3::new(-1.0, 0.5, 2.0),
            voxel: 0.125,
            dims: [10, 20, 30],
        };
        let (w, h) = lattice.image_size().expect("6000 voxels fit");
        let wire = lattice_to_wire(&lattice);
        assert_eq!(lattice_from_wire(&wire, w, h), Ok(lattice));
        assert!(matches!(
            lattice_from_wire(&wire, w, h + 1),
            Err(WireError::InvalidLattice(_))
        ));
        for bad in [
            pb::BakeLattice { voxel: 0.0, ..wire },
            pb::BakeLattice {
                origin_x: f32::NAN,
                ..wire
            },
            pb::BakeLattice { nz: 0, ..wire },
            pb::BakeLattice {
                nx: u32::MAX,
                ..wire
            },
        ] {
            assert!(
                matches!(
                    lattice_from_wire(&bad, w, h),
                    Err(WireError::InvalidLattice(_))
                ),
                "{bad:?}"
            );
        }
    }
}
