//! Two-pass compositing (Perlin 1985): the EXR keeps the scalar field per pixel
//! (the `density` channel, the opacity-weighted density along the ray), so a new
//! colour map can be applied to a finished render without rendering again.

use std::path::Path;
use std::time::Instant;

use hypertexture::{Film, Sample};

use crate::{CoordinatorError, image::output};

/// The channels of an EXR written by the coordinator that a new colour map
/// keeps: `density` and `A`, and the AOVs carried through (`depth`,
/// `normal.X/Y/Z`; zero where the file has none).
pub struct DensityImage {
    /// Width in pixels.
    pub width: u32,
    /// Height in pixels.
    pub height: u32,
    /// (density, alpha) per pixel, row-major.
    pub pixels: Vec<(f32, f32)>,
    /// (depth, normal) per pixel, row-major.
    pub aovs: Vec<(f32, [f32; 3])>,
    /// The file's `worldToCamera`.
    pub world_to_camera: Option<[f32; 16]>,
    /// The file's `worldToNDC`.
    pub world_to_ndc: Option<[f32; 16]>,
}

/// One pixel as read: density, alpha, depth, normal.X/Y/Z.
type Channels = (f32, f32, f32, f32, f32, f32);

/// Reads the `density` and `A` channels of `path`, and its AOVs.
pub fn read_density(path: &Path) -> Result<DensityImage, CoordinatorError> {
    use exr::prelude::*;
    let fail = |message: String| CoordinatorError::Recolor {
        path: path.to_path_buf(),
        message,
    };
    let bytes = crate::files::read_capped(path, crate::files::MAX_EXR_BYTES, "EXR")?;
    let image = read()
        .no_deep_data()
        .largest_resolution_level()
        .specific_channels()
        .required("density")
        .required("A")
        .optional("depth", 0.0f32)
        .optional("normal.X", 0.0f32)
        .optional("normal.Y", 0.0f32)
        .optional("normal.Z", 0.0f32)
        .collect_pixels(
            |resolution, _| {
                (
                    resolution.width(),
                    vec![Channels::default(); resolution.width() * resolution.height()],
                )
            },
            |(width, pixels): &mut (usize, Vec<Channels>), position, pixel: Channels| {
                pixels[position.y() * *width + position.x()] = pixel;
            },
        )
        .first_valid_layer()
        .all_attributes()
        .from_buffered(std::io::Cursor::new(bytes))
        .map_err(|e| fail(format!("cannot read the density channel: {e}")))?;
    let size = image.layer_data.size;
    let (width, height) = (
        u32::try_from(size.width()).map_err(|_| fail("image too wide".into()))?,
        u32::try_from(size.height()).map_err(|_| fail("image too tall".into()))?,
    );
    hypertexture::desc::check_resolution(width, height).map_err(fail)?;
    let attributes = &image.layer_data.attributes;
    let channels = &image.layer_data.channel_data.pixels.1;
    Ok(DensityImage {
        width,
        height,
        pixels: channels.iter().map(|c| (c.0, c.1)).collect(),
        aovs: channels.iter().map(|c| (c.2, [c.3, c.4, c.5])).collect(),
        world_to_camera: attributes.world_to_camera,
        world_to_ndc: attributes.world_to_normalized_device,
    })
}

/// The film of `image` coloured by `map`: colour = map(density), premultiplied by
/// the pixel's alpha (the background is left transparent); density, depth and
/// normal as they were.
pub fn recolor(image: &DensityImage, map: &hypertexture::field::curve::Curve<3>) -> Film {
    let mut film = Film::new(image.width, image.height);
    let pixels = image.pixels.iter().zip(&image.aovs);
    for (out, (&(density, alpha), &(depth, normal))) in film.pixels_mut().iter_mut().zip(pixels) {
        let alpha = if alpha.is_finite() {
            alpha.clamp(0.0, 1.0)
        } else {
            0.0
        };
        let c = map.eval(density);
        *out = Sample {
            rgba: [c[0] * alpha, c[1] * alpha, c[2] * alpha, alpha],
            density,
            depth,
            normal,
        };
    }
    film
}

/// `coordinator recolor`: reads `input`, applies the colour map file `colormap`,
/// writes `out`.
pub fn run(input: &Path, colormap: &Path, out: &Path) -> Result<(), CoordinatorError> {
    output::ImageFormat::from_path(out)?;
    let start = Instant::now();
    let text = hypertexture::scene::read_text(colormap)?;
    let map = hypertexture::scene::parse_colour_map(&text, &colormap.display().to_string())?;
    let image = read_density(input)?;
    let film = recolor(&image, &map);
    // The camera still places the image; the scene would render the old colours.
    let meta = output::ImageMetadata::without_scene(
        image.width,
        image.height,
        image.world_to_camera,
        image.world_to_ndc,
    );
    output::write_image(&film, out, &meta)?;
    tracing::info!(
        "recoloured {} ({}×{}) with {} in {:.3} s → {}",
        input.display(),
        image.width,
        image.height,
        colormap.display(),
        start.elapsed().as_secs_f64(),
        out.display()
    );
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn an_exr_recoloured_keeps_density_depth_normal_and_camera() {
        let dir = std::env::temp_dir().join(format!("ht-recolor-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let mut film = Film::new(3, 2);
        for (i, p) in film.pixels_mut().iter_mut().enumerate() {
            let v = i as f32;
            *p = Sample {
                rgba: [0.1, 0.2, 0.3, 0.5],
                density: v / 8.0,
                depth: 2.0 + v,
                normal: [v / 10.0, -1.0, 0.25],
            };
        }
        let camera: [f32; 16] = std::array::from_fn(|i| i as f32);
        let meta = output::ImageMetadata::without_scene(3, 2, Some(camera), Some(camera));
        let (input, out) = (dir.join("in.exr"), dir.join("out.exr"));
        output::write_image(&film, &input, &meta).unwrap();
        let colormap = dir.join("map.ron");
        std::fs::write(
            &colormap,
            "(interpolation: Linear, points: [(0.0, (1.0, 0.0, 0.0)), (1.0, (0.0, 0.0, 1.0))])",
        )
        .unwrap();
        run(&input, &colormap, &out).unwrap();
        let again = read_density(&out).unwrap();
        let map = hypertexture::scene::parse_colour_map(
            &std::fs::read_to_string(&colormap).unwrap(),
            "map",
        )
        .unwrap();
        let want = recolor(&read_density(&input).unwrap(), &map);
        for (i, p) in film.pixels().iter().enumerate() {
            assert_eq!(again.pixels[i], (p.density, p.rgba[3]), "pixel {i}");
            assert_eq!(again.aovs[i], (p.depth, p.normal), "pixel {i}");
            assert_eq!(want.pixels()[i].depth, p.depth);
        }
        assert_eq!(again.world_to_camera, Some(camera));
        assert_eq!(again.world_to_ndc, Some(camera));
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
