//! Whether an object goes on past the march's bounds: the rays are marched
//! only inside the bounds, so an object whose density reaches a face of them
//! is cut flat there (a sphere swapped in for a torus keeps the torus's flat
//! bounds). The density is sampled on a grid over each face.

use glam::Vec3;
use hypertexture::Scene;

/// Samples per side of each face's grid.
const GRID: u32 = 16;

/// The density above which a face counts as cutting the object: the faint
/// edge of a soft region that the bounds trim leaves no visible cut.
const VISIBLE: f32 = 0.05;

/// The faces of `scene`'s bounds (`-x`, `+x`, `-y`, …) where its density at
/// `frame` is visible.
pub fn faces_cut(scene: &Scene, frame: u32) -> Vec<&'static str> {
    const NAMES: [[&str; 2]; 3] = [["-x", "+x"], ["-y", "+y"], ["-z", "+z"]];
    let (min, max) = scene.bounds();
    let at = |lo: f32, hi: f32, i: u32| lo + (hi - lo) * (i as f32 + 0.5) / GRID as f32;
    let mut cut = Vec::new();
    for (axis, names) in NAMES.iter().enumerate() {
        let (u, v) = ((axis + 1) % 3, (axis + 2) % 3);
        for (side, name) in [min[axis], max[axis]].into_iter().zip(names) {
            let visible = (0..GRID * GRID).any(|k| {
                let mut p = Vec3::ZERO;
                p[axis] = side;
                p[u] = at(min[u], max[u], k % GRID);
                p[v] = at(min[v], max[v], k / GRID);
                scene.density_at(p, frame) > VISIBLE
            });
            if visible {
                cut.push(*name);
            }
        }
    }
    cut
}

/// The warning the page shows when an object leaves `scene`'s bounds.
pub fn warning(scene: &Scene, frame: u32) -> Option<String> {
    let cut = faces_cut(scene, frame);
    if cut.is_empty() {
        return None;
    }
    let (min, max) = scene.bounds();
    Some(format!(
        "the object goes on past the march bounds (min {:?}, max {:?}) at {}: the march cuts it \
         flat there; widen march.bounds to hold it",
        min.to_array(),
        max.to_array(),
        cut.join(", ")
    ))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn scene(text: &str) -> Scene {
        hypertexture::RenderRequest::new(text, "scene.ron")
            .build(None)
            .unwrap()
    }

    #[test]
    fn a_sphere_in_the_torus_bounds_is_cut_at_their_flat_faces() {
        let fur = include_str!("../../../../scenes/fur.ron");
        assert_eq!(faces_cut(&scene(fur), 0), Vec::<&str>::new());
        let torus = fur
            .lines()
            .find(|l| l.contains("object: Torus("))
            .expect("fur.ron's torus");
        let sphere = fur.replace(torus, "    object: Sphere(radius: 1.0, softness: 0.2),");
        let swapped = scene(&sphere);
        assert_eq!(faces_cut(&swapped, 0), ["-y", "+y"]);
        let why = warning(&swapped, 0).unwrap();
        assert!(
            why.contains("-y, +y") && why.contains("march.bounds"),
            "{why}"
        );
    }

    #[test]
    fn the_stock_scenes_stay_inside_their_bounds() {
        for (name, text) in [
            (
                "noisy_sphere",
                include_str!("../../../../scenes/noisy_sphere.ron"),
            ),
            (
                "fire_ball",
                include_str!("../../../../scenes/fire_ball.ron"),
            ),
            ("tribble", include_str!("../../../../scenes/tribble.ron")),
        ] {
            assert_eq!(warning(&scene(text), 0), None, "{name}");
        }
    }
}
