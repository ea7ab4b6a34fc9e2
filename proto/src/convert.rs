//! Conversions between wire (prost) types and the program's own types, both ways.

use hypertexture::Sample;
use hypertexture::interleave::{PixelSet, WorkUnit};

use crate::pb;

/// Why a wire message could not be turned into a program type.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum WireError {
    /// A required field is absent.
    #[error("missing field {0}")]
    Missing(&'static str),
    /// A unit names a set or rows outside the image.
    #[error("invalid unit: {0}")]
    InvalidUnit(String),
    /// A tile has the wrong number of values.
    #[error("tile has {got} values, expected {expected} ({pixels} pixels × {channels})")]
    TileLength {
        /// Values received.
        got: usize,
        /// Values expected.
        expected: usize,
        /// Pixels in the unit.
        pixels: usize,
        /// Values per pixel.
        channels: usize,
    },
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

/// The samples of a tile as a flat list of floats (9 per pixel).
pub fn samples_to_wire(samples: &[Sample]) -> Vec<f32> {
    samples.iter().flat_map(Sample::to_array).collect()
}

/// The samples of a tile from the wire: exactly `pixels` samples, all finite.
pub fn samples_from_wire(values: &[f32], pixels: usize) -> Result<Vec<Sample>, WireError> {
    let expected = pixels * Sample::CHANNELS;
    if values.len() != expected {
        return Err(WireError::TileLength {
            got: values.len(),
            expected,
            pixels,
            channels: Sample::CHANNELS,
        });
    }
    if let Some((index, &value)) = values.iter().enumerate().find(|(_, v)| !v.is_finite()) {
        return Err(WireError::NotFinite { index, value });
    }
    Ok(values
        .chunks_exact(Sample::CHANNELS)
        .map(|c| {
            let mut a = [0.0; Sample::CHANNELS];
            a.copy_from_slice(c);
            Sample::from_array(a)
        })
        .collect())
}

/// The content hash of a job: FNV-1a over the scene text, then the size, then
/// each knob override (name, a 0 byte, the value's bits). Stable across machines
/// and builds (workers cache scenes by it); without knobs it is the hash of
/// (text, width, height) alone.
pub fn scene_hash(text: &str, width: u32, height: u32, knobs: &[(String, f64)]) -> u64 {
    let mut h: u64 = 0xcbf2_9ce4_8422_2325;
    let knob_bytes = knobs.iter().flat_map(|(name, value)| {
        name.as_bytes()
            .iter()
            .copied()
            .chain([0])
            .chain(value.to_bits().to_le_bytes())
    });
    for b in text
        .as_bytes()
        .iter()
        .copied()
        .chain(width.to_le_bytes())
        .chain(height.to_le_bytes())
        .chain(knob_bytes)
    {
        h ^= u64::from(b);
        h = h.wrapping_mul(0x0000_0100_0000_01b3);
    }
    h
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
    use hypertexture::interleave::work_units;

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
        let wire = samples_to_wire(&samples);
        assert_eq!(samples_from_wire(&wire, 3).unwrap(), samples);
        assert!(matches!(
            samples_from_wire(&wire, 4),
            Err(WireError::TileLength { .. })
        ));
        let mut nan = wire.clone();
        nan[5] = f32::NAN;
        assert!(matches!(
            samples_from_wire(&nan, 3),
            Err(WireError::NotFinite { index: 5, .. })
        ));
        let mut inf = wire;
        inf[0] = f32::INFINITY;
        assert!(samples_from_wire(&inf, 3).is_err());
    }

    #[test]
    fn hash_depends_on_text_and_size() {
        let h = scene_hash("Scene()", 10, 10, &[]);
        assert_eq!(h, scene_hash("Scene()", 10, 10, &[]));
        assert_ne!(h, scene_hash("Scene( )", 10, 10, &[]));
        assert_ne!(h, scene_hash("Scene()", 10, 11, &[]));
        let knob = |v: f64| vec![("curliness".to_string(), v)];
        assert_ne!(h, scene_hash("Scene()", 10, 10, &knob(0.5)));
        assert_ne!(
            scene_hash("Scene()", 10, 10, &knob(0.5)),
            scene_hash("Scene()", 10, 10, &knob(0.6))
        );
        let wire = knobs_to_wire(&knob(0.5));
        assert_eq!(knobs_from_wire(&wire), knob(0.5));
    }
}
