//! Writing a [`Film`] to disk: 8-bit sRGB PNG, or float OpenEXR with the AOVs.
//!
//! Encoders are pure functions of the film (same film, same bytes), and files are
//! written atomically (temporary file, then rename), so a preview reader never
//! sees half an image.

use std::io::Write;
use std::path::{Path, PathBuf};

use hypertexture::{Film, FrameRange, Overrides, PixelFormat, RenderRequest, Scene};

use crate::image::canvas::FrameImage;

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
    /// The image holds no usable stored render.
    #[error("{path}: {message}")]
    Stored {
        /// The image.
        path: PathBuf,
        /// What is missing or wrong.
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

/// What an image records of the render that made it: enough to place it in a
/// compositor (the camera) and to render it again bit for bit (the scene text
/// and every setting beside it that changes pixels). The same for a frame
/// whichever path wrote it (in-process, farm, service), so the files are too.
#[derive(Clone, Debug, PartialEq)]
pub struct ImageMetadata {
    /// `hypertexture <version>`.
    pub software: String,
    /// The request the image was rendered from: the scene's name and whole
    /// RON text (empty: the image records no scene, it was not rendered from
    /// one as it is, e.g. recoloured), its overrides with the image's size
    /// written in ([`RenderRequest::with_size_of`]), and the image's one
    /// frame.
    pub request: RenderRequest,
    /// Samples per pixel the image was rendered with.
    pub spp: u32,
    /// OpenEXR's `worldToCamera` (row-major, for row vectors).
    pub world_to_camera: Option<[f32; 16]>,
    /// OpenEXR's `worldToNDC` (row-major, for row vectors).
    pub world_to_ndc: Option<[f32; 16]>,
    /// The files the scene names (path as written, content hash): part of
    /// the scene hash.
    pub assets: Vec<(String, u64)>,
}

/// The `software` an image names.
pub fn software() -> String {
    format!("hypertexture {}", env!("CARGO_PKG_VERSION"))
}

/// Names of the EXR header attributes (PNG text keywords use `:` for `/`).
pub mod keys {
    /// The scene's name.
    pub const SCENE_NAME: &str = "hypertexture/sceneName";
    /// The scene's whole text.
    pub const SCENE: &str = "hypertexture/scene";
    /// The farm's scene hash, 16 hexadecimal digits.
    pub const SCENE_HASH: &str = "hypertexture/sceneHash";
    /// The frame.
    pub const FRAME: &str = "hypertexture/frame";
    /// Samples per pixel rendered.
    pub const SPP: &str = "hypertexture/spp";
    /// The command-line options beside the scene that changed the pixels.
    pub const OPTIONS: &str = "hypertexture/options";
}

impl ImageMetadata {
    /// The metadata of frame 0 of `scene`, built from `request`.
    pub fn new(scene: &Scene, request: &RenderRequest) -> ImageMetadata {
        ImageMetadata {
            software: software(),
            request: RenderRequest {
                frames: FrameRange::one(0),
                ..request.clone().with_size_of(scene)
            },
            spp: scene.spp(),
            world_to_camera: Some(scene.camera().world_to_camera()),
            world_to_ndc: Some(scene.camera().world_to_ndc()),
            assets: scene.asset_hashes().to_vec(),
        }
    }

    /// The metadata of an image that was not rendered from a scene as it is:
    /// the software and the camera, no scene.
    pub fn without_scene(
        width: u32,
        height: u32,
        world_to_camera: Option<[f32; 16]>,
        world_to_ndc: Option<[f32; 16]>,
    ) -> ImageMetadata {
        let mut request = RenderRequest::new(String::new(), String::new());
        request.overrides.width = Some(width);
        request.overrides.height = Some(height);
        ImageMetadata {
            software: software(),
            request,
            spp: 0,
            world_to_camera,
            world_to_ndc,
            assets: Vec::new(),
        }
    }

    /// The scene's fields as (EXR attribute name, value as text), none when
    /// the image records no scene.
    fn scene_fields(&self) -> Vec<(&'static str, String)> {
        if self.request.scene_text.is_empty() {
            return Vec::new();
        }
        vec![
            (keys::SCENE_NAME, self.request.scene_name.clone()),
            (keys::SCENE_HASH, format!("{:016x}", self.scene_hash())),
            (keys::FRAME, self.frame().to_string()),
            (keys::SPP, self.spp.to_string()),
            (keys::OPTIONS, self.options()),
            (keys::SCENE, self.request.scene_text.clone()),
        ]
    }

    /// The image's frame.
    pub fn frame(&self) -> u32 {
        self.request.frames.first
    }

    /// The same for `frame`.
    pub fn at_frame(&self, frame: u32) -> ImageMetadata {
        let mut meta = self.clone();
        meta.request.frames = FrameRange::one(frame);
        meta
    }

    /// The hash the farm's workers cache the built scene by (the same inputs).
    pub fn scene_hash(&self) -> u64 {
        hypertexture_proto::request::content_hash(&self.request, &self.assets)
    }

    /// The command-line options beside the scene that changed the pixels:
    /// `--spp 4 --quality interactive --set curliness=0.8` (knob values in
    /// Rust's shortest exact form).
    pub fn options(&self) -> String {
        let overrides = &self.request.overrides;
        let mut words = Vec::new();
        if let Some(spp) = overrides.spp {
            words.push(format!("--spp {spp}"));
        }
        if let Some(quality) = overrides.quality {
            words.push(format!("--quality {quality}"));
        }
        for (name, value) in &overrides.knobs {
            words.push(format!("--set {name}={value:?}"));
        }
        words.join(" ")
    }

    /// Parses [`ImageMetadata::options`] into the overrides (spp, quality, knobs).
    pub fn parse_options(options: &str) -> Result<Overrides, String> {
        let mut stored = Overrides::default();
        let mut words = options.split(' ').filter(|w| !w.is_empty());
        while let Some(flag) = words.next() {
            let value = words
                .next()
                .ok_or_else(|| format!("{flag} without a value"))?;
            match flag {
                "--spp" => {
                    stored.spp = Some(value.parse().map_err(|_| format!("--spp {value}"))?);
                }
                "--quality" => {
                    stored.quality = Some(value.parse().map_err(|e| format!("--quality {e}"))?);
                }
                "--set" => {
                    let knob = Overrides::parse_knob(value).map_err(|e| format!("--set {e}"))?;
                    stored.knobs.push(knob);
                }
                _ => return Err(format!("unknown option {flag}")),
            }
        }
        Ok(stored)
    }
}

/// Reads the render stored in a PNG's or EXR's metadata (the scene at most
/// [`hypertexture::scene::MAX_SCENE_BYTES`]): the request of
/// [`ImageMetadata::request`], its size the image's, for full samples.
pub fn read_stored_render(path: &Path) -> Result<RenderRequest, OutputError> {
    let fail = |message: String| OutputError::Stored {
        path: path.to_path_buf(),
        message,
    };
    let fields = match ImageFormat::from_path(path)? {
        ImageFormat::Png => read_png_fields(path),
        ImageFormat::Exr => read_exr_fields(path),
    }
    .map_err(fail)?;
    let field = |key: &str| {
        fields
            .iter()
            .find(|(k, _)| k == key)
            .map(|(_, v)| v.clone())
    };
    let Some(scene_text) = field(keys::SCENE) else {
        let missing = match ImageFormat::from_path(path)? {
            ImageFormat::Png => format!("`{}` text chunk", png_keyword(keys::SCENE)),
            ImageFormat::Exr => format!("`{}` attribute", keys::SCENE),
        };
        return Err(fail(format!(
            "the image holds no scene (no {missing}): it was not written by {} or its metadata was stripped",
            software()
        )));
    };
    if scene_text.len() > hypertexture::scene::MAX_SCENE_BYTES {
        return Err(fail(format!(
            "the stored scene is {} bytes; a scene may be at most {} bytes",
            scene_text.len(),
            hypertexture::scene::MAX_SCENE_BYTES
        )));
    }
    let number = |key: &str| -> Result<u32, OutputError> {
        let text = field(key).ok_or_else(|| fail(format!("no `{key}`")))?;
        text.parse()
            .map_err(|_| fail(format!("`{key}` is {text:?}, not a whole number")))
    };
    let options = ImageMetadata::parse_options(&field(keys::OPTIONS).unwrap_or_default())
        .map_err(|e| fail(format!("`{}`: {e}", keys::OPTIONS)))?;
    let scene_name = field(keys::SCENE_NAME).unwrap_or_else(|| path.display().to_string());
    Ok(RenderRequest {
        overrides: Overrides {
            width: Some(number("width")?),
            height: Some(number("height")?),
            ..options
        },
        frames: FrameRange::one(number(keys::FRAME)?),
        ..RenderRequest::new(scene_text, scene_name)
    })
}

/// The PNG keyword of an EXR attribute name.
fn png_keyword(key: &str) -> String {
    key.replace('/', ":")
}

/// A PNG's text chunks as (EXR attribute name, text), with its size.
fn read_png_fields(path: &Path) -> Result<Vec<(String, String)>, String> {
    let file = std::fs::File::open(path).map_err(|e| e.to_string())?;
    let mut decoder = png::Decoder::new(std::io::BufReader::new(file));
    decoder.set_limits(png::Limits {
        bytes: 16 * hypertexture::scene::MAX_SCENE_BYTES,
    });
    let reader = decoder
        .read_info()
        .map_err(|e| format!("cannot read the PNG: {e}"))?;
    let info = reader.info();
    let mut fields = vec![
        ("width".to_string(), info.width.to_string()),
        ("height".to_string(), info.height.to_string()),
    ];
    for key in [
        keys::SCENE_NAME,
        keys::SCENE,
        keys::SCENE_HASH,
        keys::FRAME,
        keys::SPP,
        keys::OPTIONS,
    ] {
        let keyword = png_keyword(key);
        let itxt = info.utf8_text.iter().find(|c| c.keyword == keyword);
        let text = match itxt {
            Some(chunk) => Some(chunk.get_text().map_err(|e| format!("{keyword}: {e}"))?),
            None => info
                .uncompressed_latin1_text
                .iter()
                .find(|c| c.keyword == keyword)
                .map(|c| c.text.clone()),
        };
        if let Some(text) = text {
            fields.push((key.to_string(), text));
        }
    }
    Ok(fields)
}

/// An EXR's header attributes as (name, text), with its size.
fn read_exr_fields(path: &Path) -> Result<Vec<(String, String)>, String> {
    use exr::meta::attribute::AttributeValue;
    let meta = exr::meta::MetaData::read_from_file(path, false)
        .map_err(|e| format!("cannot read the EXR header: {e}"))?;
    let header = meta.headers.first().ok_or("the EXR has no header")?;
    let size = header.layer_size;
    let mut fields = vec![
        ("width".to_string(), size.width().to_string()),
        ("height".to_string(), size.height().to_string()),
    ];
    for (name, value) in &header.own_attributes.other {
        let text = match value {
            AttributeValue::Text(t) => String::from_utf8(t.bytes().to_vec())
                .map_err(|_| format!("{name}: not UTF-8 text"))?,
            AttributeValue::I32(i) => i.to_string(),
            _ => continue,
        };
        fields.push((name.to_string(), text));
    }
    Ok(fields)
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
pub fn encode_png(film: &Film, meta: &ImageMetadata) -> Result<Vec<u8>, OutputError> {
    encode_srgb8_png(&film.to_srgb8(), film.width(), film.height(), meta)
}

/// Encodes straight-alpha 8-bit sRGB RGBA bytes ([`Film::to_srgb8`]) as a PNG:
/// IHDR, sRGB (perceptual), a `Software` tEXt, the render's metadata as iTXt
/// (the scene text in `hypertexture:scene`), then the pixels.
pub fn encode_srgb8_png(
    bytes: &[u8],
    width: u32,
    height: u32,
    meta: &ImageMetadata,
) -> Result<Vec<u8>, OutputError> {
    let fail = |e: png::EncodingError| OutputError::Encode {
        path: PathBuf::from("<memory>"),
        message: e.to_string(),
    };
    let mut out = Vec::new();
    let mut encoder = png::Encoder::new(&mut out, width, height);
    encoder.set_color(png::ColorType::Rgba);
    encoder.set_depth(png::BitDepth::Eight);
    encoder.set_compression(png::Compression::Fast);
    encoder.set_filter(png::Filter::Adaptive);
    encoder.set_source_srgb(png::SrgbRenderingIntent::Perceptual);
    encoder
        .add_text_chunk("Software".into(), meta.software.clone())
        .map_err(fail)?;
    for (key, text) in meta.scene_fields() {
        encoder
            .add_itxt_chunk(png_keyword(key), text)
            .map_err(fail)?;
    }
    let mut writer = encoder.write_header().map_err(fail)?;
    writer.write_image_data(bytes).map_err(fail)?;
    writer.finish().map_err(fail)?;
    Ok(out)
}

/// The names of the EXR channels, in the order of [`hypertexture::Sample::to_array`].
pub const EXR_CHANNELS: [&str; 9] = [
    "R", "G", "B", "A", "density", "depth", "normal.X", "normal.Y", "normal.Z",
];

/// Encodes the film as a scanline OpenEXR of 32-bit float channels
/// (ZIP-compressed, lossless).
pub fn encode_exr(film: &Film, meta: &ImageMetadata) -> Result<Vec<u8>, OutputError> {
    use exr::meta::attribute::AttributeValue;
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
    let mut attributes = LayerAttributes::named("hypertexture");
    attributes.software_name = Some(Text::from(meta.software.as_str()));
    attributes.world_to_camera = meta.world_to_camera;
    attributes.world_to_normalized_device = meta.world_to_ndc;
    for (key, value) in meta.scene_fields() {
        // Numbers as `int` (a frame beyond i32 as text).
        let value = match (key, value.parse::<i32>()) {
            (keys::FRAME | keys::SPP, Ok(n)) => AttributeValue::I32(n),
            _ => AttributeValue::Text(Text::from_slice_unchecked(value.as_bytes())),
        };
        attributes.other.insert(Text::from(key), value);
    }
    let layer = Layer::new(
        size,
        attributes,
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
    let mut bytes = cursor.into_inner();
    sort_exr_attributes(&mut bytes)?;
    Ok(bytes)
}

/// Puts a single-part EXR's header attributes in name order, as OpenEXR's own
/// library writes them. `exr` writes its extra attributes in the order of a
/// `HashMap`, which differs from process to process; sorted, the same image
/// has the same bytes wherever it is written. The header keeps its length, so
/// the chunk offsets after it stay right.
fn sort_exr_attributes(bytes: &mut [u8]) -> Result<(), OutputError> {
    let bad = || OutputError::Encode {
        path: PathBuf::from("<memory>"),
        message: "the EXR header written does not parse".into(),
    };
    let zero_after = |at: usize| {
        bytes[at..]
            .iter()
            .position(|&b| b == 0)
            .map(|p| at + p)
            .ok_or_else(bad)
    };
    // Magic number and version, then (name\0 type\0 size value)* \0.
    let start = 8;
    let mut at = start;
    let mut attributes: Vec<(Vec<u8>, std::ops::Range<usize>)> = Vec::new();
    while *bytes.get(at).ok_or_else(bad)? != 0 {
        let name_end = zero_after(at)?;
        let type_end = zero_after(name_end + 1)?;
        let size_at = type_end + 1;
        let size: [u8; 4] = bytes
            .get(size_at..size_at + 4)
            .and_then(|s| s.try_into().ok())
            .ok_or_else(bad)?;
        let size = usize::try_from(i32::from_le_bytes(size)).map_err(|_| bad())?;
        let end = size_at + 4 + size;
        if end > bytes.len() {
            return Err(bad());
        }
        attributes.push((bytes[at..name_end].to_vec(), at..end));
        at = end;
    }
    attributes.sort_by(|a, b| a.0.cmp(&b.0));
    let sorted: Vec<u8> = attributes
        .iter()
        .flat_map(|(_, range)| bytes[range.clone()].to_vec())
        .collect();
    bytes[start..at].copy_from_slice(&sorted);
    Ok(())
}

/// Encodes the film in the format `path` names.
pub fn encode(
    film: &Film,
    format: ImageFormat,
    meta: &ImageMetadata,
) -> Result<Vec<u8>, OutputError> {
    match format {
        ImageFormat::Png => encode_png(film, meta),
        ImageFormat::Exr => encode_exr(film, meta),
    }
}

/// Writes the film to `path` in the format its extension names, atomically.
pub fn write_image(film: &Film, path: &Path, meta: &ImageMetadata) -> Result<(), OutputError> {
    let bytes = encode(film, ImageFormat::from_path(path)?, meta).map_err(|e| e.at(path))?;
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
pub fn write_frame_image(
    image: &FrameImage,
    path: &Path,
    meta: &ImageMetadata,
) -> Result<(), OutputError> {
    let (width, height, bytes) = match image {
        FrameImage::Film(film) => return write_image(film, path, meta),
        FrameImage::Srgb8 {
            width,
            height,
            bytes,
        } => (*width, *height, bytes),
    };
    let encoded = match ImageFormat::from_path(path)? {
        ImageFormat::Png => encode_srgb8_png(bytes, width, height, meta).map_err(|e| e.at(path))?,
        ImageFormat::Exr => {
            return Err(OutputError::Encode {
                path: path.to_path_buf(),
                message: "an EXR keeps every channel, and this image has only 8-bit colour".into(),
            });
        }
    };
    write_atomically(path, &encoded)
}

/// Writes `bytes` to a temporary file beside `path`, then renames it over
/// `path`. The temporary file is created new (`O_EXCL`) without following a
/// symlink (`O_NOFOLLOW`); a `path` that exists and is not a regular file (a
/// symlink, a directory, a device) is refused.
pub fn write_atomically(path: &Path, bytes: &[u8]) -> Result<(), OutputError> {
    use std::os::unix::fs::OpenOptionsExt as _;
    let io = |source| OutputError::Io {
        path: path.to_path_buf(),
        source,
    };
    if let Ok(existing) = std::fs::symlink_metadata(path)
        && !existing.file_type().is_file()
    {
        return Err(io(std::io::Error::new(
            std::io::ErrorKind::AlreadyExists,
            "it exists and is not a regular file; refused",
        )));
    }
    let dir = match path.parent() {
        Some(d) if !d.as_os_str().is_empty() => d.to_path_buf(),
        _ => PathBuf::from("."),
    };
    let name = path
        .file_name()
        .map_or_else(|| "image".into(), |n| n.to_string_lossy().into_owned());
    let temp = dir.join(format!(".{name}.{}.tmp", std::process::id()));
    let create = || {
        std::fs::OpenOptions::new()
            .write(true)
            .create_new(true)
            .custom_flags(libc::O_NOFOLLOW)
            .open(&temp)
    };
    let file = match create() {
        // Left by a process of the same id that died writing: removed (a
        // symlink is removed itself, never followed), then created anew.
        Err(e) if e.kind() == std::io::ErrorKind::AlreadyExists => {
            std::fs::remove_file(&temp).and_then(|()| create())
        }
        other => other,
    };
    let mut created = false;
    let result = file
        .and_then(|mut f| {
            created = true;
            f.write_all(bytes).and_then(|_| f.sync_all())
        })
        .and_then(|_| std::fs::rename(&temp, path));
    if result.is_err() && created {
        let _ = std::fs::remove_file(&temp);
    }
    result.map_err(io)
}

#[cfg(test)]
mod tests {
    use super::*;
    use hypertexture::Quality;
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

    fn meta() -> ImageMetadata {
        ImageMetadata {
            software: software(),
            request: RenderRequest {
                overrides: Overrides {
                    width: Some(5),
                    height: Some(3),
                    spp: Some(4),
                    quality: Some(Quality::Interactive),
                    knobs: vec![("curliness".into(), 0.1 + 0.2), ("b=c".into(), -1.0)],
                },
                frames: FrameRange::one(7),
                ..RenderRequest::new(
                    "Scene(image: (width: 5, height: 3)) // ✓",
                    "scenes/ünïcode.ron",
                )
            },
            spp: 4,
            world_to_camera: Some(std::array::from_fn(|i| i as f32)),
            world_to_ndc: Some(std::array::from_fn(|i| -(i as f32) / 3.0)),
            assets: Vec::new(),
        }
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
        let png = encode_png(&f, &meta()).unwrap();
        let img = image::load_from_memory(&png).unwrap().to_rgba8();
        assert_eq!(img.dimensions(), (1, 1));
        assert_eq!(img.get_pixel(0, 0).0, [188, 0, 0, 128]);
        assert_eq!(png, encode_png(&f, &meta()).unwrap(), "deterministic");
    }

    #[test]
    fn exr_has_the_nine_channels_and_values() {
        use exr::prelude::*;
        let film = film();
        let bytes = encode_exr(&film, &meta()).unwrap();
        assert_eq!(bytes, encode_exr(&film, &meta()).unwrap(), "deterministic");
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
        write_image(&film(), &path, &meta()).unwrap();
        let entries: Vec<_> = std::fs::read_dir(&dir)
            .unwrap()
            .map(|e| e.unwrap().file_name())
            .collect();
        assert_eq!(entries, vec![std::ffi::OsString::from("x.png")]);
        let err = write_image(&film(), &dir.join("missing/x.png"), &meta()).unwrap_err();
        assert!(err.to_string().contains("missing/x.png"));
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn a_target_that_is_not_a_regular_file_and_a_planted_temp_symlink_are_never_followed() {
        let dir = std::env::temp_dir().join(format!("ht-output-nofollow-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(dir.join("a-dir.png")).unwrap();
        let victim = dir.join("victim");
        std::fs::write(&victim, b"keep").unwrap();
        std::os::unix::fs::symlink(&victim, dir.join("link.png")).unwrap();
        for target in ["link.png", "a-dir.png"] {
            let e = write_atomically(&dir.join(target), b"image").unwrap_err();
            assert!(e.to_string().contains("not a regular file"), "{e}");
        }
        // A symlink planted at the temporary file's name is replaced, not followed.
        let temp = dir.join(format!(".x.png.{}.tmp", std::process::id()));
        std::os::unix::fs::symlink(&victim, &temp).unwrap();
        write_atomically(&dir.join("x.png"), b"image").unwrap();
        assert_eq!(std::fs::read(&victim).unwrap(), b"keep");
        assert_eq!(std::fs::read(dir.join("x.png")).unwrap(), b"image");
        assert!(!temp.exists());
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
        write_image(&film, &dir.join("film.png"), &meta()).unwrap();
        write_frame_image(&image, &dir.join("bytes.png"), &meta()).unwrap();
        assert_eq!(
            std::fs::read(dir.join("film.png")).unwrap(),
            std::fs::read(dir.join("bytes.png")).unwrap()
        );
        let err = write_frame_image(&image, &dir.join("x.exr"), &meta()).unwrap_err();
        assert!(err.to_string().contains("x.exr") && err.to_string().contains("8-bit"));
        assert!(!dir.join("x.exr").exists());
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn options_round_trip_exactly() {
        let m = meta();
        assert_eq!(
            m.options(),
            "--spp 4 --quality interactive --set curliness=0.30000000000000004 --set b=c=-1.0"
        );
        let parsed = ImageMetadata::parse_options(&m.options()).unwrap();
        let given = &m.request.overrides;
        assert_eq!(parsed.spp, given.spp);
        assert_eq!(parsed.quality, given.quality);
        assert_eq!(parsed.knobs, given.knobs);
        assert_eq!(
            ImageMetadata::parse_options("").unwrap(),
            Overrides::default()
        );
        assert!(ImageMetadata::parse_options("--spp").is_err());
        assert!(ImageMetadata::parse_options("--frobnicate 1").is_err());
        assert!(ImageMetadata::parse_options("--set k=inf").is_err());
        assert!(ImageMetadata::parse_options("--quality best").is_err());
    }

    #[test]
    fn png_stores_srgb_software_and_the_scene() {
        let dir = std::env::temp_dir().join(format!("ht-output-png-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("x.png");
        write_image(&film(), &path, &meta()).unwrap();
        let decoder =
            png::Decoder::new(std::io::BufReader::new(std::fs::File::open(&path).unwrap()));
        let reader = decoder.read_info().unwrap();
        let info = reader.info();
        assert_eq!(info.srgb, Some(png::SrgbRenderingIntent::Perceptual));
        let software: Vec<_> = info
            .uncompressed_latin1_text
            .iter()
            .map(|c| (c.keyword.as_str(), c.text.as_str()))
            .collect();
        assert_eq!(software, [("Software", meta().software.as_str())]);
        let scene = info
            .utf8_text
            .iter()
            .find(|c| c.keyword == "hypertexture:scene")
            .unwrap();
        assert_eq!(scene.get_text().unwrap(), meta().request.scene_text);
        assert_eq!(read_stored_render(&path).unwrap(), meta().request);
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn exr_header_holds_the_standard_and_scene_attributes_in_name_order() {
        use exr::meta::attribute::AttributeValue;
        let dir = std::env::temp_dir().join(format!("ht-output-exr-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("x.exr");
        write_image(&film(), &path, &meta()).unwrap();
        let header = exr::meta::MetaData::read_from_file(&path, true)
            .unwrap()
            .headers
            .remove(0);
        let own = &header.own_attributes;
        assert_eq!(own.software_name.as_ref().unwrap().to_string(), software());
        assert_eq!(own.world_to_camera, meta().world_to_camera);
        assert_eq!(own.world_to_normalized_device, meta().world_to_ndc);
        let text = |key: &str| match own.other.get(&exr::prelude::Text::from(key)) {
            Some(AttributeValue::Text(t)) => String::from_utf8(t.bytes().to_vec()).unwrap(),
            other => panic!("{key}: {other:?}"),
        };
        assert_eq!(text(keys::SCENE), meta().request.scene_text);
        assert_eq!(
            text(keys::SCENE_HASH),
            format!("{:016x}", meta().scene_hash())
        );
        assert!(matches!(
            own.other.get(&exr::prelude::Text::from(keys::FRAME)),
            Some(AttributeValue::I32(7))
        ));
        // Name order, as OpenEXR writes it: the bytes do not depend on a hash map.
        let bytes = std::fs::read(&path).unwrap();
        let mut names = Vec::new();
        let mut at = 8;
        while bytes[at] != 0 {
            let name_end = at + bytes[at..].iter().position(|&b| b == 0).unwrap();
            let type_end =
                name_end + 1 + bytes[name_end + 1..].iter().position(|&b| b == 0).unwrap();
            let size = i32::from_le_bytes(bytes[type_end + 1..type_end + 5].try_into().unwrap());
            names.push(String::from_utf8(bytes[at..name_end].to_vec()).unwrap());
            at = type_end + 5 + size as usize;
        }
        let mut sorted = names.clone();
        sorted.sort();
        assert_eq!(names, sorted);
        assert!(names.contains(&"worldToNDC".to_string()), "{names:?}");
        let stored = read_stored_render(&path).unwrap();
        assert_eq!(stored, meta().request);
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn an_image_without_a_scene_says_so() {
        let dir = std::env::temp_dir().join(format!("ht-output-none-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        for name in ["x.png", "x.exr"] {
            let path = dir.join(name);
            let m = ImageMetadata::without_scene(5, 3, None, None);
            write_image(&film(), &path, &m).unwrap();
            let err = read_stored_render(&path).unwrap_err().to_string();
            assert!(
                err.starts_with(&format!("{}: the image holds no scene", path.display())),
                "{err}"
            );
        }
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
