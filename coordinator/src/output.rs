//! Writing a [`Film`] to disk: 8-bit sRGB PNG, or float OpenEXR with the AOVs.
//!
//! Encoders are pure functions of the film (same film, same bytes), and files are
//! written atomically (temporary file, then rename), so a preview reader never
//! sees half an image.

use std::io::Write;
use std::path::{Path, PathBuf};

use hypertexture::{Film, PixelFormat};

use crate::canvas::FrameImage;

/// Image formats we write, chosen by the output file's extension.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ImageFormat {
    /// 8-bit sRGB with straight alpha.
    Png,
    /// 32-bit float, linear premultiplied RGBA plus `density`, `depth`, `normal.X/Y/Z`.
    Exr,
}

/// Why an image could not be written.
#[derive(Debug, thiserror::Error)]
pub enum OutputError {
    /// The extension names no format we write.
    #[error("{path}: unsupported output format (use a .png or .exr file name)")]
    UnsupportedFormat {
        /// The output path.
        path: PathBuf,
    },
    /// Encoding failed.
    #[error("{path}: cannot encode the image: {message}")]
    Encode {
        /// The output path (or `<memory>`).
        path: PathBuf,
        /// The encoder's message.
        message: String,
    },
    /// The file could not be written.
    #[error("{path}: cannot write the image: {source}")]
    Io {
        /// The output path.
        path: PathBuf,
        /// What the OS said.
        source: std::io::Error,
    },
}

impl ImageFormat {
    /// The format for `path`'s extension (case-insensitive).
    pub fn from_path(path: &Path) -> Result<ImageFormat, OutputError> {
        let ext = path
            .extension()
            .and_then(|e| e.to_str())
            .map(str::to_ascii_lowercase);
        match ext.as_deref() {
            Some("png") => Ok(ImageFormat::Png),
            Some("exr") => Ok(ImageFormat::Exr),
            _ => Err(OutputError::UnsupportedFormat {
                path: path.to_path_buf(),
            }),
        }
    }
}

/// Encodes the film as an 8-bit sRGB PNG with alpha.
pub fn encode_png(film: &Film) -> Result<Vec<u8>, OutputError> {
    encode_srgb8_png(&film.to_srgb8(), film.width(), film.height())
}

/// Encodes straight-alpha 8-bit sRGB RGBA bytes ([`Film::to_srgb8`]) as a PNG.
pub fn encode_srgb8_png(bytes: &[u8], width: u32, height: u32) -> Result<Vec<u8>, OutputError> {
    use image::ImageEncoder;
    use image::codecs::png::{CompressionType, FilterType, PngEncoder};
    let mut out = Vec::new();
    PngEncoder::new_with_quality(&mut out, CompressionType::Fast, FilterType::Adaptive)
        .write_image(bytes, width, height, image::ExtendedColorType::Rgba8)
        .map_err(|e| OutputError::Encode {
            path: PathBuf::from("<memory>"),
            message: e.to_string(),
        })?;
    Ok(out)
}

/// The names of the EXR channels, in the order of [`hypertexture::Sample::to_array`].
pub const EXR_CHANNELS: [&str; 9] = [
    "R", "G", "B", "A", "density", "depth", "normal.X", "normal.Y", "normal.Z",
];

/// Encodes the film as a scanline OpenEXR of 32-bit float channels
/// (ZIP-compressed, lossless).
pub fn encode_exr(film: &Film) -> Result<Vec<u8>, OutputError> {
    use exr::prelude::*;
    let size = (film.width() as usize, film.height() as usize);
    let channels: Vec<AnyChannel<FlatSamples>> = EXR_CHANNELS
        .iter()
        .enumerate()
        .map(|(c, name)| {
            let values = film.pixels().iter().map(|s| s.to_array()[c]).collect();
            AnyChannel::new(*name, FlatSamples::F32(values))
        })
        .collect();
    let encoding = Encoding {
        compression: Compression::ZIP16,
        blocks: Blocks::ScanLines,
        line_order: LineOrder::Increasing,
    };
    let layer = Layer::new(
        size,
        LayerAttributes::named("hypertexture"),
        encoding,
        AnyChannels::sort(channels.into()),
    );
    let mut cursor = std::io::Cursor::new(Vec::new());
    Image::from_layer(layer)
        .write()
        .non_parallel()
        .to_buffered(&mut cursor)
        .map_err(|e| OutputError::Encode {
            path: PathBuf::from("<memory>"),
            message: e.to_string(),
        })?;
    Ok(cursor.into_inner())
}

/// Encodes the film in the format `path` names.
pub fn encode(film: &Film, format: ImageFormat) -> Result<Vec<u8>, OutputError> {
    match format {
        ImageFormat::Png => encode_png(film),
        ImageFormat::Exr => encode_exr(film),
    }
}

/// Writes the film to `path` in the format its extension names, atomically.
pub fn write_image(film: &Film, path: &Path) -> Result<(), OutputError> {
    let bytes = encode(film, ImageFormat::from_path(path)?).map_err(|e| e.at(path))?;
    write_atomically(path, &bytes)
}

impl OutputError {
    /// An encoder's error (made for `<memory>`) as the error of writing `path`.
    fn at(self, path: &Path) -> OutputError {
        match self {
            OutputError::Encode { message, .. } => OutputError::Encode {
                path: path.to_path_buf(),
                message,
            },
            other => other,
        }
    }
}

/// What the farm's tiles must carry for these outputs: 8-bit sRGB when every one
/// is a PNG (a ninth of the bytes), every sample otherwise.
pub fn pixel_format_for<'a>(outputs: impl IntoIterator<Item = &'a Path>) -> PixelFormat {
    let png = |p: &Path| matches!(ImageFormat::from_path(p), Ok(ImageFormat::Png));
    if outputs.into_iter().all(png) {
        PixelFormat::Srgb8
    } else {
        PixelFormat::Samples
    }
}

/// Writes a frame's image to `path` like [`write_image`]; an image collected as
/// 8-bit sRGB can only become a PNG.
pub fn write_frame_image(image: &FrameImage, path: &Path) -> Result<(), OutputError> {
    let (width, height, bytes) = match image {
        FrameImage::Film(film) => return write_image(film, path),
        FrameImage::Srgb8 {
            width,
            height,
            bytes,
        } => (*width, *height, bytes),
    };
    let encoded = match ImageFormat::from_path(path)? {
        ImageFormat::Png => encode_srgb8_png(bytes, width, height).map_err(|e| e.at(path))?,
        ImageFormat::Exr => {
            return Err(OutputError::Encode {
                path: path.to_path_buf(),
                message: "an EXR keeps every channel, and this image has only 8-bit colour".into(),
            });
        }
    };
    write_atomically(path, &encoded)
}

/// Writes `bytes` to a temporary file beside `path`, then renames it over `path`.
pub fn write_atomically(path: &Path, bytes: &[u8]) -> Result<(), OutputError> {
    let io = |source| OutputError::Io {
        path: path.to_path_buf(),
        source,
    };
    let dir = match path.parent() {
        Some(d) if !d.as_os_str().is_empty() => d.to_path_buf(),
        _ => PathBuf::from("."),
    };
    let name = path
        .file_name()
        .map_or_else(|| "image".into(), |n| n.to_string_lossy().into_owned());
    let temp = dir.join(format!(".{name}.{}.tmp", std::process::id()));
    let result = std::fs::File::create(&temp)
        .and_then(|mut f| f.write_all(bytes).and_then(|_| f.sync_all()))
        .and_then(|_| std::fs::rename(&temp, path));
    if result.is_err() {
        let _ = std::fs::remove_file(&temp);
    }
    result.map_err(io)
}

#[cfg(test)]
mod tests {
    use super::*;
    use hypertexture::Sample;

    fn film() -> Film {
        let mut film = Film::new(5, 3);
        for y in 0..3 {
            for x in 0..5 {
                let v = (y * 5 + x) as f32;
                film.set(
                    x,
                    y,
                    Sample {
                        rgba: [v / 20.0, 0.5, 0.25, 1.0],
                        density: v / 15.0,
                        depth: 1.0 + v,
                        normal: [0.0, 1.0, v / 100.0],
                    },
                );
            }
        }
        film
    }

    #[test]
    fn format_by_extension() {
        assert_eq!(
            ImageFormat::from_path(Path::new("a.png")).unwrap(),
            ImageFormat::Png
        );
        assert_eq!(
            ImageFormat::from_path(Path::new("dir/A.PNG")).unwrap(),
            ImageFormat::Png
        );
        assert_eq!(
            ImageFormat::from_path(Path::new("a.exr")).unwrap(),
            ImageFormat::Exr
        );
        let err = ImageFormat::from_path(Path::new("out/a.jpg")).unwrap_err();
        assert!(err.to_string().contains("out/a.jpg") && err.to_string().contains(".png"));
        assert!(ImageFormat::from_path(Path::new("noext")).is_err());
    }

    #[test]
    fn png_unpremultiplies_and_round_trips() {
        let mut f = Film::new(1, 1);
        f.set(
            0,
            0,
            Sample {
                rgba: [0.25, 0.0, 0.0, 0.5],
                ..Sample::default()
            },
        );
        let png = encode_png(&f).unwrap();
        let img = image::load_from_memory(&png).unwrap().to_rgba8();
        assert_eq!(img.dimensions(), (1, 1));
        assert_eq!(img.get_pixel(0, 0).0, [188, 0, 0, 128]);
        assert_eq!(png, encode_png(&f).unwrap(), "deterministic");
    }

    #[test]
    fn exr_has_the_nine_channels_and_values() {
        use exr::prelude::*;
        let film = film();
        let bytes = encode_exr(&film).unwrap();
        assert_eq!(bytes, encode_exr(&film).unwrap(), "deterministic");
        let image = read()
            .no_deep_data()
            .largest_resolution_level()
            .all_channels()
            .all_layers()
            .all_attributes()
            .from_buffered(std::io::Cursor::new(bytes))
            .unwrap();
        let layer = &image.layer_data[0];
        assert_eq!(layer.size, Vec2(5, 3));
        let mut names: Vec<String> = layer
            .channel_data
            .list
            .iter()
            .map(|c| c.name.to_string())
            .collect();
        names.sort();
        let mut expected: Vec<String> = EXR_CHANNELS.iter().map(|s| s.to_string()).collect();
        expected.sort();
        assert_eq!(names, expected);
        for channel in &layer.channel_data.list {
            let c = EXR_CHANNELS
                .iter()
                .position(|n| channel.name.to_string() == *n)
                .unwrap();
            let FlatSamples::F32(values) = &channel.sample_data else {
                panic!("{} is not f32", channel.name);
            };
            for (i, v) in values.iter().enumerate() {
                let (x, y) = ((i % 5) as u32, (i / 5) as u32);
                assert_eq!(
                    *v,
                    film.get(x, y).to_array()[c],
                    "{} at {x},{y}",
                    channel.name
                );
            }
        }
    }

    #[test]
    fn write_is_atomic_and_clean() {
        let dir = std::env::temp_dir().join(format!("ht-output-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("x.png");
        write_image(&film(), &path).unwrap();
        let entries: Vec<_> = std::fs::read_dir(&dir)
            .unwrap()
            .map(|e| e.unwrap().file_name())
            .collect();
        assert_eq!(entries, vec![std::ffi::OsString::from("x.png")]);
        let err = write_image(&film(), &dir.join("missing/x.png")).unwrap_err();
        assert!(err.to_string().contains("missing/x.png"));
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn an_srgb8_image_writes_the_same_png_and_refuses_an_exr() {
        let dir = std::env::temp_dir().join(format!("ht-output-8-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let film = film();
        let image = FrameImage::Srgb8 {
            width: film.width(),
            height: film.height(),
            bytes: film.to_srgb8(),
        };
        write_image(&film, &dir.join("film.png")).unwrap();
        write_frame_image(&image, &dir.join("bytes.png")).unwrap();
        assert_eq!(
            std::fs::read(dir.join("film.png")).unwrap(),
            std::fs::read(dir.join("bytes.png")).unwrap()
        );
        let err = write_frame_image(&image, &dir.join("x.exr")).unwrap_err();
        assert!(err.to_string().contains("x.exr") && err.to_string().contains("8-bit"));
        assert!(!dir.join("x.exr").exists());
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
