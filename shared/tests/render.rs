//! Whole-render properties: determinism across thread counts and tilings, and
//! independence of the marching step.

use hypertexture::{Film, Overrides, Scene};

fn scene(name: &str, size: u32) -> Scene {
    let path =
        std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join(format!("../scenes/{name}.ron"));
    Scene::load(
        path,
        Overrides {
            width: Some(size),
            height: Some(size),
            ..Overrides::default()
        },
    )
    .unwrap()
}

fn render_with(scene: &Scene, threads: usize) -> Film {
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()
        .unwrap();
    pool.install(|| hypertexture::render::render(scene, 0, &|_| {}))
}

fn bits(film: &Film) -> Vec<u32> {
    film.pixels()
        .iter()
        .flat_map(|s| s.to_array())
        .map(f32::to_bits)
        .collect()
}

#[test]
fn one_thread_and_many_give_identical_bits() {
    for name in ["fur", "blue_glass"] {
        let scene = scene(name, 40);
        let serial = render_with(&scene, 1);
        for threads in [2, 3, 8] {
            assert_eq!(
                bits(&serial),
                bits(&render_with(&scene, threads)),
                "{name} with {threads} threads"
            );
        }
    }
}

#[test]
fn any_pixel_can_be_rendered_alone_in_any_order() {
    let scene = scene("tribble", 24);
    let film = render_with(&scene, 2);
    let mut pixels: Vec<(u32, u32)> = (0..24).flat_map(|y| (0..24).map(move |x| (x, y))).collect();
    pixels.reverse();
    let samples = hypertexture::render::render_pixels(&scene, 0, &pixels);
    for (&(x, y), s) in pixels.iter().zip(&samples) {
        assert_eq!(
            film.get(x, y).to_array().map(f32::to_bits),
            s.to_array().map(f32::to_bits)
        );
    }
}

#[test]
fn every_sample_is_finite() {
    for name in ["fur", "blue_glass", "fire_ball", "eroded_cube"] {
        let film = render_with(&scene(name, 24), 2);
        assert!(film.pixels().iter().all(|s| s.is_finite()), "{name}");
    }
}

/// α = 1 - (1 - density)^(c·step) makes the picture independent of the step: the
/// fur rendered at step s and at s/2 differs little. Measured: mean absolute
/// difference of the linear RGBA channels 0.0088 at 48×48; the bound is 0.02.
#[test]
fn opacity_is_resolution_independent() {
    let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../scenes/fur.ron");
    let text = std::fs::read_to_string(path).unwrap();
    let size = Overrides {
        width: Some(48),
        height: Some(48),
        ..Overrides::default()
    };
    let coarse = Scene::from_text(&text, "fur.ron", size.clone()).unwrap();
    let fine = Scene::from_text(
        &text.replace("Diagonal(200)", "Diagonal(400)"),
        "fur-fine.ron",
        size,
    )
    .unwrap();
    assert!((coarse.step() / fine.step() - 2.0).abs() < 1e-5);
    let (a, b) = (render_with(&coarse, 2), render_with(&fine, 2));
    let mut sum = 0.0f64;
    for (p, q) in a.pixels().iter().zip(b.pixels()) {
        for c in 0..4 {
            sum += f64::from((p.rgba[c] - q.rgba[c]).abs());
        }
    }
    let mad = sum / (a.pixels().len() * 4) as f64;
    println!("mean absolute difference between step s and s/2: {mad:.4}");
    assert!(mad < 0.02, "mean absolute difference {mad}");
    // And it is not trivially zero: the fur is actually there.
    let coverage: f32 = a.pixels().iter().map(|s| s.rgba[3]).sum::<f32>() / a.pixels().len() as f32;
    assert!(coverage > 0.3, "coverage {coverage}");
}

#[test]
fn known_answer_hard_sphere_under_a_known_light() {
    // An opaque hard-edged sphere lit head-on by a unit white light with no ambient:
    // the centre pixel sees the normal facing the light, so its colour is the
    // albedo; the corner pixel misses and sees the background.
    let text = r#"Scene(
        image: (width: 33, height: 33),
        camera: (eye: (0.0, 0.0, 5.0), look_at: (0.0, 0.0, 0.0), projection: Orthographic(height: 3.0)),
        background: Colour(0.0, 0.0, 1.0),
        lights: (ambient: (0.0, 0.0, 0.0), sources: [Directional(direction: (0.0, 0.0, 1.0), colour: (1.0, 1.0, 1.0))]),
        march: (bounds: (min: (-1.2, -1.2, -1.2), max: (1.2, 1.2, 1.2)), step: Length(0.002), opacity: 2000.0, threshold: 0.999),
        object: Sphere(radius: 1.0, softness: 0.05),
        colour_map: (points: [(0.0, (0.5, 0.25, 1.0))]),
    )"#;
    let scene = Scene::from_text(text, "known.ron", Overrides::default()).unwrap();
    let centre = hypertexture::render::render_pixel(&scene, 16, 16, 0);
    let expected = [0.5, 0.25, 1.0];
    for (got, want) in centre.rgba.iter().zip(expected) {
        assert!((got - want).abs() < 0.01, "{:?}", centre.rgba);
    }
    assert!(centre.rgba[3] > 0.999);
    assert!(
        (centre.normal[2] - 1.0).abs() < 0.01,
        "normal {:?}",
        centre.normal
    );
    // The first sample with density lies within a step of the outer radius 1.025.
    assert!(
        (centre.depth - (5.0 - 1.025)).abs() < 0.005,
        "depth {}",
        centre.depth
    );
    let corner = hypertexture::render::render_pixel(&scene, 0, 0, 0);
    assert_eq!(corner.rgba, [0.0, 0.0, 1.0, 1.0]);
    assert_eq!(corner.depth, 0.0);
}

const GALLERY: [&str; 10] = [
    "noisy_sphere",
    "noisy_sphere_high_frequency",
    "noisy_sphere_high_amplitude",
    "fractal_sphere",
    "dripping_sphere",
    "eroded_cube",
    "blue_glass",
    "fire_ball",
    "fur",
    "tribble",
];

/// The 1989 gallery at 40×40 and every other scene under scenes/ at 20×20.
fn every_scene() -> Vec<(String, u32)> {
    let mut all: Vec<(String, u32)> = GALLERY.iter().map(|n| (n.to_string(), 40)).collect();
    let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../scenes");
    for dir in ["gilet", "pse", "mesh"] {
        let Ok(entries) = std::fs::read_dir(root.join(dir)) else {
            continue;
        };
        let mut names: Vec<String> = entries
            .filter_map(|e| {
                let name = e.ok()?.file_name().into_string().ok()?;
                Some(format!("{dir}/{}", name.strip_suffix(".ron")?))
            })
            .collect();
        names.sort();
        all.extend(names.into_iter().map(|n| (n, 20)));
    }
    all
}

/// Every instruction-set path this CPU has (scalar, SSE4.1, AVX2) renders every
/// scene to the same bits: what lets mixed CPUs share one image.
#[test]
fn every_simd_path_renders_the_same_bits() {
    use hypertexture::math::simd::Isa;
    let paths = Isa::available();
    eprintln!("paths on this CPU: {paths:?}");
    for (name, size) in every_scene() {
        let name = name.as_str();
        let mut s = scene(name, size);
        assert!(s.set_isa(Isa::Scalar));
        let reference = bits(&render_with(&s, 2));
        for &isa in &paths[1..] {
            assert!(s.set_isa(isa));
            assert_eq!(reference, bits(&render_with(&s, 2)), "{name} on {isa:?}");
        }
    }
}

/// Skipping the space where the density is 0 for certain changes no bit.
#[test]
fn empty_space_skipping_changes_nothing() {
    for (name, size) in every_scene() {
        let name = name.as_str();
        let mut s = scene(name, size);
        let skipped = bits(&render_with(&s, 2));
        s.set_empty_space_skipping(false);
        assert_eq!(skipped, bits(&render_with(&s, 2)), "{name}");
    }
}

/// The dual-number gradient is the derivative of the density: at points of
/// every scene's soft region, its value is the density and its gradient agrees
/// with fine central differences of the density (but at the few points within
/// a difference's reach of a kink or a jump: a clamp, |noise| = 0, a face of a
/// box, a seam of a distortion).
#[test]
fn the_dual_gradient_is_the_derivative() {
    let mut rng = 0x2545_f491_4f6c_dd1du64;
    let mut uniform = move || {
        rng ^= rng << 13;
        rng ^= rng >> 7;
        rng ^= rng << 17;
        (rng >> 40) as f32 / (1u64 << 24) as f32
    };
    let h = 1e-4;
    let mut scenes_with_soft_points = 0;
    let all = every_scene();
    for (name, _) in &all {
        let s = scene(name, 8);
        let (min, max) = s.bounds();
        let (mut soft, mut agree) = (0, 0);
        for _ in 0..20_000 {
            if soft == 200 {
                break;
            }
            let x = min + (max - min) * glam::Vec3::new(uniform(), uniform(), uniform());
            let f = s.density_at(x, 0);
            if !(f > 0.0 && f < 1.0) {
                continue;
            }
            soft += 1;
            // The distortion and expressions are differentiated by central
            // differences: as fine as the reference's here.
            let (value, gradient) = s.density_gradient_with(x, 0, h);
            assert!((value - f).abs() <= 1e-5, "{name} at {x:?}: {value} vs {f}");
            assert!(gradient.is_finite(), "{name} at {x:?}: {gradient:?}");
            let d = |e: glam::Vec3| {
                (s.density_at(x + e * h, 0) - s.density_at(x - e * h, 0)) / (2.0 * h)
            };
            let fd = glam::Vec3::new(d(glam::Vec3::X), d(glam::Vec3::Y), d(glam::Vec3::Z));
            if (gradient - fd).length() <= 0.02 * fd.length() + 0.02 {
                agree += 1;
            }
        }
        eprintln!("{name}: {agree} of {soft} soft points agree");
        scenes_with_soft_points += usize::from(soft > 0);
        assert!(
            agree * 10 >= soft * 9,
            "{name}: only {agree} of {soft} soft points agree"
        );
    }
    // Only hard objects (pse/corona's slab) have no soft region.
    assert!(
        scenes_with_soft_points + 2 >= all.len(),
        "{scenes_with_soft_points}"
    );
}

/// `gradient: Dual` renders the same bits on every instruction-set path, and
/// an image close to the paper's differences: the normals differ where the
/// density bends within a step, not the picture.
#[test]
fn the_dual_gradient_renders_exactly_and_close_to_the_differences() {
    use hypertexture::math::simd::Isa;
    use hypertexture::scene::Gradient;
    for name in ["noisy_sphere", "fur", "gilet/holes_r05"] {
        let mut s = scene(name, 32);
        let forward = render_with(&s, 2).to_srgb8();
        s.set_gradient(Gradient::Dual);
        assert!(s.set_isa(Isa::Scalar));
        let dual = render_with(&s, 2);
        for &isa in &Isa::available()[1..] {
            assert!(s.set_isa(isa));
            assert_eq!(bits(&dual), bits(&render_with(&s, 2)), "{name} on {isa:?}");
        }
        let dual = dual.to_srgb8();
        assert_ne!(dual, forward, "{name}: the normals should differ a little");
        let mean = dual
            .iter()
            .zip(&forward)
            .map(|(a, b)| f64::from(a.abs_diff(*b)))
            .sum::<f64>()
            / dual.len() as f64;
        eprintln!("{name}: mean 8-bit difference {mean:.2}");
        assert!(mean < 12.0, "{name}: mean 8-bit difference {mean}");
    }
}
