//! One render request: a scene's text and everything that replaces its own
//! settings (size, samples per pixel, quality, knobs), the frames to render,
//! what a pixel carries, and for a bake the lattice whose voxels the pixels
//! are.
//!
//! The command line, the service's queue and store, the studio and the
//! farm's wire all hold a [`RenderRequest`]; the wire form and its content
//! hash are in `hypertexture-proto` (`request`). A scene is built from a
//! request by [`RenderRequest::build`]; a process builds each request's scene
//! once ([`RenderRequest::build_shared`]): the coordinator's own checks and
//! in-process workers take the scene it built.

use std::collections::HashMap;
use std::sync::{Arc, Mutex, OnceLock, Weak};

use crate::render::bake::Lattice;
use crate::render::film::PixelFormat;
use crate::scene::{Assets, Overrides, Scene, SceneError};

/// The first and last frame of a request (inclusive): the frames a job
/// renders one after another, counted and indexed from 0 as the farm's
/// scheduler walks them. A `last` before `first` is taken as `first`. Held as
/// its two ends: a range of 100,000 frames takes the room of one.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct FrameRange {
    /// The first frame.
    pub first: u32,
    /// The last frame (at least `first`).
    pub last: u32,
}

impl FrameRange {
    /// The frames `first..=last` (`last` before `first` is taken as `first`).
    pub const fn new(first: u32, last: u32) -> FrameRange {
        FrameRange {
            first,
            last: if last < first { first } else { last },
        }
    }

    /// The single frame `frame`.
    pub const fn one(frame: u32) -> FrameRange {
        FrameRange::new(frame, frame)
    }

    /// The frames of `numbers` when they are consecutive and increasing (and
    /// at least one), else `None`.
    pub fn consecutive(mut numbers: impl Iterator<Item = u32>) -> Option<FrameRange> {
        let first = numbers.next()?;
        let mut last = first;
        for n in numbers {
            if last.checked_add(1) != Some(n) {
                return None;
            }
            last = n;
        }
        Some(FrameRange { first, last })
    }

    /// The last frame, at least the first.
    const fn end(self) -> u32 {
        if self.last < self.first {
            self.first
        } else {
            self.last
        }
    }

    /// Frames in the range (at most 2³², which a 64-bit `usize` holds; a
    /// narrower one saturates).
    pub fn len(self) -> usize {
        usize::try_from(u64::from(self.end() - self.first) + 1).unwrap_or(usize::MAX)
    }

    /// Always false: a range holds at least its first frame.
    pub const fn is_empty(self) -> bool {
        false
    }

    /// The `index`-th frame (from 0).
    pub fn get(self, index: usize) -> Option<u32> {
        u32::try_from(index)
            .ok()
            .and_then(|i| self.first.checked_add(i))
            .filter(|&f| f <= self.end())
    }

    /// The index of frame `frame` (from 0).
    pub fn index_of(self, frame: u32) -> Option<usize> {
        self.iter()
            .contains(&frame)
            .then(|| (frame - self.first) as usize)
    }

    /// Every frame, in order.
    pub fn iter(self) -> std::ops::RangeInclusive<u32> {
        self.first..=self.end()
    }
}

/// What to render: the scene, its overrides, the frames and the pixel format.
#[derive(Clone, Debug, PartialEq)]
pub struct RenderRequest {
    /// The scene's RON text.
    pub scene_text: String,
    /// Its name for messages (its file path); meshes it names are read
    /// beside it when no files are given.
    pub scene_name: String,
    /// Settings that replace the scene's own: size, samples per pixel,
    /// quality, knobs.
    pub overrides: Overrides,
    /// The frames.
    pub frames: FrameRange,
    /// What a pixel carries: what the outputs need.
    pub pixel_format: PixelFormat,
    /// For a bake: the lattice whose voxels the pixels are
    /// ([`crate::render::bake`]); `None`: the camera's image.
    pub bake: Option<Lattice>,
}

impl RenderRequest {
    /// A request for frame 0 of the scene `scene_text` named `scene_name`,
    /// with no overrides, as full samples.
    pub fn new(scene_text: impl Into<String>, scene_name: impl Into<String>) -> RenderRequest {
        RenderRequest {
            scene_text: scene_text.into(),
            scene_name: scene_name.into(),
            overrides: Overrides::default(),
            frames: FrameRange::one(0),
            pixel_format: PixelFormat::Samples,
            bake: None,
        }
    }

    /// Builds the scene: with the files it names from `assets` (`Some`:
    /// nothing is read from disk), or read beside `scene_name` (`None`).
    pub fn build(&self, assets: Option<&Assets>) -> Result<Scene, SceneError> {
        Scene::from_text_with(
            &self.scene_text,
            &self.scene_name,
            self.overrides.clone(),
            assets,
        )
    }

    /// The request with the size `scene` was built at written in: what the
    /// farm sends, so that every worker builds the same image.
    pub fn with_size_of(mut self, scene: &Scene) -> RenderRequest {
        self.overrides.width = Some(scene.width());
        self.overrides.height = Some(scene.height());
        self
    }

    /// The scene of this request whose content hash is `hash`: the one this
    /// process has built and still holds ([`RenderRequest::share`]), or
    /// built now ([`RenderRequest::build`]) and shared.
    pub fn build_shared(
        &self,
        hash: u64,
        assets: Option<&Assets>,
    ) -> Result<Arc<Scene>, SceneError> {
        if let Some(scene) = shared_scene(hash) {
            return Ok(scene);
        }
        let scene = Arc::new(self.build(assets)?);
        RenderRequest::share(hash, &scene);
        Ok(scene)
    }

    /// Offers `scene`, built from the request whose content hash is `hash`,
    /// to the rest of this process for as long as someone holds it.
    pub fn share(hash: u64, scene: &Arc<Scene>) {
        let mut built = built_scenes();
        built.retain(|_, s| s.strong_count() > 0);
        built.insert(hash, Arc::downgrade(scene));
    }
}

/// The scenes this process has built and still holds, by content hash.
fn built_scenes() -> std::sync::MutexGuard<'static, HashMap<u64, Weak<Scene>>> {
    static BUILT: OnceLock<Mutex<HashMap<u64, Weak<Scene>>>> = OnceLock::new();
    BUILT
        .get_or_init(Default::default)
        .lock()
        .unwrap_or_else(|p| p.into_inner())
}

/// The scene with content hash `hash` this process holds, if any.
pub fn shared_scene(hash: u64) -> Option<Arc<Scene>> {
    built_scenes().get(&hash).and_then(Weak::upgrade)
}

#[cfg(test)]
mod tests {
    use super::*;

    const SCENE: &str = include_str!("../../../scenes/noisy_sphere.ron");

    #[test]
    fn frame_ranges_count_their_frames() {
        assert_eq!(FrameRange::one(7).len(), 1);
        assert_eq!(FrameRange { first: 3, last: 9 }.len(), 7);
        #[cfg(target_pointer_width = "64")]
        assert_eq!(FrameRange::new(0, u32::MAX).len(), 1 << 32);
        // A last frame before the first is the first.
        assert_eq!(FrameRange::new(5, 2), FrameRange::one(5));
        assert_eq!(FrameRange { first: 5, last: 2 }.len(), 1);
        assert_eq!(FrameRange { first: 5, last: 2 }.iter().count(), 1);
    }

    #[test]
    fn frame_ranges_index_their_frames() {
        let frames = FrameRange::new(3, 5);
        assert_eq!(frames.iter().collect::<Vec<_>>(), [3, 4, 5]);
        assert_eq!(
            (frames.get(0), frames.get(2), frames.get(3)),
            (Some(3), Some(5), None)
        );
        assert_eq!(frames.get(usize::MAX), None);
        assert_eq!(
            (frames.index_of(3), frames.index_of(5), frames.index_of(2)),
            (Some(0), Some(2), None)
        );
        assert_eq!(frames.index_of(6), None);
        let top = FrameRange::new(u32::MAX - 1, u32::MAX);
        assert_eq!((top.get(1), top.get(2)), (Some(u32::MAX), None));
    }

    #[test]
    fn consecutive_frames_make_a_range() {
        assert_eq!(
            FrameRange::consecutive([4, 5, 6].into_iter()),
            Some(FrameRange::new(4, 6))
        );
        assert_eq!(FrameRange::consecutive([4, 6].into_iter()), None);
        assert_eq!(FrameRange::consecutive([5, 4].into_iter()), None);
        assert_eq!(FrameRange::consecutive(std::iter::empty()), None);
        assert_eq!(
            FrameRange::consecutive([u32::MAX, 0].into_iter()),
            None,
            "no wrap past the last frame number"
        );
    }

    #[test]
    fn a_request_builds_its_overrides_and_records_its_size() {
        let mut request = RenderRequest::new(SCENE, "noisy_sphere.ron");
        request.overrides.width = Some(24);
        request.overrides.spp = Some(2);
        let scene = request.build(None).unwrap();
        assert_eq!((scene.width(), scene.spp()), (24, 2));
        let sized = request.clone().with_size_of(&scene);
        assert_eq!(sized.overrides.width, Some(24));
        assert_eq!(sized.overrides.height, Some(scene.height()));
        request.overrides.spp = Some(0);
        assert!(request.build(None).is_err(), "spp 0 is refused");
    }

    #[test]
    fn a_built_scene_is_shared_while_it_is_held() {
        let request = RenderRequest::new(SCENE, "noisy_sphere.ron");
        let hash = 0x5eed_0001_u64;
        let first = request.build_shared(hash, None).unwrap();
        let again = request.build_shared(hash, None).unwrap();
        assert!(Arc::ptr_eq(&first, &again));
        drop((first, again));
        assert!(shared_scene(hash).is_none());
    }
}
