//! Scenes: loading a RON file into a ready-to-render [`Scene`].
//!
//! Loading has two phases, as in pbrt-v4: the text is read into a plain
//! description ([`desc::SceneDesc`]), every value checked where it stands so that
//! errors carry file:line:column; then the description is built into runtime
//! objects with every constant precomputed. After that nothing can fail.
//!
//! The built objects that are the scene's own live here: the [`camera`]
//! (rays from the description's projection). Densities, curves and motion are
//! built by their own modules in [`crate::field`].

pub mod camera;
mod diagnostic;
pub mod ron_text;

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::sync::Arc;

use glam::Vec3;

use crate::desc::{self, BackgroundDesc, ColourIndexDesc, LightDesc, SceneDesc};
use crate::field::curve::Curve;
use crate::field::density::Density;
use crate::field::domain::{Aabb, Support};
use crate::field::motion::Motion;
use crate::field::noise::{Noise, clamped_octaves};
use crate::math::simd::Isa;
use crate::mesh::{Mesh, MeshError, MeshLimits};
use crate::pse::{ExpressionFailure, SceneExpressions};
use crate::scene::camera::Camera;

/// The largest scene file we read. The paper's whole database was under 5 KB.
pub const MAX_SCENE_BYTES: usize = 64 * 1024;

/// Why a scene could not be loaded.
#[derive(Debug, thiserror::Error)]
pub enum SceneError {
    /// The file could not be read.
    #[error("{path}: cannot read the scene: {source}")]
    Io {
        /// The scene file.
        path: String,
        /// What the OS said.
        source: std::io::Error,
    },
    /// The file is larger than [`MAX_SCENE_BYTES`].
    #[error("{path}: the scene is larger than {MAX_SCENE_BYTES} bytes, the most a scene may be")]
    TooLarge {
        /// The scene file.
        path: String,
        /// Its size, or the bytes read before giving up.
        size: usize,
    },
    /// Syntax error, unknown field, wrong type or out-of-range value.
    #[error("{path}:{line}:{column}: {message}")]
    Parse {
        /// The scene file.
        path: String,
        /// 1-based line.
        line: usize,
        /// 1-based column.
        column: usize,
        /// What was wrong and what was expected.
        message: String,
    },
    /// An override (from the command line) is out of range.
    #[error("{0}")]
    Override(String),
    /// A mesh the scene names is missing, unreadable, malformed, open or
    /// too large.
    #[error("{scene}: mesh {error}")]
    Mesh {
        /// The scene file.
        scene: String,
        /// The mesh file and what is wrong with it.
        error: MeshError,
    },
    /// An expression does not parse, names something unknown or mixes types.
    /// `line:column` is the spot in the scene file; `detail` gives the line and
    /// column inside the expression, the expression's line and a caret.
    #[error("{path}:{line}:{column}: {field}: {detail}")]
    Expression {
        /// The scene file.
        path: String,
        /// 1-based line in the file.
        line: usize,
        /// 1-based column in the file.
        column: usize,
        /// The scene field holding the expression (`density`, `colour`, …).
        field: String,
        /// `line:column: message`, the expression's line, a caret under the spot.
        detail: String,
    },
}

/// The files a scene names (meshes), loaded, by the path as the scene writes
/// it: what a scene needs beyond its text. Loaded from disk beside the scene
/// file ([`Assets::load`]) or from bytes sent over the farm ([`Assets::insert`]).
#[derive(Clone, Debug, Default)]
pub struct Assets {
    meshes: BTreeMap<String, Arc<Mesh>>,
}

impl Assets {
    /// No files: a scene that names one fails to build with it.
    pub fn none() -> Assets {
        Assets::default()
    }

    /// Gives the file the scene calls `path` (as written) its mesh.
    pub fn insert(&mut self, path: &str, mesh: Arc<Mesh>) {
        self.meshes.insert(path.to_string(), mesh);
    }

    /// The mesh the scene calls `path`.
    pub fn mesh(&self, path: &str) -> Option<&Arc<Mesh>> {
        self.meshes.get(path)
    }

    /// Every file, as (path as written, content hash), in path order: what the
    /// scene hash covers beyond the text.
    pub fn hashes(&self) -> Vec<(String, u64)> {
        self.meshes
            .iter()
            .map(|(p, m)| (p.clone(), m.hash()))
            .collect()
    }

    /// Reads and builds every mesh `desc` names, each path relative to the
    /// directory of the scene file `scene_path`.
    pub fn load(
        desc: &SceneDesc,
        scene_path: &str,
        limits: MeshLimits,
    ) -> Result<Assets, SceneError> {
        let mut assets = Assets::default();
        for path in desc.mesh_paths() {
            let file = asset_path(scene_path, &path);
            let name = file.display().to_string();
            let mesh_error = |message: String| SceneError::Mesh {
                scene: scene_path.to_string(),
                error: MeshError {
                    path: name.clone(),
                    message,
                },
            };
            let bytes = read_asset(&file).map_err(mesh_error)?;
            let mesh = Mesh::from_obj(&name, &bytes, limits).map_err(|error| SceneError::Mesh {
                scene: scene_path.to_string(),
                error,
            })?;
            warn_once(scene_path, &name, &mesh);
            assets.insert(&path, Arc::new(mesh));
        }
        Ok(assets)
    }
}

/// Logs what is wrong with a mesh that loads anyway (open, non-manifold,
/// inconsistently oriented: [`Mesh::warnings`]) as warnings naming the scene
/// and the file, once per file and content in this process (a scene loaded
/// again, as the studio does at each change, does not repeat them).
fn warn_once(scene_path: &str, name: &str, mesh: &Mesh) {
    static WARNED: std::sync::Mutex<std::collections::BTreeSet<(String, u64)>> =
        std::sync::Mutex::new(std::collections::BTreeSet::new());
    if mesh.warnings().is_empty() {
        return;
    }
    let mut warned = WARNED.lock().unwrap_or_else(|e| e.into_inner());
    if warned.insert((name.to_string(), mesh.hash())) {
        for w in mesh.warnings() {
            tracing::warn!("{scene_path}: mesh {name}: {w}");
        }
    }
}

/// Where the file a scene at `scene_path` calls `asset` is: relative to the
/// scene file's directory (an absolute path as it is).
pub fn asset_path(scene_path: &str, asset: &str) -> PathBuf {
    let base = Path::new(scene_path).parent().unwrap_or(Path::new(""));
    base.join(asset)
}

/// An asset file's bytes (at most [`crate::mesh::MAX_OBJ_BYTES`]); the error
/// says what the OS said.
pub fn read_asset(path: &Path) -> Result<Vec<u8>, String> {
    use std::io::Read as _;
    let mut bytes = Vec::new();
    std::fs::File::open(path)
        .and_then(|f| {
            f.take(crate::mesh::MAX_OBJ_BYTES + 1)
                .read_to_end(&mut bytes)
        })
        .map_err(|e| format!("cannot read the mesh: {e}"))?;
    if bytes.len() as u64 > crate::mesh::MAX_OBJ_BYTES {
        return Err(format!(
            "the file is larger than {} bytes, the most a mesh file may be",
            crate::mesh::MAX_OBJ_BYTES
        ));
    }
    Ok(bytes)
}

/// Settings that replace the scene file's own at load time (from the command line).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Overrides {
    /// Image width in pixels.
    pub width: Option<u32>,
    /// Image height in pixels.
    pub height: Option<u32>,
    /// Samples per pixel (`--spp`).
    pub spp: Option<u32>,
    /// The marching step preset (`--quality`).
    pub quality: Option<Quality>,
    /// Knob values (`--set name=value`), one per name in name order
    /// ([`Overrides::knob_list`]), applied in order.
    pub knobs: Vec<(String, f64)>,
}

impl Overrides {
    /// Knob values as a request holds them, whatever form they were given
    /// in (the HTTP API's and a stored job's JSON map, `--set` flags, the
    /// studio's sliders, an image's stored options): one per name, in name
    /// order, a later value for a name replacing an earlier one. Applying
    /// them gives the scene the given values would; equal values give equal
    /// requests, and so equal content hashes.
    pub fn knob_list(knobs: impl IntoIterator<Item = (String, f64)>) -> Vec<(String, f64)> {
        knobs
            .into_iter()
            .collect::<BTreeMap<String, f64>>()
            .into_iter()
            .collect()
    }

    /// One knob setting as `--set` and an image's stored options write it,
    /// `name=value` (the value after the last `=`, a finite number; spaces
    /// around either are dropped). The refusal names what is wrong.
    pub fn parse_knob(setting: &str) -> Result<(String, f64), String> {
        let (name, value) = setting
            .rsplit_once('=')
            .ok_or_else(|| format!("expected KNOB=VALUE, found {setting:?}"))?;
        let name = name.trim();
        let value: f64 = value
            .trim()
            .parse()
            .map_err(|_| format!("knob {name}: expected a number, found {value:?}"))?;
        if !value.is_finite() {
            return Err(format!(
                "knob {name}: expected a finite number, found {value}"
            ));
        }
        Ok((name.to_string(), value))
    }
}

/// Where [`SceneError`] meets the expressions: a compile error located in the
/// scene file.
impl ExpressionFailure {
    /// The error located in the scene file `text` named `path`: the file position of
    /// the spot when the expression appears verbatim in the file (no escapes), else
    /// of the field's name.
    pub fn locate(&self, text: &str, path: &str) -> SceneError {
        let offset = if self.source.is_empty() {
            None
        } else {
            text.find(&self.source)
                .map(|i| i + self.error.at.min(self.source.len()))
        }
        .or_else(|| text.find(&format!("{}:", self.field)))
        .unwrap_or(0);
        let before = &text[..floor_boundary(text, offset)];
        let line = before.matches('\n').count() + 1;
        let column = before.rsplit('\n').next().map_or(0, |l| l.chars().count()) + 1;
        SceneError::Expression {
            path: path.to_string(),
            line,
            column,
            field: self.field.clone(),
            detail: self.error.render(&self.source),
        }
    }
}

fn floor_boundary(s: &str, mut i: usize) -> usize {
    i = i.min(s.len());
    while !s.is_char_boundary(i) {
        i -= 1;
    }
    i
}

/// The knob values of `desc` after applying `overrides` (each checked: known name,
/// inside the declared range).
pub fn knob_values(
    desc: &SceneDesc,
    overrides: &[(String, f64)],
) -> Result<BTreeMap<String, f64>, SceneError> {
    let mut values: BTreeMap<String, f64> = desc
        .knobs
        .iter()
        .map(|(k, v)| (k.clone(), v.default))
        .collect();
    for (name, value) in overrides {
        let Some(knob) = desc.knobs.get(name) else {
            let known: Vec<&str> = desc.knobs.keys().map(String::as_str).collect();
            return Err(SceneError::Override(if known.is_empty() {
                format!("--set {name}: the scene has no knobs")
            } else {
                format!(
                    "--set {name}: unknown knob; the scene's knobs are {}",
                    known.join(", ")
                )
            }));
        };
        if !(value.is_finite() && knob.min <= *value && *value <= knob.max) {
            return Err(SceneError::Override(format!(
                "--set {name}={value}: outside the knob's range [{}, {}]",
                knob.min, knob.max
            )));
        }
        values.insert(name.clone(), *value);
    }
    Ok(values)
}

/// The two sampling presets of Gilet & Dischler's Figures 11–12: the
/// marching step a request asks for. Spelt `interactive` and `high` by the
/// command line (`--quality`), the HTTP API and the studio (JSON), and an
/// image's stored options ([`Quality::NAMES`]; [`std::str::FromStr`] and
/// [`std::fmt::Display`] are the one parse and display).
#[derive(
    Clone, Copy, Debug, Default, PartialEq, Eq, Hash, serde::Serialize, serde::Deserialize,
)]
#[serde(rename_all = "lowercase")]
pub enum Quality {
    /// Interactive exploration: the scene's `interactive_step` (4 × `step` by default).
    Interactive,
    /// High quality: the scene's `step`.
    #[default]
    High,
}

impl Quality {
    /// Every preset, in the order of [`Quality::NAMES`].
    pub const ALL: [Quality; 2] = [Quality::Interactive, Quality::High];
    /// The presets' names.
    pub const NAMES: [&'static str; 2] = ["interactive", "high"];

    /// The preset's name.
    pub const fn name(self) -> &'static str {
        match self {
            Quality::Interactive => Quality::NAMES[0],
            Quality::High => Quality::NAMES[1],
        }
    }

    /// The step the preset marches with, in words (the command line's help).
    pub const fn step(self) -> &'static str {
        match self {
            Quality::Interactive => "The scene's interactive step",
            Quality::High => "The scene's step",
        }
    }
}

impl std::fmt::Display for Quality {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

impl std::str::FromStr for Quality {
    type Err = String;

    /// `interactive` or `high`; anything else is refused naming both.
    fn from_str(s: &str) -> Result<Quality, String> {
        Quality::ALL
            .into_iter()
            .find(|q| q.name() == s)
            .ok_or_else(|| format!("{s:?}: expected `interactive` or `high`"))
    }
}

/// How the shading normal is estimated (see [`desc::GradientDesc`]).
pub use desc::GradientDesc as Gradient;

/// Parses scene text; `path` names it in error messages.
pub fn parse(text: &str, path: &str) -> Result<SceneDesc, SceneError> {
    let text = strip_bom(text);
    if text.len() > MAX_SCENE_BYTES {
        return Err(SceneError::TooLarge {
            path: path.to_string(),
            size: text.len(),
        });
    }
    if let Some((offset, message)) = diagnostic::check_brackets(text) {
        let (line, column) = diagnostic::line_column(text, offset);
        return Err(SceneError::Parse {
            path: path.to_string(),
            line,
            column,
            message,
        });
    }
    let options = ron::Options::default()
        .with_default_extension(ron::extensions::Extensions::IMPLICIT_SOME)
        .with_default_extension(ron::extensions::Extensions::UNWRAP_VARIANT_NEWTYPES);
    options
        .from_str::<SceneDesc>(text)
        .map_err(|e| parse_error(&e, text, path))
}

/// `ron`'s error in the scene's words ([`diagnostic::message`]).
fn parse_error(e: &ron::error::SpannedError, text: &str, path: &str) -> SceneError {
    let offset = diagnostic::offset_of(text, e.span.start.line, e.span.start.col);
    let (offset, message) = diagnostic::message(&e.code, text, offset);
    let (line, column) = diagnostic::line_column(text, offset);
    SceneError::Parse {
        path: path.to_string(),
        line,
        column,
        message,
    }
}

/// Parses a colour map file (the format of a scene's `colour_map`: `(interpolation:
/// Spline, points: [(0.0, (r, g, b)), …])`); `path` names it in error messages.
pub fn parse_colour_map(text: &str, path: &str) -> Result<Curve<3>, SceneError> {
    let text = strip_bom(text);
    if text.len() > MAX_SCENE_BYTES {
        return Err(SceneError::TooLarge {
            path: path.to_string(),
            size: text.len(),
        });
    }
    ron::Options::default()
        .from_str::<desc::CurveDesc<desc::Rgb>>(text)
        .map(|d| Curve::colours(&d))
        .map_err(|e| parse_error(&e, text, path))
}

/// `text` without a UTF-8 byte order mark at its start (editors on Windows
/// write one).
pub fn strip_bom(text: &str) -> &str {
    text.strip_prefix('\u{feff}').unwrap_or(text)
}

/// Reads a scene file's text (at most [`MAX_SCENE_BYTES`], valid UTF-8, a
/// byte order mark dropped). Never reads more than one byte beyond the cap,
/// so that a device that never ends (`/dev/zero`) fails at once.
pub fn read_text(path: &Path) -> Result<String, SceneError> {
    use std::io::Read as _;
    let name = path.display().to_string();
    let io = |source| SceneError::Io {
        path: name.clone(),
        source,
    };
    let mut bytes = Vec::new();
    std::fs::File::open(path)
        .map_err(io)?
        .take(MAX_SCENE_BYTES as u64 + 1)
        .read_to_end(&mut bytes)
        .map_err(io)?;
    if bytes.len() > MAX_SCENE_BYTES {
        return Err(SceneError::TooLarge {
            path: name,
            size: bytes.len(),
        });
    }
    if let Some(rest) = bytes.strip_prefix(b"\xef\xbb\xbf") {
        bytes = rest.to_vec();
    }
    let text = std::str::from_utf8(&bytes).map_err(|e| {
        let before = &bytes[..e.valid_up_to()];
        let line = before.iter().filter(|&&b| b == b'\n').count() + 1;
        let column = before.iter().rev().take_while(|&&b| b != b'\n').count() + 1;
        SceneError::Parse {
            path: name.clone(),
            line,
            column,
            message: "the scene is not valid UTF-8 text".into(),
        }
    })?;
    Ok(text.to_string())
}

/// How a ray that leaves the volume is coloured.
#[derive(Clone, Copy, Debug, PartialEq)]
pub(crate) enum Background {
    Transparent,
    Colour(Vec3),
    Checker { colours: (Vec3, Vec3), squares: f32 },
}

impl Background {
    /// (colour, alpha) seen along a unit direction.
    #[inline]
    pub(crate) fn sample(&self, d: Vec3) -> (Vec3, f32) {
        match *self {
            Background::Transparent => (Vec3::ZERO, 0.0),
            Background::Colour(c) => (c, 1.0),
            Background::Checker { colours, squares } => {
                let u = libm::atan2f(d.z, d.x) / std::f32::consts::TAU + 0.5;
                let v = libm::asinf(d.y.clamp(-1.0, 1.0)) / std::f32::consts::PI + 0.5;
                let cell = (u * squares).floor() as i64 + (v * squares / 2.0).floor() as i64;
                (if cell & 1 == 0 { colours.0 } else { colours.1 }, 1.0)
            }
        }
    }
}

/// A light source.
#[derive(Clone, Copy, Debug, PartialEq)]
pub(crate) enum Light {
    Directional { direction: Vec3, colour: Vec3 },
    Point { position: Vec3, colour: Vec3 },
}

/// What indexes the colour map.
#[derive(Clone, Copy, Debug, PartialEq)]
pub(crate) enum ColourIndex {
    Density,
    Strata {
        frequency: f32,
        amplitude: f32,
        octaves: u32,
    },
}

impl Background {
    fn build(desc: &BackgroundDesc) -> Background {
        match *desc {
            BackgroundDesc::Transparent => Background::Transparent,
            BackgroundDesc::Colour(c) => Background::Colour(Vec3::from_array(c.0)),
            BackgroundDesc::Checker { colours, squares } => Background::Checker {
                colours: (Vec3::from_array(colours.0.0), Vec3::from_array(colours.1.0)),
                squares: squares.0 as f32,
            },
        }
    }
}

impl Light {
    fn build(desc: &LightDesc) -> Light {
        match *desc {
            LightDesc::Directional { direction, colour } => Light::Directional {
                direction: direction.0,
                colour: Vec3::from_array(colour.0),
            },
            LightDesc::Point { position, colour } => Light::Point {
                position: position.0,
                colour: Vec3::from_array(colour.0),
            },
        }
    }
}

impl ColourIndex {
    /// The colour index with the strata's octaves clamped for the step.
    fn build(desc: &ColourIndexDesc, step: f32) -> ColourIndex {
        match *desc {
            ColourIndexDesc::Density => ColourIndex::Density,
            ColourIndexDesc::Strata {
                frequency,
                amplitude,
                octaves,
            } => ColourIndex::Strata {
                frequency: frequency.0,
                amplitude: amplitude.0,
                octaves: clamped_octaves(frequency.0, step, octaves.0),
            },
        }
    }
}

/// Which of the marcher's shortcuts a scene allows (the fields of the same
/// names in [`Scene`] say what each skips).
struct Shortcuts {
    common_case: bool,
    position_free_shading: bool,
    light_waits: bool,
}

impl Shortcuts {
    fn of(
        desc: &SceneDesc,
        motion: &Option<Motion>,
        expressions: &SceneExpressions,
        colour_index: &ColourIndex,
        lights: &[Light],
    ) -> Shortcuts {
        let directional_only = || {
            lights
                .iter()
                .all(|l| matches!(l, Light::Directional { .. }))
        };
        Shortcuts {
            common_case: desc.refraction.is_none()
                && motion.is_none()
                && expressions.colour.is_none()
                && expressions.normal_perturbation.is_none()
                && !desc.shading.shadows
                && matches!(colour_index, ColourIndex::Density),
            position_free_shading: motion.is_none()
                && expressions.colour.is_none()
                && expressions.normal_perturbation.is_none()
                && !desc.shading.shadows
                && matches!(colour_index, ColourIndex::Density)
                && directional_only(),
            light_waits: desc.refraction.is_none()
                && expressions.normal_perturbation.is_none()
                && !desc.shading.shadows
                && !lights.is_empty()
                && directional_only(),
        }
    }
}

/// The marble strata's key (Perlin 1985) at the noise-space point q
/// (`x − offset`) whose turbulence is `turb`: `½ + ½ sin(f·q_y + a·turb)`.
#[inline]
fn strata(frequency: f32, amplitude: f32, q: Vec3, turb: f32) -> f32 {
    0.5 + 0.5 * libm::sinf(frequency * q.y + amplitude * turb)
}

/// A scene ready to render: immutable, shared by every thread.
#[derive(Clone, Debug)]
pub struct Scene {
    pub(crate) width: u32,
    pub(crate) height: u32,
    pub(crate) camera: Camera,
    pub(crate) bounds: (Vec3, Vec3),
    /// The marching step Δμ.
    pub(crate) step: f32,
    /// The samples a ray may take in all (its bends included), so that a
    /// ray bent back and forth inside the volume (total internal
    /// reflection) still terminates: 4 · diagonal / step + 64.
    pub(crate) budget: u64,
    /// `c · step`, the exponent of the opacity.
    pub(crate) opacity_exponent: f32,
    pub(crate) threshold: f32,
    pub(crate) density: Density,
    /// The objects' own density D, without the value DMFs (what an expression
    /// calls `D`, under the same motion): its gradient shades the samples
    /// where a ray reaches a hard region (f = 1, where ∇f = 0).
    pub(crate) object: Density,
    pub(crate) noise: Noise,
    pub(crate) colour_map: Curve<3>,
    pub(crate) colour_index: ColourIndex,
    pub(crate) alpha_map: Option<Curve<1>>,
    pub(crate) refraction: Option<Curve<1>>,
    pub(crate) background: Background,
    pub(crate) ambient: Vec3,
    pub(crate) lights: Vec<Light>,
    pub(crate) diffuse: f32,
    pub(crate) specular: f32,
    pub(crate) shininess: f32,
    pub(crate) flow: Vec3,
    /// Where the density can be non-zero (widened by two steps, so the sample
    /// after the last non-zero one is inside too), or `None`: anywhere.
    pub(crate) support: Option<Support>,
    /// The instruction-set path of the batch kernels (every path gives the same bits).
    pub(crate) isa: Isa,
    /// Forward or central differences.
    pub(crate) gradient: Gradient,
    /// Secondary rays towards the lights.
    pub(crate) shadows: bool,
    /// Samples per pixel.
    pub(crate) spp: u32,
    /// Fraction of a frame the shutter is open (motion blur).
    pub(crate) shutter: f32,
    /// The scene's seed, also seeding the pixel samples' jitter.
    pub(crate) seed: u64,
    /// Frames per second of the expressions' time t.
    pub(crate) frame_rate: f32,
    /// The colour of a sample and the normal perturbation (bumps, waves), when
    /// written as expressions.
    pub(crate) expressions: SceneExpressions,
    /// The object's rigid motion (`density` is then [`Density::Moving`]).
    pub(crate) motion: Option<Motion>,
    /// The files the scene names (path as written, content hash), in path order.
    pub(crate) assets: Vec<(String, u64)>,
    /// Whether the marcher's common case holds: no refraction, no motion,
    /// no colour or normal expressions, no shadows and the density as the
    /// colour key. It then runs a sample loop without
    /// the rest (`march::trace_with_phase`).
    pub(crate) common_case: bool,
    /// Whether a sample's colour is a function of its f, its shading normal
    /// and the ray's direction alone (no expressions, motion, strata,
    /// shadows or point lights), so that a run of samples sharing those
    /// shares it: see `march`.
    pub(crate) position_free_shading: bool,
    /// Whether a sample's light may wait and be found with other samples'
    /// (`march`'s `Deferred`): no refraction, no normal expression, no
    /// shadows, and directional lights only (at least one).
    pub(crate) light_waits: bool,
}

impl Scene {
    /// Reads, checks and builds the scene in `path`.
    pub fn load(path: impl AsRef<Path>, overrides: Overrides) -> Result<Scene, SceneError> {
        let path = path.as_ref();
        let text = read_text(path)?;
        Scene::from_text(&text, &path.display().to_string(), overrides)
    }

    /// Checks and builds a scene from its text; `path` names it in errors,
    /// and the meshes it names are read relative to `path`'s directory.
    pub fn from_text(text: &str, path: &str, overrides: Overrides) -> Result<Scene, SceneError> {
        Scene::from_text_with(text, path, overrides, None)
    }

    /// [`Scene::from_text`] with the files the scene names given (`Some`:
    /// nothing is read from disk; a file not among them is an error), or read
    /// beside the scene file (`None`).
    pub fn from_text_with(
        text: &str,
        path: &str,
        overrides: Overrides,
        assets: Option<&Assets>,
    ) -> Result<Scene, SceneError> {
        let mut desc = parse(text, path)?;
        let loaded;
        let assets = match assets {
            Some(a) => a,
            None => {
                loaded = Assets::load(&desc, path, MeshLimits::default())?;
                &loaded
            }
        };
        desc.attach_meshes(|p| assets.mesh(p).cloned())
            .map_err(|missing| SceneError::Mesh {
                scene: path.to_string(),
                error: MeshError {
                    path: missing,
                    message: "not among the files sent with the scene".into(),
                },
            })?;
        desc.attach_mesh_fields(&|d| {
            crate::field::distortion::Distortion::build(d).max_displacement()
        })
        .map_err(|(mesh, message)| SceneError::Mesh {
            scene: path.to_string(),
            error: MeshError {
                path: mesh,
                message,
            },
        })?;
        if let Some(w) = overrides.width {
            desc.image.width = w;
        }
        if let Some(h) = overrides.height {
            desc.image.height = h;
        }
        if let Some(spp) = overrides.spp {
            desc.sampling.spp = desc::Spp::try_from(u64::from(spp))
                .map_err(|e| SceneError::Override(format!("--spp: {e}")))?;
        }
        if overrides.quality == Some(Quality::Interactive) {
            let diagonal = (desc.march.bounds.max.0 - desc.march.bounds.min.0).length();
            desc.march.step = desc
                .march
                .interactive_step
                .unwrap_or(desc::StepDesc::Length(desc::Positive(
                    4.0 * desc.march.step.length(diagonal),
                )));
        }
        desc::check_resolution(desc.image.width, desc.image.height)
            .map_err(SceneError::Override)?;
        let knobs = knob_values(&desc, &overrides.knobs)?;
        let mut scene = Scene::build(&desc, &knobs).map_err(|f| f.locate(text, path))?;
        scene.assets = desc
            .mesh_paths()
            .into_iter()
            .filter_map(|p| assets.mesh(&p).map(|m| (p, m.hash())))
            .collect();
        Ok(scene)
    }

    /// The files the scene names, as (path as written, content hash of the
    /// bytes), in path order: what the farm's scene hash covers beyond the text.
    pub fn asset_hashes(&self) -> &[(String, u64)] {
        &self.assets
    }

    /// Builds the runtime scene from a checked description and its knob values,
    /// compiling the expressions.
    pub fn build(
        desc: &SceneDesc,
        knobs: &BTreeMap<String, f64>,
    ) -> Result<Scene, ExpressionFailure> {
        let (min, max) = (desc.march.bounds.min.0, desc.march.bounds.max.0);
        let step = desc.march.step.length((max - min).length());
        let object = desc.object_with_modulation();
        let background = Background::build(&desc.background);
        let lights: Vec<Light> = desc.lights.sources.iter().map(Light::build).collect();
        let colour_index = ColourIndex::build(&desc.colour_index, step);
        let colour_map = Curve::colours(&desc.colour_map);
        let (density, expressions) =
            SceneExpressions::build(desc, &object, step, knobs, &colour_map)?;
        let motion = desc.transform.as_ref().map(Motion::build);
        let (density, own) = Scene::densities(desc, &object, step, density, motion.is_some());
        // In object space for a moving object: each field maps it to the world.
        let support = Scene::widened_support(&density, step, (min, max));
        let shortcuts = Shortcuts::of(desc, &motion, &expressions, &colour_index, &lights);
        Ok(Scene {
            width: desc.image.width,
            height: desc.image.height,
            camera: Camera::new(&desc.camera, desc.image.width, desc.image.height),
            bounds: (min, max),
            step,
            budget: (4.0 * (max - min).length() / step) as u64 + 64,
            opacity_exponent: desc.march.opacity.0 * step,
            threshold: desc.march.threshold.0,
            density,
            object: own,
            noise: Noise::new(desc.seed),
            colour_map,
            colour_index,
            alpha_map: desc.alpha_map.as_ref().map(Curve::scalars),
            refraction: desc.refraction.as_ref().map(Curve::scalars),
            background,
            ambient: Vec3::from_array(desc.lights.ambient.0),
            lights,
            diffuse: desc.shading.diffuse.0,
            specular: desc.shading.specular.0,
            shininess: desc.shading.shininess.0,
            flow: desc.flow.0,
            support,
            isa: Isa::detect(),
            gradient: desc.shading.gradient,
            shadows: desc.shading.shadows,
            spp: desc.sampling.spp.0,
            shutter: desc.sampling.shutter.0,
            seed: desc.seed,
            frame_rate: desc.frame_rate.0,
            expressions,
            motion,
            assets: Vec::new(),
            common_case: shortcuts.common_case,
            position_free_shading: shortcuts.position_free_shading,
            light_waits: shortcuts.light_waits,
        })
    }

    /// The density the marcher samples (with the expressions' own, if any)
    /// and the object's own density (the description's object, without the
    /// scene's `density` expression), each wrapped in the motion when the
    /// object moves.
    fn densities(
        desc: &SceneDesc,
        object: &desc::ObjectDesc,
        step: f32,
        density: Density,
        moving: bool,
    ) -> (Density, Density) {
        let own = match desc.density {
            Some(_) => Density::build(object, step),
            None => density.clone(),
        };
        if moving {
            (
                Density::Moving(Box::new(density)),
                Density::Moving(Box::new(own)),
            )
        } else {
            (density, own)
        }
    }

    /// The instruction-set path the batch kernels run on ([`Isa::detect`] by default).
    pub fn isa(&self) -> Isa {
        self.isa
    }

    /// Turns empty-space skipping off (every sample is evaluated) or back on.
    /// The image is the same either way: only samples where the density is 0
    /// for certain are skipped.
    pub fn set_empty_space_skipping(&mut self, on: bool) {
        self.support = if on {
            Scene::widened_support(&self.density, self.step, self.bounds)
        } else {
            None
        };
    }

    /// The bounding parallelepiped the rays are marched through (min, max).
    pub fn bounds(&self) -> (Vec3, Vec3) {
        self.bounds
    }

    /// How the shading normal is estimated (the scene's `shading.gradient`).
    pub fn gradient(&self) -> Gradient {
        self.gradient
    }

    /// Replaces the scene's `shading.gradient`.
    pub fn set_gradient(&mut self, gradient: Gradient) {
        self.gradient = gradient;
    }

    fn widened_support(density: &Density, step: f32, (min, max): (Vec3, Vec3)) -> Option<Support> {
        let margin = Vec3::splat(2.0 * step) + (max - min).abs() * 1e-4;
        density.support().map(|(lo, hi)| Support {
            aabb: (lo - margin, hi + margin),
            ball: density
                .support_ball()
                .map(|(centre, r)| (centre, r + margin.max_element())),
        })
    }

    /// Runs the batch kernels on `isa` instead; false (and no change) when this
    /// CPU cannot. Images are the same bits on every path.
    pub fn set_isa(&mut self, isa: Isa) -> bool {
        if !isa.is_available() {
            return false;
        }
        self.isa = isa;
        true
    }

    /// The camera the rays come from.
    pub fn camera(&self) -> &Camera {
        &self.camera
    }

    /// Image width in pixels.
    pub fn width(&self) -> u32 {
        self.width
    }

    /// Image height in pixels.
    pub fn height(&self) -> u32 {
        self.height
    }

    /// The marching step Δμ in scene units.
    pub fn step(&self) -> f32 {
        self.step
    }

    /// Samples per pixel.
    pub fn spp(&self) -> u32 {
        self.spp
    }

    /// How far any distortion can carry density beyond the undistorted objects.
    pub fn max_displacement(&self) -> f32 {
        self.density.max_displacement()
    }

    /// The hypertexture H(x) for `frame`, in [0, 1].
    pub fn density_at(&self, x: Vec3, frame: u32) -> f32 {
        self.density.eval(x, &self.field(frame))
    }

    /// The box where H can be non-zero at `frame`, in world space: the
    /// density's support (widened by two steps) within the marching bounds,
    /// or the marching bounds when the support is unknown (a complement).
    pub fn density_box(&self, frame: u32) -> Aabb {
        let (min, max) = self.bounds;
        match self.field(frame).support {
            Some(s) => {
                let lo = s.aabb.0.max(min);
                (lo, s.aabb.1.min(max).max(lo))
            }
            None => (min, max),
        }
    }

    /// The base colour of a sample of density `f` at world point x of
    /// `frame`, before lighting: the `colour` expression, or the colour map at
    /// the colour index, as the marcher colours it.
    pub fn colour_at(&self, x: Vec3, f: f32, frame: u32) -> Vec3 {
        let field = self.field(frame);
        let object_x = field.object_point(x);
        let key = self.colour_key(object_x, f, &field);
        crate::pse::surface::surface_colour(
            &self.expressions,
            &self.colour_map,
            object_x,
            f,
            key,
            &field,
        )
    }

    /// What indexes the colour map for a sample of density `f` at the
    /// object-space point `object_x`: the density, or the marble strata.
    #[inline]
    pub(crate) fn colour_key(
        &self,
        object_x: Vec3,
        f: f32,
        field: &crate::field::domain::Field,
    ) -> f32 {
        match self.colour_index {
            ColourIndex::Density => f,
            ColourIndex::Strata {
                frequency,
                amplitude,
                octaves,
            } => {
                let q = object_x - field.offset;
                let turb = field.noise.turbulence_on(self.isa, q, octaves);
                strata(frequency, amplitude, q, turb)
            }
        }
    }

    /// [`Scene::colour_key`] of the first `len` of `object_x`, f being `f`:
    /// the same bits. The strata's octaves of all the points go to the
    /// noise kernel together, a register's worth of (point, octave) pairs a
    /// call, where one point's few octaves would leave lanes empty; each
    /// point's sum is then taken in `turbulence`'s order.
    pub(crate) fn colour_keys(
        &self,
        object_x: &crate::field::domain::Points,
        f: &crate::math::simd::Lanes,
        len: usize,
        field: &crate::field::domain::Field,
    ) -> crate::math::simd::Lanes {
        let ColourIndex::Strata {
            frequency,
            amplitude,
            octaves,
        } = self.colour_index
        else {
            return *f;
        };
        let octaves = octaves as usize;
        // Whole registers of pairs (the AVX2 kernel's 8), of as many
        // points as fit in `BATCH`.
        const BATCH: usize = 64;
        let per_call = (BATCH / octaves).max(1);
        let mut keys = [0.0; crate::math::simd::LANES];
        let mut start = 0;
        while start < len {
            let end = (start + per_call).min(len);
            let mut points = [Vec3::ZERO; BATCH];
            let mut i = 0;
            for l in start..end {
                let q = object_x.get(l) - field.offset;
                let mut scale = 1.0f32;
                for _ in 0..octaves {
                    points[i] = q * scale;
                    scale *= 2.0;
                    i += 1;
                }
            }
            let count = i.next_multiple_of(8);
            let mut values = [0.0f32; BATCH];
            field
                .noise
                .noise_batch(self.isa, &points[..count], &mut values[..count]);
            for (l, v) in (start..end).zip(values.chunks_exact(octaves)) {
                let (mut turb, mut scale) = (0.0f32, 1.0f32);
                for n in v {
                    turb += n.abs() / scale;
                    scale *= 2.0;
                }
                keys[l] = strata(frequency, amplitude, object_x.get(l) - field.offset, turb);
            }
            start = end;
        }
        keys
    }

    /// H(x) for `frame` and its gradient ∇H(x), by forward-mode
    /// differentiation ([`crate::math::dual`]), as `gradient: Dual` shades.
    pub fn density_gradient_at(&self, x: Vec3, frame: u32) -> (f32, Vec3) {
        self.density_gradient_with(x, frame, crate::math::dual::spacing(self.step))
    }

    /// [`Scene::density_gradient_at`] with the parts that have no derivative
    /// written out (the distortion, expressions) differentiated by central
    /// differences of spacing `h` rather than a step.
    pub fn density_gradient_with(&self, x: Vec3, frame: u32, h: f32) -> (f32, Vec3) {
        let g = self
            .density
            .eval_dual(&crate::math::dual::DualPoint::at(x), &self.field(frame), h);
        (g.v, g.d)
    }

    /// The evaluation context of `frame`.
    #[inline]
    pub(crate) fn field(&self, frame: u32) -> crate::field::domain::Field<'_> {
        self.field_at(frame as f32)
    }

    /// The evaluation context at `time` frames (a frame plus a shutter offset).
    #[inline]
    pub(crate) fn field_at(&self, time: f32) -> crate::field::domain::Field<'_> {
        let pose = self.motion.map(|m| m.at(time));
        crate::field::domain::Field {
            noise: &self.noise,
            offset: self.flow * time,
            frame: time as u32,
            time,
            frame_rate: self.frame_rate,
            pose,
            support: match pose {
                Some(pose) => self.support.map(|b| pose.world_support(b)),
                None => self.support,
            },
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn quality_names_parse_and_display_one_way() {
        for (q, name) in Quality::ALL.into_iter().zip(Quality::NAMES) {
            assert_eq!(q.to_string(), name);
            assert_eq!(name.parse::<Quality>(), Ok(q));
        }
        let e = "best".parse::<Quality>().unwrap_err();
        assert!(e.contains("\"best\"") && e.contains("interactive"), "{e}");
        assert!("High".parse::<Quality>().is_err(), "names are lower case");
    }

    #[test]
    fn knob_lists_hold_one_value_a_name_in_name_order() {
        let given = [("b", 1.0), ("a", 2.0), ("b", 3.0)].map(|(k, v)| (k.to_string(), v));
        assert_eq!(
            Overrides::knob_list(given),
            [("a".to_string(), 2.0), ("b".to_string(), 3.0)]
        );
        assert!(Overrides::knob_list(Vec::new()).is_empty());
    }

    #[test]
    fn a_knob_setting_is_its_name_and_a_finite_number() {
        assert_eq!(
            Overrides::parse_knob(" curliness = 0.8 "),
            Ok(("curliness".to_string(), 0.8))
        );
        assert_eq!(
            Overrides::parse_knob("b=c=-1.0"),
            Ok(("b=c".to_string(), -1.0))
        );
        for (bad, says) in [
            ("curliness", "KNOB=VALUE"),
            ("k=x", "knob k: expected a number"),
            ("k=inf", "knob k: expected a finite number"),
            ("k=NaN", "knob k: expected a finite number"),
        ] {
            let e = Overrides::parse_knob(bad).unwrap_err();
            assert!(e.contains(says), "{bad}: {e}");
        }
    }
}
