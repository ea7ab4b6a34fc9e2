//! The known-answer probe: a digest of the arithmetic of this build.
//!
//! The farm's images are byte-identical to the in-process render only when every
//! worker computes every pixel with the same f32 operations as the coordinator.
//! The protocol version does not say that: two builds that speak the same
//! protocol may differ in a noise kernel, an approximation of a power or the
//! order of a sum (a newer release, a local patch, another platform's libm), and
//! their pixels then differ in the last bits — a seam no check on a tile's shape
//! would see. So each side renders the same few pixels of a set of scenes and
//! hashes every bit of them; a worker whose digest differs from the coordinator's is
//! refused at registration.
//!
//! The probe scenes are the repository's scenes (the gallery, the Pixel Stream
//! Editor's and all of Gilet & Dischler's), built into the library, each
//! rendered at [`PROBE_PIXELS`] of a [`PROBE_SIZE`]² image at its interactive
//! step with at most [`PROBE_SPP`] samples per pixel: together they run the
//! density kernels, noises, powers, shading, refraction, shadows and sampling
//! the renderer has, in about 5 ms of one core (release build). A scene added
//! to the gallery belongs here too (a test checks it).
//! Every instruction-set path gives the same digest (the paths are bit-identical;
//! a test checks it here too), so a worker may run a different path from the
//! coordinator's.

use crate::math::random::Fnv1a;
use crate::math::simd::Isa;
use crate::render::film::srgb8;
use crate::render::render_pixel;
use crate::scene::{Overrides, Quality, Scene};

/// Width and height of each probe render, in pixels.
pub const PROBE_SIZE: u32 = 4;

/// The pixels of that image the probe renders: the two on the diagonal nearest
/// the centre, where the scenes put their objects (a test checks that each
/// scene's object is met). Cheap enough for the coordinator's CPU budget.
pub const PROBE_PIXELS: [(u32, u32); 2] = [(1, 1), (2, 2)];

/// The most samples per pixel the probe takes (enough to run supersampling).
pub const PROBE_SPP: u32 = 2;

/// The frame the probe renders (not 0, so that motion and flow move).
const PROBE_FRAME: u32 = 3;

macro_rules! probe_scenes {
    ($($path:literal),* $(,)?) => {
        &[$(($path, include_str!(concat!("../../../scenes/", $path)))),*]
    };
}

/// The probe scenes: (path under `scenes/`, text).
pub const PROBE_SCENES: &[(&str, &str)] = probe_scenes![
    "blue_glass.ron",
    "dripping_sphere.ron",
    "eroded_cube.ron",
    "fire_ball.ron",
    "fractal_sphere.ron",
    "fur.ron",
    "noisy_sphere.ron",
    "noisy_sphere_high_amplitude.ron",
    "noisy_sphere_high_frequency.ron",
    "tribble.ron",
    "pse/bumps.ron",
    "pse/checkerboard.ron",
    "pse/clouds.ron",
    "pse/corona.ron",
    "pse/fur.ron",
    "pse/marble.ron",
    "pse/spinning_marble.ron",
    "pse/tribble.ron",
    "pse/water.ron",
    "pse/wood.ron",
    "mesh/furry_spot.ron",
    "mesh/furry_teddy.ron",
    "mesh/wool_spot.ron",
    "gilet/cave.ron",
    "gilet/clods.ron",
    "gilet/clouds_one_noise.ron",
    "gilet/clouds_three_noises.ron",
    "gilet/craters_r0.ron",
    "gilet/craters_r05.ron",
    "gilet/craters_r1.ron",
    "gilet/field_boundary.ron",
    "gilet/field_constant.ron",
    "gilet/field_curl.ron",
    "gilet/field_perturbed.ron",
    "gilet/field_perturbed_curl.ron",
    "gilet/field_shifted_centre.ron",
    "gilet/hedge.ron",
    "gilet/holes_r0.ron",
    "gilet/holes_r05.ron",
    "gilet/holes_r1.ron",
    "gilet/identity_r0.ron",
    "gilet/identity_r05.ron",
    "gilet/identity_r1.ron",
    "gilet/isolines_r0.ron",
    "gilet/isolines_r05.ron",
    "gilet/isolines_r1.ron",
    "gilet/lawn.ron",
    "gilet/motion_blur.ron",
    "gilet/multi_blend_bumps.ron",
    "gilet/multi_sum_holes.ron",
    "gilet/multi_sum_turbulence.ron",
    "gilet/mushrooms.ron",
    "gilet/sponge.ron",
    "gilet/wool.ron",
];

/// Why the probe could not run: a probe scene that does not build (a defect of
/// this build, reported rather than hidden in a digest).
#[derive(Debug, thiserror::Error)]
#[error("probe scene scenes/{path}: {error}")]
pub struct ProbeError {
    /// The scene's path under `scenes/`.
    pub path: &'static str,
    /// Why it did not build.
    pub error: crate::SceneError,
}

/// The digest of this build's arithmetic on instruction-set path `isa` (which
/// must be available): FNV-1a over every channel's bits and the 8-bit sRGB
/// encoding of the probe pixels of every probe scene. Pure and deterministic;
/// it runs on the calling thread (about 5 ms in a release build: on a farm,
/// the coordinator's CPU budget).
pub fn digest(isa: Isa) -> Result<u64, ProbeError> {
    let mut h = Fnv1a::default();
    for &(path, text) in PROBE_SCENES {
        h.write(probe_render(path, text, isa)?);
    }
    Ok(h.finish())
}

/// The files the probe scenes name. A mesh scene is probed on a stand-in for
/// its mesh (an icosphere), read by the same OBJ reader and walked by the
/// same tree and closest-point code as the scene's own: Spot's 5,856
/// triangles cost 14 ms to read and build, three times the rest of the probe,
/// in every worker and coordinator process. Built once per process.
fn probe_assets() -> &'static crate::scene::Assets {
    static ASSETS: std::sync::OnceLock<crate::scene::Assets> = std::sync::OnceLock::new();
    ASSETS.get_or_init(|| {
        let mut assets = crate::scene::Assets::none();
        // An icosahedron cut in four (80 triangles) inside Spot's box, where
        // the mesh scenes look. A test loads every probe scene, so a stand-in
        // that fails to build cannot go unnoticed.
        let stand_in = crate::mesh::icosphere_obj(glam::Vec3::new(0.0, 0.1, 0.18), 0.45, 1);
        if let Ok(mesh) =
            crate::mesh::Mesh::from_obj("meshes/spot.obj", stand_in.as_bytes(), Default::default())
        {
            let mesh = std::sync::Arc::new(mesh);
            for path in ["meshes/spot.obj", "meshes/teddy.obj"] {
                assets.insert(path, std::sync::Arc::clone(&mesh));
            }
        }
        assets
    })
}

/// A probe scene's text with its meshes read exactly (`sdf: Exact`): a mesh's
/// distance field costs every process hundreds of milliseconds to build,
/// against the probe's few, and its trilinear read is the same scalar
/// arithmetic on every path; the exact search is the arithmetic that
/// differs between instruction sets.
fn exact_meshes(text: &str) -> std::borrow::Cow<'_, str> {
    if text.contains("Mesh(path:") {
        text.replace("Mesh(path:", "Mesh(sdf: Exact, path:").into()
    } else {
        text.into()
    }
}

/// The bytes the digest hashes for one probe scene: each probe pixel's channels
/// (little-endian f32 bits) and its 8-bit sRGB encoding.
fn probe_render(path: &'static str, text: &str, isa: Isa) -> Result<Vec<u8>, ProbeError> {
    // The interactive step and at most two samples a pixel: the same
    // arithmetic as the scene's own, on fewer samples.
    let build = |spp| {
        let overrides = Overrides {
            width: Some(PROBE_SIZE),
            height: Some(PROBE_SIZE),
            spp,
            quality: Some(Quality::Interactive),
            ..Overrides::default()
        };
        Scene::from_text_with(&exact_meshes(text), path, overrides, Some(probe_assets()))
            .map_err(|error| ProbeError { path, error })
    };
    let mut scene = build(None)?;
    if scene.spp() > PROBE_SPP {
        scene = build(Some(PROBE_SPP))?;
    }
    scene.set_isa(isa);
    let mut bytes = Vec::new();
    for (x, y) in PROBE_PIXELS {
        let sample = render_pixel(&scene, x, y, PROBE_FRAME);
        for v in sample.to_array() {
            bytes.extend_from_slice(&v.to_bits().to_le_bytes());
        }
        bytes.extend_from_slice(&srgb8(&sample));
    }
    Ok(bytes)
}

/// [`digest`] on the fastest path this CPU has (the one scenes render on),
/// computed once per process: every worker a process runs (the
/// coordinator's in-process fallback, a test's thousand clients) registers
/// with the same digest.
pub fn arithmetic_digest() -> Result<u64, ProbeError> {
    static DIGEST: std::sync::OnceLock<u64> = std::sync::OnceLock::new();
    if let Some(&d) = DIGEST.get() {
        return Ok(d);
    }
    let d = digest(Isa::detect())?;
    Ok(*DIGEST.get_or_init(|| d))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn mesh_scenes_are_probed_on_the_exact_distance() {
        let meshes: Vec<_> = PROBE_SCENES
            .iter()
            .filter(|(_, text)| text.contains("Mesh("))
            .collect();
        assert!(!meshes.is_empty());
        for (path, text) in meshes {
            let probed = exact_meshes(text);
            assert_eq!(
                probed.matches("Mesh(sdf: Exact, path:").count(),
                text.matches("Mesh(").count(),
                "{path}"
            );
        }
    }

    #[test]
    fn every_path_gives_the_same_digest() {
        let reference = digest(Isa::Scalar).unwrap();
        for isa in Isa::available() {
            assert_eq!(digest(isa).unwrap(), reference, "{}", isa.name());
        }
        assert_eq!(arithmetic_digest().unwrap(), reference);
    }

    #[test]
    fn probe_scenes_are_not_blank() {
        // A probe that only saw the background would vouch for nothing: every
        // scene must put density in front of some probe pixel (the density
        // channel is the fifth f32 of each pixel's 40 bytes).
        for &(path, text) in PROBE_SCENES {
            let bytes = probe_render(path, text, Isa::Scalar).unwrap();
            let hit = bytes
                .chunks(40)
                .any(|pixel| f32::from_le_bytes(pixel[16..20].try_into().unwrap()) > 0.0);
            assert!(hit, "{path}: no probe pixel meets the object");
        }
    }

    #[test]
    fn one_ulp_changes_the_digest() {
        // The fur's opacity nudged by one ulp (40 → 40.000004) must change
        // what the probe hashes.
        let (path, text) = PROBE_SCENES[5];
        assert_eq!(path, "fur.ron");
        let nudged = text.replace("opacity: 40.0", "opacity: 40.000004");
        assert_ne!(nudged, text);
        assert_ne!(
            probe_render(path, text, Isa::Scalar).unwrap(),
            probe_render(path, &nudged, Isa::Scalar).unwrap()
        );
    }

    #[test]
    fn every_scene_of_the_repository_is_a_probe_scene() {
        // Colour maps are not scenes; the benchmark scenes repeat the fur.
        let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../scenes");
        let mut missing = Vec::new();
        let mut dirs = vec![root.clone()];
        while let Some(dir) = dirs.pop() {
            for entry in std::fs::read_dir(&dir).unwrap() {
                let path = entry.unwrap().path();
                let name = path
                    .strip_prefix(&root)
                    .unwrap()
                    .to_string_lossy()
                    .into_owned();
                if path.is_dir() {
                    if name != "colormaps" && name != "bench" {
                        dirs.push(path);
                    }
                } else if name.ends_with(".ron") && !PROBE_SCENES.iter().any(|&(p, _)| p == name) {
                    missing.push(name);
                }
            }
        }
        assert!(missing.is_empty(), "not in PROBE_SCENES: {missing:?}");
    }
}
