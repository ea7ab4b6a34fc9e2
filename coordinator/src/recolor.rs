//! Two-pass compositing (Perlin 1985): the EXR keeps the scalar field per pixel
//! (the `density` channel, the opacity-weighted density along the ray), so a new
//! colour map can be applied to a finished render without rendering again.

use std::path::Path;
use std::time::Instant;

use hypertexture::{Film, Sample};

use crate::{CoordinatorError, output};

/// The `density` and `A` channels of an EXR written by the coordinator.
pub struct DensityImage {
    /// Width in pixels.
    pub width: u32,
    /// Height in pixels.
    pub height: u32,
    /// (density, alpha) per pixel, row-major.
    pub pixels: Vec<(f32, f32)>,
}

/// Reads the `density` and `A` channels of `path`.
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
        .collect_pixels(
            |resolution, _| {
                (
                    resolution.width(),
                    vec![(0.0f32, 0.0f32); resolution.width() * resolution.height()],
                )
            },
            |(width, pixels): &mut (usize, Vec<(f32, f32)>), position, (d, a): (f32, f32)| {
                pixels[position.y() * *width + position.x()] = (d, a);
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
    hypertexture::scene::desc::check_resolution(width, height).map_err(fail)?;
    Ok(DensityImage {
        width,
        height,
        pixels: image.layer_data.channel_data.pixels.1,
    })
}

/// The film of `image` coloured by `map`: colour = map(density), premultiplied by
/// the pixel's alpha (the background is left transparent).
pub fn recolor(image: &DensityImage, map: &hypertexture::curve::Curve<3>) -> Film {
    let mut film = Film::new(image.width, image.height);
    for (out, &(density, alpha)) in film.pixels_mut().iter_mut().zip(&image.pixels) {
        let alpha = if alpha.is_finite() {
            alpha.clamp(0.0, 1.0)
        } else {
            0.0
        };
        let c = map.eval(density);
        *out = Sample {
            rgba: [c[0] * alpha, c[1] * alpha, c[2] * alpha, alpha],
            density,
            ..Sample::default()
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
    output::write_image(&film, out)?;
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
