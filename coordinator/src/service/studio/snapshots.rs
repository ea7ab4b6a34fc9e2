//! Named snapshots of the live state, held by the server for every tab: a
//! snapshot keeps the text as the page shows it (knob values written as
//! defaults), its version and frame, and its image, rendered once by the
//! farm at high quality (the live frame's quality once the edits rest) and
//! kept for the A/B view. Restoring one is an edit.

use std::sync::Arc;

use hypertexture::PixelFormat;
use hypertexture::render::interleave::WorkUnit;
use serde::Serialize;

use crate::farm::JobId;
use crate::image::canvas::Canvas;

/// How many snapshots a studio holds.
pub const MOST: usize = 64;

/// The longest name, in characters.
pub const NAME_CHARS: usize = 80;

/// One snapshot.
pub struct Snapshot {
    pub id: u64,
    pub name: String,
    /// The version of the live state it was taken at.
    pub version: u64,
    /// The text as the page showed it.
    pub shown: String,
    /// The frame of the sequence shown.
    pub frame: u32,
    pub render: Render,
}

/// A snapshot's image: its frame's tiles, collected as the farm renders
/// them, then its 8-bit sRGB RGBA pixels.
pub struct Render {
    /// The farm's job rendering it.
    pub job: JobId,
    units: Vec<WorkUnit>,
    recorded: Vec<bool>,
    remaining: usize,
    canvas: Canvas,
    /// Straight-alpha 8-bit sRGB RGBA, row-major, once every unit arrived.
    pixels: Option<Arc<Vec<u8>>>,
    /// Why the farm gave the frame up.
    error: Option<String>,
    /// The scene, held while the frame is in the farm (its checks and
    /// in-process workers render this one).
    _scene: Arc<hypertexture::Scene>,
}

impl Render {
    /// The render of `units` of a `width` × `height` frame at `interleave`,
    /// submitted to the farm as `job`.
    pub fn new(
        job: JobId,
        units: Vec<WorkUnit>,
        (width, height, interleave): (u32, u32, u32),
        scene: Arc<hypertexture::Scene>,
    ) -> Render {
        Render {
            job,
            recorded: vec![false; units.len()],
            remaining: units.len(),
            units,
            canvas: Canvas::new(width, height, interleave, PixelFormat::Srgb8),
            pixels: None,
            error: None,
            _scene: scene,
        }
    }

    /// Stores the tile of unit `unit` (8-bit sRGB RGBA); a unit unknown,
    /// stored already or of the wrong size is ignored. Returns whether this
    /// tile made the image whole.
    pub fn store(&mut self, unit: usize, tile: &[u8]) -> bool {
        let Some(&work) = self.units.get(unit) else {
            return false;
        };
        let size = work.pixel_count(self.canvas.width()) * PixelFormat::Srgb8.bytes_per_pixel();
        if self.recorded[unit] || tile.len() != size {
            return false;
        }
        self.recorded[unit] = true;
        self.canvas.store(&work, tile);
        self.remaining -= 1;
        if self.remaining > 0 {
            return false;
        }
        self.pixels = Some(Arc::new(self.canvas.take().srgb8().into_owned()));
        true
    }

    /// The image's width and height.
    pub fn size(&self) -> (u32, u32) {
        (self.canvas.width(), self.canvas.height())
    }

    /// The image, once whole.
    pub fn pixels(&self) -> Option<&Arc<Vec<u8>>> {
        self.pixels.as_ref()
    }

    /// The farm gave the frame up.
    pub fn fail(&mut self, why: String) {
        self.error = Some(why);
    }
}

/// A snapshot as the page lists it.
#[derive(Clone, Debug, Serialize)]
pub struct SnapshotView {
    id: u64,
    name: String,
    version: u64,
    frame: u32,
    width: u32,
    height: u32,
    /// Its image is rendered (`GET /studio/snapshots/ID/pixels`).
    ready: bool,
    error: Option<String>,
}

/// The snapshots of a studio, oldest first.
#[derive(Default)]
pub struct Snapshots {
    list: Vec<Snapshot>,
    last_id: u64,
}

impl Snapshots {
    /// `name` trimmed, if a new snapshot may take it: not empty, at most
    /// [`NAME_CHARS`] characters, no other snapshot's, and fewer than
    /// [`MOST`] snapshots held.
    pub fn check_name(&self, name: &str) -> Result<String, String> {
        let name = name.trim();
        if name.is_empty() {
            return Err("a snapshot needs a name".to_string());
        }
        if name.chars().count() > NAME_CHARS {
            return Err(format!(
                "snapshot name `{name}` is longer than {NAME_CHARS} characters"
            ));
        }
        if self.list.iter().any(|s| s.name == name) {
            return Err(format!("a snapshot is already named `{name}`"));
        }
        if self.list.len() >= MOST {
            return Err(format!(
                "the studio holds {MOST} snapshots at most: restart it to start afresh"
            ));
        }
        Ok(name.to_string())
    }

    /// Adds a snapshot (its `id` is given here); returns its id.
    pub fn add(&mut self, snapshot: Snapshot) -> u64 {
        self.last_id += 1;
        self.list.push(Snapshot {
            id: self.last_id,
            ..snapshot
        });
        self.last_id
    }

    /// Drops every snapshot (their ids are not given again).
    pub fn clear(&mut self) {
        self.list.clear();
    }

    /// The farm's jobs of the snapshots' images.
    pub fn jobs(&self) -> Vec<JobId> {
        self.list.iter().map(|s| s.render.job).collect()
    }

    pub fn get(&self, id: u64) -> Option<&Snapshot> {
        self.list.iter().find(|s| s.id == id)
    }

    /// The snapshot the farm's `job` renders.
    pub fn rendered_by(&mut self, job: JobId) -> Option<&mut Snapshot> {
        self.list.iter_mut().find(|s| s.render.job == job)
    }

    pub fn views(&self) -> Vec<SnapshotView> {
        self.list
            .iter()
            .map(|s| SnapshotView {
                id: s.id,
                name: s.name.clone(),
                version: s.version,
                frame: s.frame,
                width: s.render.canvas.width(),
                height: s.render.canvas.height(),
                ready: s.render.pixels.is_some(),
                error: s.render.error.clone(),
            })
            .collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use hypertexture::render::interleave::farm_units;

    fn scene() -> Arc<hypertexture::Scene> {
        Arc::new(
            hypertexture::RenderRequest::new(
                include_str!("../../../../scenes/noisy_sphere.ron"),
                "noisy_sphere.ron",
            )
            .build(None)
            .unwrap(),
        )
    }

    #[test]
    fn a_snapshots_image_is_put_together_from_its_tiles() {
        let (width, height, interleave) = (10, 6, 4);
        let units = farm_units(width, height, interleave, 4);
        // Each pixel's value names its place: (x, y, 7, 255).
        let tiles: Vec<Vec<u8>> = units
            .iter()
            .map(|u| {
                let mut tile = Vec::new();
                for i in 0..u.row_count {
                    let set_row = u.first_row + i * u.row_stride;
                    let y = set_row * interleave + u.set.index / interleave;
                    for c in 0..u.set.columns(width) {
                        let x = c * interleave + u.set.index % interleave;
                        tile.extend_from_slice(&[x as u8, y as u8, 7, 255]);
                    }
                }
                tile
            })
            .collect();
        let mut render = Render::new(9, units.clone(), (width, height, interleave), scene());
        assert!(!render.store(units.len(), &[]), "an unknown unit");
        assert!(!render.store(0, &[1, 2, 3]), "a tile of the wrong size");
        for (i, tile) in tiles.iter().enumerate().rev() {
            assert_eq!(render.pixels(), None);
            assert_eq!(render.store(i, tile), i == 0, "whole with the last tile");
        }
        assert!(!render.store(0, &tiles[0]), "a tile twice");
        let pixels = render.pixels().unwrap();
        let expected: Vec<u8> = (0..height)
            .flat_map(|y| (0..width).flat_map(move |x| [x as u8, y as u8, 7, 255]))
            .collect();
        assert_eq!(pixels.as_slice(), expected.as_slice());
    }

    #[test]
    fn snapshot_names_are_checked() {
        let mut snapshots = Snapshots::default();
        assert_eq!(snapshots.check_name("  warm  "), Ok("warm".to_string()));
        assert_eq!(
            snapshots.check_name(" "),
            Err("a snapshot needs a name".to_string())
        );
        let long = "x".repeat(NAME_CHARS + 1);
        assert!(snapshots.check_name(&long).unwrap_err().contains("longer"));
        let id = snapshots.add(Snapshot {
            id: 0,
            name: "warm".to_string(),
            version: 3,
            shown: String::new(),
            frame: 0,
            render: Render::new(5, Vec::new(), (1, 1, 1), scene()),
        });
        assert_eq!(id, 1);
        assert_eq!(
            snapshots.check_name("warm"),
            Err("a snapshot is already named `warm`".to_string())
        );
        assert_eq!(snapshots.rendered_by(5).map(|s| s.id), Some(1));
        assert_eq!(snapshots.get(1).map(|s| s.version), Some(3));
        assert!(snapshots.get(2).is_none());
    }
}
