//! A [`RenderRequest`] on the wire (`pb::Job`) and back, and its content
//! hash: the one conversion each way, and the one hash by which the farm
//! tells requests apart (workers cache built scenes by it, images record it).

use std::sync::Arc;

use hypertexture::scene::Assets;
use hypertexture::{FrameRange, Overrides, RenderRequest, Scene, SceneError};

use crate::convert::{self, WireError};
use crate::pb;

/// The wire form of `request` for its first frame (each assignment sets its
/// own), naming the files `assets` the scene names. The request carries the
/// image size the workers build ([`RenderRequest::with_size_of`]); an absent
/// size goes as 0.
pub fn to_wire(request: &RenderRequest, assets: Vec<pb::AssetRef>) -> pb::Job {
    let o = &request.overrides;
    let hashes: Vec<(String, u64)> = assets.iter().map(|a| (a.path.clone(), a.hash)).collect();
    pb::Job {
        scene_hash: content_hash(request, &hashes),
        scene_text: request.scene_text.clone(),
        scene_name: request.scene_name.clone(),
        width: o.width.unwrap_or(0),
        height: o.height.unwrap_or(0),
        frame: request.frames.first,
        spp: o.spp.unwrap_or(0),
        quality: convert::quality_to_wire(o.quality) as i32,
        knobs: convert::knobs_to_wire(&o.knobs),
        pixel_format: convert::pixel_format_to_wire(request.pixel_format) as i32,
        bake: request.bake.as_ref().map(convert::lattice_to_wire),
        assets,
    }
}

/// The request of a job from the wire, for the job's frame: its size is
/// always set, 0 samples per pixel is the scene's own, and the quality,
/// pixel format and bake lattice are checked.
pub fn from_wire(job: &pb::Job) -> Result<RenderRequest, WireError> {
    Ok(RenderRequest {
        scene_text: job.scene_text.clone(),
        scene_name: job.scene_name.clone(),
        overrides: Overrides {
            width: Some(job.width),
            height: Some(job.height),
            spp: (job.spp != 0).then_some(job.spp),
            quality: convert::quality_from_wire(job.quality)?,
            knobs: convert::knobs_from_wire(&job.knobs),
        },
        frames: FrameRange::one(job.frame),
        pixel_format: convert::pixel_format_from_wire(job.pixel_format)?,
        bake: job
            .bake
            .as_ref()
            .map(|l| convert::lattice_from_wire(l, job.width, job.height))
            .transpose()?,
    })
}

/// The content hash of `request` with the files its scene names (path as
/// written, content hash, in path order): everything that changes the
/// built scene. The frame, the pixel format and a bake's lattice are left
/// out: they choose what a unit computes from that scene, and travel in the
/// job beside the hash. Stable across machines and builds.
pub fn content_hash(request: &RenderRequest, assets: &[(String, u64)]) -> u64 {
    let o = &request.overrides;
    convert::scene_hash_with_assets(
        convert::scene_hash(
            &request.scene_text,
            o.width.unwrap_or(0),
            o.height.unwrap_or(0),
            o.spp.unwrap_or(0),
            convert::quality_to_wire(o.quality) as i32,
            &o.knobs,
        ),
        assets,
    )
}

/// The content hash a job from the wire claims to have, recomputed from its
/// fields ([`content_hash`]).
pub fn wire_hash(job: &pb::Job) -> Result<u64, WireError> {
    let hashes: Vec<(String, u64)> = job
        .assets
        .iter()
        .map(|a| (a.path.clone(), a.hash))
        .collect();
    Ok(content_hash(&from_wire(job)?, &hashes))
}

/// A request's scene, built in this process, and the request as the farm
/// sends it.
#[derive(Clone, Debug)]
pub struct Built {
    /// The scene.
    pub scene: Arc<Scene>,
    /// The request with the scene's image size written in
    /// ([`RenderRequest::with_size_of`]).
    pub request: RenderRequest,
    /// Its content hash ([`content_hash`], with the files the scene names).
    pub hash: u64,
}

/// Builds the scene of `request` (the files it names from `assets`, or read
/// beside the scene when `None`) and shares it with the rest of this process
/// under its content hash ([`RenderRequest::share`]): in-process workers and
/// the farm's own checks render it without building it again.
pub fn build(request: &RenderRequest, assets: Option<&Assets>) -> Result<Built, SceneError> {
    let scene = Arc::new(request.build(assets)?);
    let request = request.clone().with_size_of(&scene);
    let hash = content_hash(&request, scene.asset_hashes());
    RenderRequest::share(hash, &scene);
    Ok(Built {
        scene,
        request,
        hash,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use hypertexture::render::bake::Lattice;
    use hypertexture::{PixelFormat, Quality};

    fn request() -> RenderRequest {
        RenderRequest {
            scene_text: "Scene()".into(),
            scene_name: "a.ron".into(),
            overrides: Overrides {
                width: Some(64),
                height: Some(48),
                spp: Some(4),
                quality: Some(Quality::Interactive),
                knobs: vec![("b".into(), 0.5), ("a".into(), -1.0)],
            },
            frames: FrameRange::one(7),
            pixel_format: PixelFormat::Srgb8,
            bake: None,
        }
    }

    #[test]
    fn a_request_round_trips_through_the_wire() {
        let r = request();
        let asset = pb::AssetRef {
            path: "m.obj".into(),
            hash: 9,
            size: 3,
        };
        let job = to_wire(&r, vec![asset.clone()]);
        assert_eq!(job.frame, 7);
        assert_eq!(job.assets, vec![asset]);
        assert_eq!(from_wire(&job).unwrap(), r);
        assert_eq!(wire_hash(&job).unwrap(), job.scene_hash);
        let baked = RenderRequest {
            overrides: Overrides {
                width: Some(64),
                height: Some(1),
                spp: None,
                quality: None,
                knobs: Vec::new(),
            },
            pixel_format: PixelFormat::Samples,
            bake: Some(Lattice {
                origin: glam::Vec3::new(-1.0, 0.5, 2.0),
                voxel: 0.25,
                dims: [4, 4, 4],
            }),
            ..r
        };
        let job = to_wire(&baked, Vec::new());
        assert_eq!((job.spp, job.quality), (0, 0), "none: the scene's own");
        assert_eq!(from_wire(&job).unwrap(), baked);
    }

    #[test]
    fn a_job_from_the_wire_is_checked() {
        let job = to_wire(&request(), Vec::new());
        let bad = [
            pb::Job {
                quality: 9,
                ..job.clone()
            },
            pb::Job {
                pixel_format: 0,
                ..job.clone()
            },
            pb::Job {
                bake: Some(pb::BakeLattice {
                    voxel: 1.0,
                    nx: 2,
                    ny: 2,
                    nz: 2,
                    ..Default::default()
                }),
                ..job.clone()
            },
        ];
        for b in bad {
            assert!(from_wire(&b).is_err(), "{b:?}");
        }
    }

    #[test]
    fn the_hash_tells_requests_apart_and_ignores_the_frame() {
        let r = request();
        let base = content_hash(&r, &[]);
        let frame = RenderRequest {
            frames: FrameRange { first: 0, last: 9 },
            ..r.clone()
        };
        assert_eq!(content_hash(&frame, &[]), base);
        let mut changed = Vec::new();
        for change in 0..7 {
            let mut o = r.clone();
            match change {
                0 => o.scene_text.push(' '),
                1 => o.overrides.width = Some(65),
                2 => o.overrides.height = None,
                3 => o.overrides.spp = None,
                4 => o.overrides.quality = Some(Quality::High),
                5 => o.overrides.knobs.reverse(),
                _ => o.overrides.knobs[0].1 = 0.25,
            }
            changed.push(content_hash(&o, &[]));
        }
        changed.push(content_hash(&r, &[("m.obj".into(), 1)]));
        changed.push(content_hash(&r, &[("m.obj".into(), 2)]));
        for (i, h) in changed.iter().enumerate() {
            assert_ne!(*h, base, "change {i}");
            assert!(!changed[i + 1..].contains(h), "change {i} collides");
        }
        // The hash of a request with no files is the scene hash workers have
        // always cached by.
        assert_eq!(
            base,
            convert::scene_hash(
                "Scene()",
                64,
                48,
                4,
                pb::Quality::Interactive as i32,
                &r.overrides.knobs
            )
        );
    }

    #[test]
    fn a_built_request_is_what_a_worker_in_this_process_finds() {
        let request = RenderRequest {
            overrides: Overrides {
                height: Some(20),
                ..Overrides::default()
            },
            ..RenderRequest::new(
                include_str!("../../scenes/noisy_sphere.ron"),
                "noisy_sphere.ron",
            )
        };
        let built = build(&request, None).unwrap();
        assert_eq!(built.request.overrides.height, Some(20));
        assert_eq!(built.request.overrides.width, Some(built.scene.width()));
        let job = to_wire(&built.request, Vec::new());
        assert_eq!(job.scene_hash, built.hash);
        assert_eq!(wire_hash(&job).unwrap(), built.hash);
        let found = hypertexture::render::request::shared_scene(built.hash).unwrap();
        assert!(Arc::ptr_eq(&found, &built.scene));
        let rebuilt = from_wire(&job)
            .unwrap()
            .build_shared(built.hash, None)
            .unwrap();
        assert!(Arc::ptr_eq(&rebuilt, &built.scene), "not built again");
    }
}
