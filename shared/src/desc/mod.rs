//! The scene as written in RON: plain data, validated while it is read.
//!
//! This is phase one of loading (as in pbrt-v4: text → description → runtime
//! objects): the layer above [`crate::mesh`] and below [`crate::field`], whose
//! builders read it. [`values`] holds the checked numbers, vectors, colours
//! and curves; [`distortion`] the distortion model's part of a scene. Every range check happens inside deserialisation (`try_from`), so a
//! bad value is reported by `ron` with the line and column where it was read.
//! Checks that relate several fields run when their struct is complete and point
//! at its end.

use std::collections::BTreeMap;

use serde::Deserialize;

pub mod distortion;
pub mod values;

pub use distortion::{DistortionDesc, check_distortion};
pub use values::{
    CurveDesc, Direction, FieldOfView, Finite, Fraction, Interpolation, NonNegative, Octaves,
    Positive, Rgb, Squares, UnitOpen, V3,
};

/// The seed of the noise tables when a scene names none (the paper's year).
pub const DEFAULT_SEED: u64 = 1989;

/// The largest image we accept: 16384 pixels a side and 64 Mi pixels in all.
pub const MAX_SIDE: u32 = 16_384;
/// The largest pixel count we accept (a 2 GiB film at 32 bytes a pixel).
pub const MAX_PIXELS: u64 = 64 * 1024 * 1024;

/// A whole scene file.
#[derive(Clone, Debug, Deserialize, PartialEq)]
#[serde(deny_unknown_fields, try_from = "SceneFields")]
pub struct SceneDesc {
    /// Image size in pixels.
    pub image: ImageDesc,
    /// The viewpoint.
    pub camera: CameraDesc,
    /// What a ray that leaves the volume sees.
    #[serde(default)]
    pub background: BackgroundDesc,
    /// Light sources and ambient light.
    #[serde(default)]
    pub lights: LightsDesc,
    /// Ray marching settings (section 3.1).
    pub march: MarchDesc,
    /// The object density function D(x): a tree of soft objects.
    pub object: ObjectDesc,
    /// Density modulation functions applied to the whole object, in order.
    #[serde(default)]
    pub modulation: Vec<DmfDesc>,
    /// Whether the value DMFs shape the object's hard region (D = 1) too.
    #[serde(default)]
    pub hard_core: HardCore,
    /// Colour over density (or over `colour_index`).
    #[serde(default = "CurveDesc::white")]
    pub colour_map: CurveDesc<Rgb>,
    /// What indexes the colour map.
    #[serde(default)]
    pub colour_index: ColourIndexDesc,
    /// Opacity density over density (default: the identity).
    #[serde(default)]
    pub alpha_map: Option<CurveDesc<Finite>>,
    /// Refractive index over density; none means rays go straight.
    #[serde(default)]
    pub refraction: Option<CurveDesc<Positive>>,
    /// Surface response of the shaded samples.
    #[serde(default)]
    pub shading: ShadingDesc,
    /// Seed of the noise tables.
    #[serde(default = "default_seed")]
    pub seed: u64,
    /// Drift of the noise domain per frame: noise is evaluated at `x - frame · flow`,
    /// so an animation's texture streams through the object (rising flames).
    /// It moves the built-in DMFs' noise (also when an expression calls them as
    /// `D(x)`); an expression moves its own noise calls with `frame` or `t`, e.g.
    /// `noise(x - frame * [0, 0.1, 0])`, so that what it says is what it does.
    #[serde(default)]
    pub flow: V3,
    /// Gilet & Dischler's distortion of the whole object (after `modulation`'s
    /// position DMFs).
    #[serde(default)]
    pub distortion: Option<DistortionDesc>,
    /// Samples per pixel and the shutter of motion blur.
    #[serde(default)]
    pub sampling: SamplingDesc,
    /// Named parameters of the expressions, with defaults and ranges; `--set`
    /// overrides them.
    #[serde(default)]
    pub knobs: BTreeMap<String, KnobDesc>,
    /// Scene functions: `fn name(a, b) { ... }` definitions the expressions call.
    #[serde(default)]
    pub functions: Option<String>,
    /// Named soft objects the expressions call by name: `core(x)`.
    #[serde(default)]
    pub objects: BTreeMap<String, ObjectDesc>,
    /// The hypertexture as an expression of x (replaces `object` + `modulation`,
    /// which it calls as `D(x)`).
    #[serde(default)]
    pub density: Option<String>,
    /// Colour of a sample as an expression of x and its density d (replaces
    /// `colour_map` lookup; `colour_map(s)` is still callable).
    #[serde(default)]
    pub colour: Option<String>,
    /// A vector added to the shading normal, an expression of x and d (bumps, waves).
    #[serde(default)]
    pub normal_perturbation: Option<String>,
    /// Frames per second of the time `t = frame / frame_rate`.
    #[serde(default = "Positive::frame_rate")]
    pub frame_rate: Positive,
    /// Where the object is at each moment (a rigid motion). The hypertexture,
    /// its colour and its solid textures are evaluated at the object-space point,
    /// so a texture sticks to its moving object (the notes' crawling textures).
    #[serde(default)]
    pub transform: Option<TransformDesc>,
}

impl SceneDesc {
    /// The scene's object with its modulation: what expressions call `D`.
    pub fn object_with_modulation(&self) -> ObjectDesc {
        if self.modulation.is_empty() && self.distortion.is_none() {
            self.object.clone()
        } else {
            ObjectDesc::Hypertexture(HypertextureDesc {
                object: Box::new(self.object.clone()),
                modulation: self.modulation.clone(),
                hard_core: self.hard_core,
                distortion: self.distortion.clone(),
            })
        }
    }
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields, rename = "Scene")]
struct SceneFields {
    /// Image size in pixels.
    image: ImageDesc,
    /// The viewpoint.
    camera: CameraDesc,
    /// What a ray that leaves the volume sees.
    #[serde(default)]
    background: BackgroundDesc,
    /// Light sources and ambient light.
    #[serde(default)]
    lights: LightsDesc,
    /// Ray marching settings (section 3.1).
    march: MarchDesc,
    /// The object density function D(x): a tree of soft objects.
    object: ObjectDesc,
    /// Density modulation functions applied to the whole object, in order.
    #[serde(default)]
    modulation: Vec<DmfDesc>,
    /// Whether the value DMFs shape the object's hard region (D = 1) too.
    #[serde(default)]
    hard_core: HardCore,
    /// Colour over density (or over `colour_index`).
    #[serde(default = "CurveDesc::white")]
    colour_map: CurveDesc<Rgb>,
    /// What indexes the colour map.
    #[serde(default)]
    colour_index: ColourIndexDesc,
    /// Opacity density over density (default: the identity).
    #[serde(default)]
    alpha_map: Option<CurveDesc<Finite>>,
    /// Refractive index over density; none means rays go straight.
    #[serde(default)]
    refraction: Option<CurveDesc<Positive>>,
    /// Surface response of the shaded samples.
    #[serde(default)]
    shading: ShadingDesc,
    /// Seed of the noise tables.
    #[serde(default = "default_seed")]
    seed: u64,
    /// Drift of the noise domain per frame: noise is evaluated at `x - frame · flow`,
    /// so an animation's texture streams through the object (rising flames).
    #[serde(default)]
    flow: V3,
    /// Gilet & Dischler's distortion of the whole object.
    #[serde(default)]
    distortion: Option<DistortionDesc>,
    /// Samples per pixel and the shutter of motion blur.
    #[serde(default)]
    sampling: SamplingDesc,
    #[serde(default)]
    knobs: BTreeMap<String, KnobDesc>,
    #[serde(default)]
    functions: Option<String>,
    #[serde(default)]
    objects: BTreeMap<String, ObjectDesc>,
    #[serde(default)]
    density: Option<String>,
    #[serde(default)]
    colour: Option<String>,
    #[serde(default)]
    normal_perturbation: Option<String>,
    #[serde(default = "Positive::frame_rate")]
    frame_rate: Positive,
    #[serde(default)]
    transform: Option<TransformDesc>,
}

impl TryFrom<SceneFields> for SceneDesc {
    type Error = String;
    fn try_from(f: SceneFields) -> Result<Self, String> {
        check_chain(&f.object, &f.modulation)?;
        if let Some(d) = &f.distortion {
            check_distortion(d, f.object.is_primitive())?;
        }
        if f.objects.len() > MAX_NAMED_OBJECTS {
            return Err(format!(
                "objects: at most {MAX_NAMED_OBJECTS} named objects, found {}",
                f.objects.len()
            ));
        }
        for name in f.objects.keys() {
            check_name("objects", name)?;
            if f.knobs.contains_key(name) {
                return Err(format!("`{name}` is both a knob and an object"));
            }
        }
        if f.knobs.len() > MAX_KNOBS {
            return Err(format!(
                "knobs: at most {MAX_KNOBS} knobs, found {}",
                f.knobs.len()
            ));
        }
        for name in f.knobs.keys() {
            check_name("knobs", name)?;
        }
        Ok(SceneDesc {
            image: f.image,
            camera: f.camera,
            background: f.background,
            lights: f.lights,
            march: f.march,
            object: f.object,
            modulation: f.modulation,
            hard_core: f.hard_core,
            colour_map: f.colour_map,
            colour_index: f.colour_index,
            alpha_map: f.alpha_map,
            refraction: f.refraction,
            shading: f.shading,
            seed: f.seed,
            flow: f.flow,
            distortion: f.distortion,
            sampling: f.sampling,
            knobs: f.knobs,
            functions: f.functions,
            objects: f.objects,
            density: f.density,
            colour: f.colour,
            normal_perturbation: f.normal_perturbation,
            frame_rate: f.frame_rate,
            transform: f.transform,
        })
    }
}

/// The rigid motion of the object: at time τ (in frames) its object-space point o
/// is at the world point `pivot + R(angle + spin·τ)(o − pivot) + translate +
/// velocity·τ`, R the rotation about `axis` through the pivot.
#[derive(Clone, Copy, Debug, Deserialize, PartialEq)]
#[serde(deny_unknown_fields, rename = "Transform")]
pub struct TransformDesc {
    /// Offset at frame 0.
    #[serde(default)]
    pub translate: V3,
    /// Offset added per frame.
    #[serde(default)]
    pub velocity: V3,
    /// Centre of the rotation, in object space.
    #[serde(default)]
    pub pivot: V3,
    /// Axis of the rotation.
    #[serde(default = "Direction::y")]
    pub axis: Direction,
    /// Rotation at frame 0, in degrees.
    #[serde(default)]
    pub angle: Finite,
    /// Rotation added per frame, in degrees.
    #[serde(default)]
    pub spin: Finite,
}

/// Most knobs a scene may declare.
pub const MAX_KNOBS: usize = 64;
/// Most named objects a scene may declare.
pub const MAX_NAMED_OBJECTS: usize = 64;

/// Names the expression language keeps for itself.
const RESERVED: [&str; 8] = ["x", "t", "frame", "d", "pi", "let", "if", "else"];

/// A knob or object name must be an identifier the expressions can spell.
fn check_name(what: &str, name: &str) -> Result<(), String> {
    let mut chars = name.chars();
    let ok = chars
        .next()
        .is_some_and(|c| c.is_ascii_alphabetic() || c == '_')
        && chars.all(|c| c.is_ascii_alphanumeric() || c == '_')
        && name.len() <= 64;
    if !ok {
        return Err(format!(
            "{what}: `{name}` is not a name (letters, digits and _, not starting with a digit)"
        ));
    }
    if RESERVED.contains(&name) || name == "fn" || name == "D" {
        return Err(format!(
            "{what}: `{name}` is reserved by the expression language"
        ));
    }
    Ok(())
}

/// A named parameter of the scene's expressions (Perlin's knobs: length,
/// fineness, curliness…), with its default and allowed range.
#[derive(Clone, Copy, Debug, Deserialize, PartialEq)]
#[serde(deny_unknown_fields, try_from = "KnobFields")]
pub struct KnobDesc {
    /// The value unless overridden.
    pub default: f64,
    /// Smallest allowed value.
    pub min: f64,
    /// Largest allowed value.
    pub max: f64,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields, rename = "Knob")]
struct KnobFields {
    default: f64,
    min: f64,
    max: f64,
}

impl TryFrom<KnobFields> for KnobDesc {
    type Error = String;
    fn try_from(f: KnobFields) -> Result<Self, String> {
        if !(f.default.is_finite() && f.min.is_finite() && f.max.is_finite()) {
            return Err("knob: default, min and max must be finite numbers".into());
        }
        if !(f.min <= f.default && f.default <= f.max) {
            return Err(format!(
                "knob: the default {} must lie in [min, max] = [{}, {}]",
                f.default, f.min, f.max
            ));
        }
        Ok(KnobDesc {
            default: f.default,
            min: f.min,
            max: f.max,
        })
    }
}

fn default_seed() -> u64 {
    DEFAULT_SEED
}

/// Supersampling and motion blur.
#[derive(Clone, Copy, Debug, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct SamplingDesc {
    /// Jittered samples per pixel (1: one ray through the pixel centre).
    #[serde(default = "Spp::one")]
    pub spp: Spp,
    /// Motion blur: the fraction of a frame the shutter stays open. Sample times
    /// spread over `[frame, frame + shutter)`, so the noise drifting with `flow`
    /// smears. 0 (the default): no blur.
    #[serde(default)]
    pub shutter: Fraction,
}

impl Default for SamplingDesc {
    fn default() -> Self {
        SamplingDesc {
            spp: Spp::one(),
            shutter: Fraction(0.0),
        }
    }
}

/// The most samples per pixel.
pub const MAX_SPP: u32 = 1024;

/// Samples per pixel, 1 to [`MAX_SPP`].
#[derive(Clone, Copy, Debug, Deserialize, PartialEq, Eq)]
#[serde(try_from = "u64")]
pub struct Spp(pub u32);

impl TryFrom<u64> for Spp {
    type Error = String;
    fn try_from(n: u64) -> Result<Self, String> {
        if (1..=u64::from(MAX_SPP)).contains(&n) {
            Ok(Spp(n as u32))
        } else {
            Err(format!(
                "expected samples per pixel from 1 to {MAX_SPP}, found {n}"
            ))
        }
    }
}

impl Spp {
    fn one() -> Self {
        Spp(1)
    }
}

/// Image size.
#[derive(Clone, Copy, Debug, Deserialize, PartialEq)]
#[serde(deny_unknown_fields, try_from = "ImageFields")]
pub struct ImageDesc {
    /// Width in pixels.
    pub width: u32,
    /// Height in pixels.
    pub height: u32,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields, rename = "Image")]
struct ImageFields {
    width: u32,
    height: u32,
}

impl TryFrom<ImageFields> for ImageDesc {
    type Error = String;
    fn try_from(f: ImageFields) -> Result<Self, String> {
        check_resolution(f.width, f.height)?;
        Ok(ImageDesc {
            width: f.width,
            height: f.height,
        })
    }
}

/// Checks an image size against [`MAX_SIDE`] and [`MAX_PIXELS`].
pub fn check_resolution(width: u32, height: u32) -> Result<(), String> {
    if width == 0 || height == 0 {
        return Err(format!(
            "image size {width}×{height}: both sides must be at least 1"
        ));
    }
    if width > MAX_SIDE || height > MAX_SIDE {
        return Err(format!(
            "image size {width}×{height}: a side may be at most {MAX_SIDE} pixels"
        ));
    }
    if u64::from(width) * u64::from(height) > MAX_PIXELS {
        return Err(format!(
            "image size {width}×{height}: at most {MAX_PIXELS} pixels in all"
        ));
    }
    Ok(())
}

/// Camera: a pinhole with a vertical field of view, or an orthographic view.
#[derive(Clone, Copy, Debug, Deserialize, PartialEq)]
#[serde(deny_unknown_fields, try_from = "CameraFields")]
pub struct CameraDesc {
    /// Eye point.
    pub eye: V3,
    /// Point looked at.
    pub look_at: V3,
    /// Up direction (need not be perpendicular to the view direction).
    pub up: V3,
    /// Perspective or orthographic.
    pub projection: ProjectionDesc,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields, rename = "Camera")]
struct CameraFields {
    eye: V3,
    look_at: V3,
    #[serde(default = "V3::y")]
    up: V3,
    projection: ProjectionDesc,
}

impl TryFrom<CameraFields> for CameraDesc {
    type Error = String;
    fn try_from(f: CameraFields) -> Result<Self, String> {
        let forward = f.look_at.0 - f.eye.0;
        if forward.length() < 1e-6 {
            return Err("camera: eye and look_at are the same point".into());
        }
        if forward.normalize().cross(f.up.0).length() < 1e-4 {
            return Err("camera: up is parallel to the view direction".into());
        }
        Ok(CameraDesc {
            eye: f.eye,
            look_at: f.look_at,
            up: f.up,
            projection: f.projection,
        })
    }
}

/// How the camera projects.
#[derive(Clone, Copy, Debug, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub enum ProjectionDesc {
    /// Pinhole camera with this vertical field of view in degrees.
    Perspective {
        /// Vertical field of view in degrees, in (0, 180).
        fov_y: FieldOfView,
    },
    /// Parallel rays; `height` is the height of the view in scene units.
    Orthographic {
        /// Height of the view in scene units.
        height: Positive,
    },
}

/// What a ray sees when it leaves the volume.
#[derive(Clone, Copy, Debug, Default, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub enum BackgroundDesc {
    /// Alpha 0: the image can be composited over anything.
    #[default]
    Transparent,
    /// An opaque colour.
    Colour(Rgb),
    /// An opaque checkerboard on the sphere of directions, so that refraction shows.
    Checker {
        /// The two colours.
        colours: (Rgb, Rgb),
        /// Squares around the horizon (≥ 2).
        squares: Squares,
    },
}

/// Lights.
#[derive(Clone, Debug, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct LightsDesc {
    /// Ambient light, added everywhere.
    #[serde(default = "Rgb::ambient")]
    pub ambient: Rgb,
    /// Directional and point lights.
    #[serde(default = "LightsDesc::default_sources")]
    pub sources: Vec<LightDesc>,
}

impl Default for LightsDesc {
    fn default() -> Self {
        LightsDesc {
            ambient: Rgb::ambient(),
            sources: LightsDesc::default_sources(),
        }
    }
}

impl LightsDesc {
    fn default_sources() -> Vec<LightDesc> {
        vec![LightDesc::Directional {
            direction: Direction(glam::Vec3::new(0.4, 0.9, 0.5).normalize()),
            colour: Rgb([1.0, 1.0, 1.0]),
        }]
    }
}

/// One light source.
#[derive(Clone, Copy, Debug, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub enum LightDesc {
    /// Light arriving from `direction` (pointing towards the light), like the sun.
    Directional {
        /// Direction towards the light (need not be unit length, must not be zero).
        direction: Direction,
        /// Its colour and intensity.
        colour: Rgb,
    },
    /// Light from a point, falling off with the square of the distance.
    Point {
        /// Where the light is.
        position: V3,
        /// Colour and intensity at distance 1.
        colour: Rgb,
    },
}

/// Ray marching settings.
#[derive(Clone, Copy, Debug, Deserialize, PartialEq)]
#[serde(deny_unknown_fields, try_from = "MarchFields")]
pub struct MarchDesc {
    /// The parallelepiped (axis-aligned box) that bounds the hypertexture.
    pub bounds: BoundsDesc,
    /// The step Δμ along the ray.
    pub step: StepDesc,
    /// The opacity constant c in `α = 1 - (1 - density)^(c · step)`.
    pub opacity: Positive,
    /// Accumulated opacity at which a ray stops.
    pub threshold: Fraction,
    /// The larger step of `--quality interactive` (default: 4 × `step`); `step`
    /// itself is the high quality.
    pub interactive_step: Option<StepDesc>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields, rename = "March")]
struct MarchFields {
    bounds: BoundsDesc,
    step: StepDesc,
    opacity: Positive,
    #[serde(default = "Fraction::threshold")]
    threshold: Fraction,
    #[serde(default)]
    interactive_step: Option<StepDesc>,
}

impl TryFrom<MarchFields> for MarchDesc {
    type Error = String;
    fn try_from(f: MarchFields) -> Result<Self, String> {
        let diagonal = (f.bounds.max.0 - f.bounds.min.0).length();
        let step = f.step.length(diagonal);
        // Guard against a march of absurd length (a hang in disguise).
        if diagonal / step > 1.0e6 {
            return Err(format!(
                "march: step {step} is too small for bounds of diagonal {diagonal} (more than a million samples per ray)"
            ));
        }
        if let Some(s) = f.interactive_step {
            let s = s.length(diagonal);
            if diagonal / s > 1.0e6 {
                return Err(format!(
                    "march: interactive_step {s} is too small for bounds of diagonal {diagonal}"
                ));
            }
        }
        Ok(MarchDesc {
            bounds: f.bounds,
            step: f.step,
            opacity: f.opacity,
            threshold: f.threshold,
            interactive_step: f.interactive_step,
        })
    }
}

/// An axis-aligned box.
#[derive(Clone, Copy, Debug, Deserialize, PartialEq)]
#[serde(deny_unknown_fields, try_from = "BoundsFields")]
pub struct BoundsDesc {
    /// The corner with the smallest coordinates.
    pub min: V3,
    /// The corner with the largest coordinates.
    pub max: V3,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields, rename = "Bounds")]
struct BoundsFields {
    min: V3,
    max: V3,
}

impl TryFrom<BoundsFields> for BoundsDesc {
    type Error = String;
    fn try_from(f: BoundsFields) -> Result<Self, String> {
        if !f.min.0.cmplt(f.max.0).all() {
            return Err(format!(
                "bounds: min {:?} must be smaller than max {:?} on every axis",
                f.min.0.to_array(),
                f.max.0.to_array()
            ));
        }
        Ok(BoundsDesc {
            min: f.min,
            max: f.max,
        })
    }
}

/// The marching step.
#[derive(Clone, Copy, Debug, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub enum StepDesc {
    /// A fixed length in scene units.
    Length(Positive),
    /// The bounding box's diagonal divided by this many steps.
    Diagonal(Positive),
}

impl StepDesc {
    /// The step length for a bounding box of this diagonal.
    pub fn length(&self, diagonal: f32) -> f32 {
        match *self {
            StepDesc::Length(l) => l.0,
            StepDesc::Diagonal(n) => diagonal / n.0,
        }
    }
}

/// A node of the object density tree.
#[derive(Clone, Debug, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub enum ObjectDesc {
    /// A soft sphere.
    Sphere(SphereDesc),
    /// A soft box.
    Box(BoxDesc),
    /// A soft torus.
    Torus(TorusDesc),
    /// A closed triangle mesh read from an OBJ file, soft outside its surface.
    Mesh(MeshDesc),
    /// Generalized union `a + b - ab`, folded over the list.
    Union(Vec<ObjectDesc>),
    /// Generalized intersection `ab`, folded over the list.
    Intersection(Vec<ObjectDesc>),
    /// Generalized difference `a - ab`.
    Difference(Box<ObjectDesc>, Box<ObjectDesc>),
    /// Generalized complement `1 - a`.
    Complement(Box<ObjectDesc>),
    /// Fuzzy-set union: the largest density.
    Max(Vec<ObjectDesc>),
    /// Fuzzy-set intersection: the smallest density.
    Min(Vec<ObjectDesc>),
    /// An object with its own density modulation functions applied.
    Hypertexture(HypertextureDesc),
}

/// An object with its own DMFs: `Hypertexture(object: ..., modulation: [...])`.
#[derive(Clone, Debug, Deserialize, PartialEq)]
#[serde(deny_unknown_fields, try_from = "HypertextureFields")]
pub struct HypertextureDesc {
    /// The object modulated.
    pub object: Box<ObjectDesc>,
    /// Its DMFs, applied in order.
    pub modulation: Vec<DmfDesc>,
    /// Whether the value DMFs shape its hard region (D = 1) too.
    pub hard_core: HardCore,
    /// Gilet & Dischler's distortion, applied after the position DMFs.
    pub distortion: Option<DistortionDesc>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields, rename = "Hypertexture")]
struct HypertextureFields {
    object: Box<ObjectDesc>,
    #[serde(default)]
    modulation: Vec<DmfDesc>,
    #[serde(default)]
    hard_core: HardCore,
    #[serde(default)]
    distortion: Option<DistortionDesc>,
}

impl TryFrom<HypertextureFields> for HypertextureDesc {
    type Error = String;
    fn try_from(f: HypertextureFields) -> Result<Self, String> {
        check_chain(&f.object, &f.modulation)?;
        if let Some(d) = &f.distortion {
            check_distortion(d, f.object.is_primitive())?;
        }
        Ok(HypertextureDesc {
            object: f.object,
            modulation: f.modulation,
            hard_core: f.hard_core,
            distortion: f.distortion,
        })
    }
}

/// What the value DMFs do where the object is solid (D = 1).
///
/// The paper's base shapes "have a hard region where they are completely
/// solid, and a soft region where they are indeterminate"; the shaping
/// functions apply in the soft region. `Solid` (the default) keeps f = 1
/// where D = 1, so a ray reaching the hard region turns opaque there (unless
/// an alpha map says otherwise). `Shaped` applies the DMFs literally
/// everywhere, the hard region included.
#[derive(Clone, Copy, Debug, Default, Deserialize, PartialEq, Eq)]
pub enum HardCore {
    /// f = 1 where D = 1: the DMFs shape only the soft region.
    #[default]
    Solid,
    /// f = f_n(… f_1(D)) everywhere, the hard region included.
    Shaped,
}

/// The most DMFs one object may have.
pub const MAX_DMFS: usize = 32;

/// Checks a DMF chain against its object: position-dependent DMFs first (they
/// choose where D is evaluated), and fur only on objects that can project.
pub fn check_chain(object: &ObjectDesc, dmfs: &[DmfDesc]) -> Result<(), String> {
    if dmfs.len() > MAX_DMFS {
        return Err(format!(
            "modulation: at most {MAX_DMFS} DMFs, found {}",
            dmfs.len()
        ));
    }
    let mut first_value: Option<&str> = None;
    for (i, dmf) in dmfs.iter().enumerate() {
        if dmf.is_position_dependent() {
            if let Some(value) = first_value {
                return Err(format!(
                    "modulation[{i}]: {} moves the point x where D is evaluated, so it must come before {value}",
                    dmf.name()
                ));
            }
        } else if first_value.is_none() {
            first_value = Some(dmf.name());
        }
        if matches!(dmf, DmfDesc::Fur { .. }) && !object.is_primitive() {
            return Err(format!(
                "modulation[{i}]: Fur projects x onto the object's inner surface, so its object must be a Sphere, Box, Torus or Mesh (wrap one in Hypertexture(object: ..., modulation: [Fur(...)]))"
            ));
        }
    }
    Ok(())
}

/// A triangle mesh as a soft object: `Mesh(path: "meshes/spot.obj", softness: 0.1)`.
/// The mesh's surface is the inner (D = 1) surface; D falls off outside it as a
/// soft sphere's does, `D = (s² - d²) / s²` at a distance d < s, the paper's
/// falloff of a sphere of inner radius 0 and outer radius s swept over the
/// surface.
#[derive(Clone, Debug, Deserialize, PartialEq)]
#[serde(deny_unknown_fields, try_from = "MeshFields")]
pub struct MeshDesc {
    /// The OBJ file, relative to the scene file's directory.
    pub path: String,
    /// Softness s: the thickness of the soft region outside the surface.
    pub softness: f32,
    /// Where the mesh's origin goes.
    pub centre: V3,
    /// Uniform scale of the mesh about its origin.
    pub scale: f32,
    /// How D reads the distance to the surface.
    pub sdf: SdfDesc,
    /// The loaded mesh, attached before the scene is built
    /// ([`SceneDesc::attach_meshes`]).
    #[serde(skip)]
    pub mesh: Option<std::sync::Arc<crate::mesh::Mesh>>,
    /// The mesh's distance field when `sdf` is a `Field`, built after the
    /// mesh is attached ([`SceneDesc::attach_mesh_fields`]).
    #[serde(skip)]
    pub field: Option<std::sync::Arc<crate::mesh::Band>>,
}

/// How a mesh's D reads the distance to its surface:
/// `sdf: Field(voxel: Some(0.005), max_mib: 1024)` (the default, every field
/// optional) or `sdf: Exact`.
#[derive(Clone, Copy, Debug, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub enum SdfDesc {
    /// A sparse narrow-band grid of the signed distance and closest point,
    /// built once per mesh and resolution and read by trilinear
    /// interpolation ([`crate::mesh::Band`]).
    Field {
        /// The voxel's edge in the scene's units (default: softness / 4).
        #[serde(default)]
        voxel: Option<Positive>,
        /// The most memory the field may take, in MiB (default 1024).
        #[serde(default = "default_field_mib")]
        max_mib: Positive,
    },
    /// The exact closest-triangle search at every sample.
    Exact,
}

impl Default for SdfDesc {
    fn default() -> Self {
        SdfDesc::Field {
            voxel: None,
            max_mib: default_field_mib(),
        }
    }
}

fn default_field_mib() -> Positive {
    Positive((crate::mesh::DEFAULT_MAX_FIELD_BYTES >> 20) as f32)
}

/// The voxel of a mesh's field when the scene gives none, as a fraction of
/// the softness.
pub const FIELD_VOXELS_PER_SOFTNESS: f32 = 4.0;

impl MeshDesc {
    /// The field's lengths in the mesh's own coordinates, or `None` for
    /// `sdf: Exact` (or a hard mesh, softness 0, whose D needs the sign
    /// alone). Under a distortion that moves points by up to `moves` (0
    /// without one) the band reaches that much and
    /// [`crate::mesh::FIELD_MARGIN_VOXELS`] voxels farther, so that the
    /// distortion reads its vector field from the band wherever it matters
    /// ([`crate::field::soft::SoftMesh::covers_distortion`]).
    pub fn field_spec(&self, moves: f32) -> Option<crate::mesh::BandSpec> {
        let SdfDesc::Field { voxel, max_mib } = self.sdf else {
            return None;
        };
        if self.softness <= 0.0 {
            return None;
        }
        let voxel = voxel.map_or(self.softness / FIELD_VOXELS_PER_SOFTNESS, |v| v.0) / self.scale;
        let outer = if moves > 0.0 {
            (self.softness + moves) / self.scale + crate::mesh::FIELD_MARGIN_VOXELS * voxel
        } else {
            self.softness / self.scale
        };
        Some(crate::mesh::BandSpec {
            voxel,
            outer,
            inner: 2.0 * voxel,
            max_bytes: (f64::from(max_mib.0) * 1048576.0) as u64,
        })
    }
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields, rename = "Mesh")]
struct MeshFields {
    path: String,
    softness: NonNegative,
    #[serde(default)]
    centre: V3,
    #[serde(default = "one")]
    scale: Positive,
    #[serde(default)]
    sdf: SdfDesc,
}

fn one() -> Positive {
    Positive(1.0)
}

impl TryFrom<MeshFields> for MeshDesc {
    type Error = String;
    fn try_from(f: MeshFields) -> Result<Self, String> {
        if f.path.trim().is_empty() || f.path.contains('\0') {
            return Err(format!("mesh: path {:?} does not name a file", f.path));
        }
        Ok(MeshDesc {
            path: f.path,
            softness: f.softness.0,
            centre: f.centre,
            scale: f.scale.0,
            sdf: f.sdf,
            mesh: None,
            field: None,
        })
    }
}

impl ObjectDesc {
    /// Calls `f` on every mesh of the tree, in the order written.
    pub fn for_each_mesh(&self, f: &mut impl FnMut(&MeshDesc)) {
        match self {
            ObjectDesc::Mesh(m) => f(m),
            ObjectDesc::Sphere(_) | ObjectDesc::Box(_) | ObjectDesc::Torus(_) => {}
            ObjectDesc::Union(v)
            | ObjectDesc::Intersection(v)
            | ObjectDesc::Max(v)
            | ObjectDesc::Min(v) => v.iter().for_each(|o| o.for_each_mesh(f)),
            ObjectDesc::Difference(a, b) => {
                a.for_each_mesh(f);
                b.for_each_mesh(f);
            }
            ObjectDesc::Complement(a) => a.for_each_mesh(f),
            ObjectDesc::Hypertexture(h) => h.object.for_each_mesh(f),
        }
    }

    /// [`ObjectDesc::for_each_mesh`], mutably.
    pub fn for_each_mesh_mut(&mut self, f: &mut impl FnMut(&mut MeshDesc)) {
        match self {
            ObjectDesc::Mesh(m) => f(m),
            ObjectDesc::Sphere(_) | ObjectDesc::Box(_) | ObjectDesc::Torus(_) => {}
            ObjectDesc::Union(v)
            | ObjectDesc::Intersection(v)
            | ObjectDesc::Max(v)
            | ObjectDesc::Min(v) => v.iter_mut().for_each(|o| o.for_each_mesh_mut(f)),
            ObjectDesc::Difference(a, b) => {
                a.for_each_mesh_mut(f);
                b.for_each_mesh_mut(f);
            }
            ObjectDesc::Complement(a) => a.for_each_mesh_mut(f),
            ObjectDesc::Hypertexture(h) => h.object.for_each_mesh_mut(f),
        }
    }

    /// [`ObjectDesc::for_each_mesh_mut`], with what a distortion can move
    /// each mesh's points by: `moves` for this object if it is a mesh, a
    /// hypertexture's distortion's for its object if that is a mesh, else 0.
    /// `displacement` gives a distortion's largest displacement.
    pub fn for_each_mesh_moved_mut(
        &mut self,
        moves: f32,
        displacement: &impl Fn(&DistortionDesc) -> f32,
        f: &mut impl FnMut(&mut MeshDesc, f32),
    ) {
        match self {
            ObjectDesc::Mesh(m) => f(m, moves),
            ObjectDesc::Hypertexture(h) => {
                let moves = h.distortion.as_ref().map_or(0.0, displacement);
                h.object.for_each_mesh_moved_mut(moves, displacement, f);
            }
            other => other.for_each_mesh_mut(&mut |m| f(m, 0.0)),
        }
    }

    /// Whether the fur's projection onto the inner surface (and the boundary
    /// vector fields) are defined for this object: a primitive.
    pub fn is_primitive(&self) -> bool {
        matches!(
            self,
            ObjectDesc::Sphere(_) | ObjectDesc::Box(_) | ObjectDesc::Torus(_) | ObjectDesc::Mesh(_)
        )
    }
}

impl SceneDesc {
    /// The mesh files the scene names, each once, in path order (as written).
    pub fn mesh_paths(&self) -> Vec<String> {
        let mut paths = std::collections::BTreeSet::new();
        let mut add = |m: &MeshDesc| {
            paths.insert(m.path.clone());
        };
        self.object.for_each_mesh(&mut add);
        for o in self.objects.values() {
            o.for_each_mesh(&mut add);
        }
        paths.into_iter().collect()
    }

    /// Gives every mesh of the scene its loaded [`crate::mesh::Mesh`]; the
    /// first path `find` has none for is the error.
    pub fn attach_meshes(
        &mut self,
        mut find: impl FnMut(&str) -> Option<std::sync::Arc<crate::mesh::Mesh>>,
    ) -> Result<(), String> {
        let mut missing = None;
        let mut attach = |m: &mut MeshDesc| match find(&m.path) {
            Some(mesh) => m.mesh = Some(mesh),
            None => {
                missing.get_or_insert_with(|| m.path.clone());
            }
        };
        self.object.for_each_mesh_mut(&mut attach);
        for o in self.objects.values_mut() {
            o.for_each_mesh_mut(&mut attach);
        }
        missing.map_or(Ok(()), Err)
    }

    /// Gives every attached mesh with `sdf: Field` its distance field (built
    /// once per process, mesh and resolution: [`crate::mesh::Band::shared`]);
    /// the first that cannot be built is the error: its path and why.
    /// `displacement` gives a distortion's largest displacement (the field
    /// layer's `Distortion::max_displacement`).
    pub fn attach_mesh_fields(
        &mut self,
        displacement: &impl Fn(&DistortionDesc) -> f32,
    ) -> Result<(), (String, String)> {
        let mut error = None;
        let mut attach = |m: &mut MeshDesc, moves: f32| {
            if let (Some(mesh), Some(spec), None) = (&m.mesh, m.field_spec(moves), &error) {
                match crate::mesh::Band::shared(mesh, &spec) {
                    Ok(band) => m.field = Some(band),
                    Err(e) => error = Some((m.path.clone(), e)),
                }
            }
        };
        let moves = self.distortion.as_ref().map_or(0.0, displacement);
        self.object
            .for_each_mesh_moved_mut(moves, displacement, &mut attach);
        for o in self.objects.values_mut() {
            o.for_each_mesh_moved_mut(0.0, displacement, &mut attach);
        }
        error.map_or(Ok(()), Err)
    }
}

/// A soft sphere.
#[derive(Clone, Copy, Debug, Deserialize, PartialEq)]
#[serde(deny_unknown_fields, try_from = "SphereFields")]
pub struct SphereDesc {
    /// Centre.
    pub centre: V3,
    /// Radius r.
    pub radius: f32,
    /// Softness s: D = 1 inside r - s/2, 0 outside r + s/2.
    pub softness: f32,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields, rename = "Sphere")]
struct SphereFields {
    #[serde(default)]
    centre: V3,
    radius: Positive,
    softness: NonNegative,
}

impl TryFrom<SphereFields> for SphereDesc {
    type Error = String;
    fn try_from(f: SphereFields) -> Result<Self, String> {
        check_softness("sphere", "radius", f.radius.0, f.softness.0)?;
        Ok(SphereDesc {
            centre: f.centre,
            radius: f.radius.0,
            softness: f.softness.0,
        })
    }
}

fn check_softness(what: &str, radius_name: &str, radius: f32, softness: f32) -> Result<(), String> {
    if softness > 2.0 * radius {
        return Err(format!(
            "{what}: softness {softness} is more than twice the {radius_name} {radius} (the inner radius r - s/2 would be negative)"
        ));
    }
    Ok(())
}

/// A soft box: the product of three soft slabs.
#[derive(Clone, Copy, Debug, Deserialize, PartialEq)]
#[serde(deny_unknown_fields, try_from = "BoxFields")]
pub struct BoxDesc {
    /// Centre.
    pub centre: V3,
    /// Half the size along each axis.
    pub half_size: V3,
    /// Softness of each face.
    pub softness: f32,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields, rename = "Box")]
struct BoxFields {
    #[serde(default)]
    centre: V3,
    half_size: V3,
    softness: NonNegative,
}

impl TryFrom<BoxFields> for BoxDesc {
    type Error = String;
    fn try_from(f: BoxFields) -> Result<Self, String> {
        for h in f.half_size.0.to_array() {
            if h <= 0.0 {
                return Err(format!("box: half_size {h} must be positive"));
            }
            check_softness("box", "half_size", h, f.softness.0)?;
        }
        Ok(BoxDesc {
            centre: f.centre,
            half_size: f.half_size,
            softness: f.softness.0,
        })
    }
}

/// A soft torus.
#[derive(Clone, Copy, Debug, Deserialize, PartialEq)]
#[serde(deny_unknown_fields, try_from = "TorusFields")]
pub struct TorusDesc {
    /// Centre of the ring.
    pub centre: V3,
    /// Axis of the ring.
    pub axis: Direction,
    /// Radius of the core circle.
    pub major_radius: f32,
    /// Radius of the tube.
    pub minor_radius: f32,
    /// Softness of the tube.
    pub softness: f32,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields, rename = "Torus")]
struct TorusFields {
    #[serde(default)]
    centre: V3,
    #[serde(default = "Direction::y")]
    axis: Direction,
    major_radius: Positive,
    minor_radius: Positive,
    softness: NonNegative,
}

impl TryFrom<TorusFields> for TorusDesc {
    type Error = String;
    fn try_from(f: TorusFields) -> Result<Self, String> {
        check_softness("torus", "minor_radius", f.minor_radius.0, f.softness.0)?;
        Ok(TorusDesc {
            centre: f.centre,
            axis: f.axis,
            major_radius: f.major_radius.0,
            minor_radius: f.minor_radius.0,
            softness: f.softness.0,
        })
    }
}

/// A density modulation function (section 2.4).
///
/// The first four are position-dependent: they move the point x at which D is
/// evaluated (the paper's `sphere(x(1 + ...))`), and must come before the others.
#[derive(Clone, Copy, Debug, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub enum DmfDesc {
    /// Noise-scaled radius: `D(c + (x - c)(1 + amplitude · noise(frequency · x)))`.
    /// The paper's noisy sphere uses amplitude 1/frequency.
    NoisyRadius {
        /// Frequency f of the noise.
        frequency: Positive,
        /// Amplitude of the radius modulation.
        amplitude: NonNegative,
        /// Centre of the scaling.
        #[serde(default)]
        centre: V3,
    },
    /// Fractal sum: `D(c + (x - c)(1 + Σ noise(2^i f x) / (2^i f)))`, the octaves
    /// clamped so that the finest is no smaller than the marching step.
    FractalRadius {
        /// Base frequency f.
        frequency: Positive,
        /// Most octaves to sum.
        #[serde(default = "Octaves::six")]
        octaves: Octaves,
        /// Overall amplitude (1 is the paper's).
        #[serde(default = "NonNegative::one")]
        amplitude: NonNegative,
        /// Centre of the scaling.
        #[serde(default)]
        centre: V3,
    },
    /// Shaped noise on one axis: below the centre only y is scaled, by the positive
    /// part of noise that varies slowly in y (`stretch`), so material hangs in drips:
    /// `y' = c.y + (y - c.y)(1 - a · max(0, noise(f · (x, stretch · y, z))))`.
    Dripping {
        /// Frequency of the noise across x and z.
        frequency: Positive,
        /// Amplitude of the y modulation.
        amplitude: NonNegative,
        /// Frequency of the noise along y relative to x and z (small: long drips).
        #[serde(default = "NonNegative::fifth")]
        stretch: NonNegative,
        /// Centre of the scaling.
        #[serde(default)]
        centre: V3,
    },
    /// Turbulence-scaled radius, the fire ball: `D(c + (x - c)(1 + a·turbulence(f x)))`.
    TurbulentRadius {
        /// Frequency of the turbulence.
        #[serde(default = "Positive::one")]
        frequency: Positive,
        /// Amplitude a.
        #[serde(default = "NonNegative::one")]
        amplitude: NonNegative,
        /// Most octaves (clamped by the step).
        #[serde(default = "Octaves::six")]
        octaves: Octaves,
        /// Centre of the scaling.
        #[serde(default)]
        centre: V3,
    },
    /// `bias_b` of the density.
    Bias(UnitOpen),
    /// `gain_g` of the density.
    Gain(UnitOpen),
    /// Fur (and curly fur): `s = noise(frequency · project(x'))`,
    /// `f = gain_g(bias_b(s)) · d` with `d = D(x)` and
    /// `x' = x + gain_{curl_gain}(1 - d) · curliness · vnoise(x)`.
    Fur {
        /// Fineness: the frequency of the noise on the inner surface.
        frequency: Positive,
        /// Bias b (0.3 in the paper: more empty space than hair).
        #[serde(default = "UnitOpen::fur_bias")]
        bias: UnitOpen,
        /// Gain g (0.9 in the paper: hard-edged hairs).
        #[serde(default = "UnitOpen::fur_gain")]
        gain: UnitOpen,
        /// Curliness (0: straight hair).
        #[serde(default)]
        curliness: NonNegative,
        /// Gain shaping the curl from root to tip (0.8 in the paper).
        #[serde(default = "UnitOpen::curl_gain")]
        curl_gain: UnitOpen,
    },
}

impl DmfDesc {
    /// The DMF's name as written in a scene.
    pub fn name(&self) -> &'static str {
        match self {
            DmfDesc::NoisyRadius { .. } => "NoisyRadius",
            DmfDesc::FractalRadius { .. } => "FractalRadius",
            DmfDesc::Dripping { .. } => "Dripping",
            DmfDesc::TurbulentRadius { .. } => "TurbulentRadius",
            DmfDesc::Bias(_) => "Bias",
            DmfDesc::Gain(_) => "Gain",
            DmfDesc::Fur { .. } => "Fur",
        }
    }

    /// Whether this DMF moves the point at which D is evaluated.
    pub fn is_position_dependent(&self) -> bool {
        matches!(
            self,
            DmfDesc::NoisyRadius { .. }
                | DmfDesc::FractalRadius { .. }
                | DmfDesc::Dripping { .. }
                | DmfDesc::TurbulentRadius { .. }
        )
    }
}

/// What indexes the colour map.
#[derive(Clone, Copy, Debug, Default, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub enum ColourIndexDesc {
    /// The density (the paper's colour maps).
    #[default]
    Density,
    /// Strata bent by turbulence, as the 1985 marble:
    /// `0.5 + 0.5 sin(frequency · y + amplitude · turbulence(x))`.
    Strata {
        /// Frequency of the layers along y.
        frequency: Positive,
        /// How much turbulence bends them.
        amplitude: NonNegative,
        /// Octaves of turbulence (clamped by the step).
        #[serde(default = "Octaves::six")]
        octaves: Octaves,
    },
}

/// Shading parameters.
#[derive(Clone, Copy, Debug, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct ShadingDesc {
    /// Diffuse reflectance factor.
    #[serde(default = "NonNegative::one")]
    pub diffuse: NonNegative,
    /// Specular reflectance factor.
    #[serde(default)]
    pub specular: NonNegative,
    /// Phong exponent of the highlight.
    #[serde(default = "Positive::shininess")]
    pub shininess: Positive,
    /// How the shading normal (the density gradient) is estimated.
    #[serde(default)]
    pub gradient: GradientDesc,
    /// Self-shadowing: a secondary ray marched towards each light attenuates it by
    /// the transmittance of the volume in between.
    #[serde(default)]
    pub shadows: bool,
}

impl Default for ShadingDesc {
    fn default() -> Self {
        ShadingDesc {
            diffuse: NonNegative(1.0),
            specular: NonNegative(0.0),
            shininess: Positive(20.0),
            gradient: GradientDesc::Forward,
            shadows: false,
        }
    }
}

/// The finite differences that estimate the density gradient.
#[derive(Clone, Copy, Debug, Default, Deserialize, PartialEq, Eq)]
pub enum GradientDesc {
    /// Hypertexture's differences along the ray basis (two extra evaluations,
    /// reusing the previous sample).
    #[default]
    Forward,
    /// Central differences along x, y and z (six extra evaluations), as Gilet &
    /// Dischler shade.
    Central,
    /// The derivative itself, by forward-mode differentiation (dual numbers)
    /// through the density chain ([`crate::math::dual`]): one pass, no extra
    /// evaluations; the image differs slightly from the differences'.
    Dual,
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::scene::{SceneError, parse};

    /// The fewest fields a scene must give.
    const MINIMAL: &str = "Scene(
    image: (width: 64, height: 48),
    camera: (eye: (0.0, 0.0, 4.0), look_at: (0.0, 0.0, 0.0), projection: Perspective(fov_y: 45.0)),
    march: (bounds: (min: (-1.0, -1.0, -1.0), max: (1.0, 1.0, 1.0)), step: Diagonal(200), opacity: 40.0),
    object: Sphere(radius: 0.8, softness: 0.2),
)";

    /// `MINIMAL` with `line` added after its `object` field.
    fn with(line: &str) -> String {
        MINIMAL.replace(
            "softness: 0.2),\n",
            &format!("softness: 0.2),\n    {line}\n"),
        )
    }

    /// The error of a text that must not parse, as (line, column, message).
    fn refused(text: &str) -> (usize, usize, String) {
        match parse(text, "t.ron") {
            Err(SceneError::Parse {
                path,
                line,
                column,
                message,
            }) => {
                assert_eq!(path, "t.ron");
                (line, column, message)
            }
            other => panic!("expected a parse error, got {other:?}"),
        }
    }

    #[test]
    fn a_minimal_scene_parses_with_its_values() {
        let desc = parse(MINIMAL, "t.ron").expect("the minimal scene parses");
        assert_eq!((desc.image.width, desc.image.height), (64, 48));
        assert_eq!(desc.camera.eye.0, glam::Vec3::new(0.0, 0.0, 4.0));
        assert_eq!(desc.march.bounds.min.0, glam::Vec3::splat(-1.0));
        assert_eq!(desc.march.step, StepDesc::Diagonal(Positive(200.0)));
        assert_eq!(desc.march.step.length(2.0), 2.0 / 200.0);
        let ObjectDesc::Sphere(sphere) = &desc.object else {
            panic!("expected a sphere, got {:?}", desc.object);
        };
        assert_eq!((sphere.radius, sphere.softness), (0.8, 0.2));
    }

    #[test]
    fn fields_left_out_take_their_defaults() {
        let desc = parse(MINIMAL, "t.ron").expect("the minimal scene parses");
        assert_eq!(desc.background, BackgroundDesc::Transparent);
        assert_eq!(desc.lights, LightsDesc::default());
        assert_eq!(desc.shading, ShadingDesc::default());
        assert_eq!(desc.sampling, SamplingDesc::default());
        assert_eq!(desc.sampling.spp, Spp(1));
        assert_eq!(desc.seed, DEFAULT_SEED);
        assert_eq!(desc.frame_rate.0, 24.0);
        assert_eq!(desc.colour_map, CurveDesc::white());
        assert_eq!(desc.colour_index, ColourIndexDesc::default());
        assert!(desc.modulation.is_empty() && desc.objects.is_empty() && desc.knobs.is_empty());
        assert!(desc.distortion.is_none() && desc.transform.is_none() && desc.density.is_none());
        assert_eq!(desc.march.threshold, Fraction::threshold());
        // No modulation: the object is its own hypertexture.
        assert_eq!(desc.object_with_modulation(), desc.object);
    }

    #[test]
    fn a_modulated_object_is_wrapped_in_its_hypertexture() {
        let desc = parse(&with("modulation: [Bias(0.3)],"), "t.ron").expect("parses");
        assert_eq!(desc.modulation, vec![DmfDesc::Bias(UnitOpen(0.3))]);
        let ObjectDesc::Hypertexture(h) = desc.object_with_modulation() else {
            panic!("expected the object wrapped in a hypertexture");
        };
        assert_eq!(*h.object, desc.object);
        assert_eq!(h.modulation, desc.modulation);
    }

    #[test]
    fn a_value_out_of_range_is_named_at_its_line_and_column() {
        let text = with("sampling: (spp: 0),");
        let (line, column, message) = refused(&text);
        let (want_line, row) = text
            .lines()
            .enumerate()
            .find(|(_, l)| l.contains("spp: 0"))
            .expect("the line is in the text");
        assert_eq!(line, want_line + 1, "{message}");
        let value = row.find("0)").expect("the value is on its line") + 1;
        assert!(
            (row.find("spp").expect("field") + 1..=value + 1).contains(&column),
            "column {column} of {row:?}: {message}"
        );
        assert!(
            message.contains(&format!(
                "expected samples per pixel from 1 to {MAX_SPP}, found 0"
            )),
            "{message}"
        );
    }

    #[test]
    fn a_field_given_twice_is_named_where_it_stands_again() {
        let text = with("sampling: (spp: 4),\n    sampling: (spp: 8),");
        let (line, _, message) = refused(&text);
        assert_eq!(line, 7, "{message}");
        assert!(message.contains("sampling"), "{message}");
    }

    #[test]
    fn a_missing_field_is_named() {
        let text = MINIMAL.replace(
            "    march: (bounds: (min: (-1.0, -1.0, -1.0), max: (1.0, 1.0, 1.0)), step: Diagonal(200), opacity: 40.0),\n",
            "",
        );
        let (_, _, message) = refused(&text);
        assert!(message.contains("march"), "{message}");
    }

    #[test]
    fn map_keys_must_increase() {
        let text = with("colour_map: (points: [(0.5, (1.0, 1.0, 1.0)), (0.2, (0.0, 0.0, 0.0))]),");
        let (line, _, message) = refused(&text);
        assert_eq!(line, 6, "{message}");
        assert!(
            message.contains("map keys must increase: 0.2 comes after 0.5"),
            "{message}"
        );
    }

    #[test]
    fn samples_per_pixel_and_image_sizes_are_bounded() {
        assert_eq!(Spp::try_from(1), Ok(Spp(1)));
        assert_eq!(Spp::try_from(u64::from(MAX_SPP)), Ok(Spp(MAX_SPP)));
        assert!(Spp::try_from(u64::from(MAX_SPP) + 1).is_err());
        assert!(Spp::try_from(0).is_err());
        assert_eq!(check_resolution(1, 1), Ok(()));
        assert_eq!(check_resolution(MAX_SIDE, 1), Ok(()));
        let zero = check_resolution(0, 5).expect_err("a zero side is refused");
        assert!(zero.contains("at least 1"), "{zero}");
        let wide = check_resolution(MAX_SIDE + 1, 1).expect_err("too wide");
        assert!(wide.contains(&MAX_SIDE.to_string()), "{wide}");
        let many = check_resolution(MAX_SIDE, MAX_SIDE).expect_err("too many pixels");
        assert!(many.contains(&MAX_PIXELS.to_string()), "{many}");
    }

    #[test]
    fn mesh_paths_are_listed_once_in_order() {
        let text = MINIMAL.replace(
            "object: Sphere(radius: 0.8, softness: 0.2),",
            "object: Union([Mesh(path: \"b.obj\", softness: 0.1), Mesh(path: \"a.obj\", softness: 0.1), Mesh(path: \"b.obj\", softness: 0.2)]),",
        );
        let mut desc = parse(&text, "t.ron").expect("parses");
        assert_eq!(
            desc.mesh_paths(),
            vec!["a.obj".to_string(), "b.obj".to_string()]
        );
        assert_eq!(desc.attach_meshes(|_| None), Err("b.obj".to_string()));
    }

    #[test]
    fn a_mesh_reads_a_field_unless_told_exact() {
        let mesh = |object: &str| {
            let text = MINIMAL.replace("object: Sphere(radius: 0.8, softness: 0.2),", object);
            let desc = parse(&text, "t.ron").expect("parses");
            let ObjectDesc::Mesh(m) = desc.object else {
                panic!("not a mesh")
            };
            m
        };
        let default = mesh("object: Mesh(path: \"a.obj\", softness: 0.08, scale: 2.0),");
        assert_eq!(default.sdf, SdfDesc::default());
        let spec = default.field_spec(0.0).expect("a field by default");
        // Lengths in the mesh's own coordinates: the scene's over the scale.
        assert_eq!((spec.voxel, spec.outer), (0.01, 0.04));
        assert_eq!(spec.max_bytes, crate::mesh::DEFAULT_MAX_FIELD_BYTES);
        let set = mesh(
            "object: Mesh(path: \"a.obj\", softness: 0.08, sdf: Field(voxel: Some(0.004), max_mib: 16)),",
        );
        let spec = set.field_spec(0.0).expect("a field");
        assert_eq!((spec.voxel, spec.max_bytes), (0.004, 16 << 20));
        let exact = mesh("object: Mesh(path: \"a.obj\", softness: 0.08, sdf: Exact),");
        assert_eq!((exact.sdf, exact.field_spec(0.0)), (SdfDesc::Exact, None));
        for (bad, says) in [
            ("sdf: Field(voxel: Some(-0.1))", "a positive number"),
            ("sdf: Fast", "Fast"),
            ("sdf: Field(size: 2.0)", "size"),
        ] {
            let text = MINIMAL.replace(
                "object: Sphere(radius: 0.8, softness: 0.2),",
                &format!("object: Mesh(path: \"a.obj\", softness: 0.08, {bad}),"),
            );
            let (line, _, message) = refused(&text);
            assert_eq!(line, 5, "{bad}: {message}");
            assert!(message.contains(says), "{bad}: {message}");
        }
    }
}
