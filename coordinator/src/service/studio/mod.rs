//! The live studio: a page at `/` of the service that shows one scene
//! refining as its units arrive, with a slider per knob and the scene's text
//! editable.
//!
//! A *live frame* is a scheduler job of its own (ids from [`LIVE_JOBS`] on,
//! the highest priority, never stored): each change of the text or of a knob
//! takes the frame in flight out of the farm (its units are no longer handed
//! out, and tiles still coming are ignored) and adds the new one. Knob values
//! travel to workers in `Job.knobs` over the unchanged scene text. While a
//! control is dragged, the page asks for previews (interactive frames at half
//! the width and height), and a begun interactive frame renders to its end
//! with the next one queued behind it ([`Studio::retire`]), so that the
//! workers never wait for the page between the values of a drag.
//!
//! Tiles reach the page by Server-Sent Events (`/studio/events`): the farm's
//! [`TileSink`](crate::farm::TileSink) hands each accepted tile of a live
//! frame to an unbounded channel (it runs with the farm's state locked, so it
//! only copies); the recorder task makes its event once (its unit, its place
//! in the frame's order and, for an interactive frame, its 8-bit sRGB pixels
//! in base64), keeps it for browsers that connect later, and broadcasts it.
//! A high-quality frame's tiles go out together, at most every 100 ms, in
//! one `tiles` event without pixels: the page fetches those of the tiles it
//! has not drawn, in one request, when it draws, so that while the workers
//! render the frame the browser does almost nothing. A browser that falls behind the broadcast is disconnected
//! (its `EventSource` reconnects and is sent the frame again); a closed tab's
//! receiver is dropped with its stream.
//!
//! The server owns the state every tab shows ([`versions`]): the text and
//! values carry a version; each edit that changes them is broadcast to every
//! tab (a `scene` event, ranges included), and an edit made on an older
//! version is merged or refused as a conflict, never applied blindly. Once
//! the edits rest for [`REST`], the server draws the high-quality frame
//! itself.
//!
//! `coordinator studio DIR` (or a scene file, whose directory is browsed)
//! lists the directory's scenes with thumbnails the farm renders below the
//! live frame's priority ([`scenes`]). Opening one (`POST /studio/open`)
//! switches the live scene for every tab: Save, Reload and Render final act
//! on its file from then on. The undo history and the snapshots belong to
//! the scene: an open drops those of the scene before, and its first
//! version is newer than any of that scene's, so an edit a tab made on the
//! scene before is refused as stale rather than applied to the new text.
//!
//! Lock order: the studio's state, then the scene browser's catalogue, then
//! the farm's state; the opened file's name and path are a leaf lock, set
//! only with the studio's state held. The tile sink takes no studio lock.
//!
//! | Method and path          | What                                                      |
//! |--------------------------|-----------------------------------------------------------|
//! | `GET /`                  | the page (and `/studio/studio.js`, `/studio/studio.css`)  |
//! | `GET /studio/scene`      | the scene: its text for the current knob values, the knobs |
//! | `POST /studio/scene`     | new text and/or values, structural edits ([`shape`]) and a quality, made on a version: a new frame; 409 when it conflicts |
//! | `POST /studio/save[?over=true]` | writes the text back to SCENE, the file before to SCENE.~N~; 409 when SCENE changed on disk |
//! | `POST /studio/reload`    | takes SCENE's text from disk: a new frame                 |
//! | `POST /studio/final`     | queues the shown text as a job writing `STEM.final.NNNN.png` (the next free N) |
//! | `GET /studio/final/N`    | final render N's PNG                                      |
//! | `GET /studio/events`     | Server-Sent Events: `scene`, `frame`, `tile`, `tiles`, `done`, `status`, `error`, `snapshots`, `scenes` (a thumbnail is ready) |
//! | `GET /studio/tiles?generation=G&from=A&to=B` | the pixels of the current frame's tiles A..B, one after another |
//! | `POST /studio/undo[?tab=T]`, `POST /studio/redo[?tab=T]` | steps back or forward through the one history of every tab's edits: a new version; 409 when there is no step |
//! | `POST /studio/snapshots` | `{"name": N}`: a snapshot of the shown state, its image rendered by the farm; answers the list |
//! | `POST /studio/snapshots/ID/restore[?tab=T]` | sets the snapshot's text and frame back, as an edit |
//! | `GET /studio/snapshots/ID/pixels` | its image's 8-bit sRGB RGBA, row-major (409 until rendered) |
//! | `GET /studio/scenes`     | the browsed directory's scenes ([`scenes`]): each one's path, name, title, thumbnail state and error; 404 when the studio browses none |
//! | `GET /studio/scenes/thumbnail?path=REL` | a scene's thumbnail (PNG): 409 while it renders, 404 for a path not listed or a scene that does not build, 400 for a path outside the directory |
//! | `POST /studio/open`      | `{"path": REL, "base": V, "discard": false}`: that scene becomes the live one, in every tab; 400 outside the directory, 404 no such scene, 409 for unsaved edits (unless `discard`) or a stale `base` |
//!
//! With a token, the data routes (not the static page, which holds nothing of
//! the service) need `Authorization: Bearer <token>`; the event stream alone
//! also takes `?token=<token>` (an `EventSource` cannot send a header), and
//! the page sends the header on every other request.

use std::collections::{BTreeMap, VecDeque};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex, OnceLock};
use std::time::{Duration, Instant};

use axum::Json;
use axum::Router;
use axum::extract::{Query, Request, State};
use axum::http::{StatusCode, header};
use axum::middleware::{self, Next};
use axum::response::sse::{Event as SseEvent, KeepAlive, Sse};
use axum::response::{IntoResponse, Response};
use base64::Engine as _;
use hypertexture::desc::KnobDesc;
use hypertexture::render::interleave::{WorkUnit, farm_units};
use hypertexture::{FrameRange, Overrides, PixelFormat, Quality, RenderRequest};
use serde::{Deserialize, Serialize};
use tokio::sync::{broadcast, mpsc};

use super::params::{self, Curve, Param};
use crate::farm::{self, Accepted, JobId, Shared, WireJob};
use crate::service::jobs::{Control, JobSpec};
use shape::{DistortionView, GridView, ShapeEdit};
use snapshots::{Render, Snapshot, SnapshotView, Snapshots};
use versions::{Edit, Origin, Stale, Versions};

mod bounds;
mod scenes;
mod shape;
mod snapshots;
mod versions;

/// Live frames' job ids start here (the store's ids are far below).
pub const LIVE_JOBS: JobId = 1 << 48;

/// Events a browser may fall behind by before it is disconnected.
const BROADCAST_CAPACITY: usize = 4096;

/// How long a high-quality frame's tile waits for others to go out with it.
const BATCH_EVERY: Duration = Duration::from_millis(100);

/// How often each browser is sent the workers and the job queue.
const STATUS_EVERY: Duration = Duration::from_millis(500);

/// How long the edits rest before the service draws the live scene at high
/// quality ([`Studio::rested`]).
pub const REST: Duration = Duration::from_millis(300);

/// One Server-Sent Event, encoded once for every browser.
#[derive(Debug)]
pub struct Event {
    name: &'static str,
    data: String,
}

/// A tile of a live frame as the farm accepted it.
struct RawTile {
    job: JobId,
    unit: usize,
    worker: String,
    pixels: Vec<u8>,
}

/// The frame rendering (or last rendered).
struct LiveFrame {
    job: JobId,
    generation: u64,
    units: Vec<WorkUnit>,
    /// Per unit: recorded yet.
    recorded: Vec<bool>,
    remaining: usize,
    started: Instant,
    /// Interactive or high.
    quality: Quality,
    /// The frame event and every tile event so far (for browsers that
    /// connect later).
    events: Vec<Arc<Event>>,
    /// The tiles' pixels in the order recorded (a tile event's `index`):
    /// what `GET /studio/tiles` serves.
    pixels: Vec<Arc<Vec<u8>>>,
    /// A high-quality frame's tile events not sent yet, and when they go.
    batch: Vec<serde_json::Value>,
    flush_at: Option<Instant>,
    /// Its scene, held while the frame is in the farm: the farm's checks
    /// and in-process workers render this one rather than build it again.
    _scene: Arc<hypertexture::Scene>,
}

/// What the studio shows.
struct Live {
    /// The scene text as loaded or edited (workers get this text).
    text: String,
    /// The knob values: every knob of the scene.
    knobs: BTreeMap<String, f64>,
    /// The text with the knob values as defaults (what Save writes).
    shown: String,
    /// The scene's knobs as declared.
    declared: BTreeMap<String, KnobDesc>,
    /// The last edit's error (the last good frame stays).
    error: Option<String>,
    /// The quality of the frame asked last.
    quality: Quality,
    /// The sliders of the text's numeric parameters, and its curves.
    params: Vec<Param>,
    curves: Vec<Curve>,
    /// The distortions (their fields and terms) and 2D transfer grids.
    distortions: Vec<DistortionView>,
    grids: Vec<GridView>,
    /// Each slider's range, kept while it moves.
    ranges: BTreeMap<String, (f64, f64)>,
    frame: Option<LiveFrame>,
    /// The interactive frame before `frame`, rendering to its end while
    /// `frame` waits behind it in the farm ([`Studio::retire`]).
    finishing: Option<LiveFrame>,
    generation: u64,
    /// The versions of the text and knob values (every tab's edits).
    versions: Versions,
    /// The frame of the sequence shown (what `frame` means in the scene).
    frame_number: u32,
    /// The named snapshots, with their images.
    snapshots: Snapshots,
    /// Why the shown scene's objects are cut by the march's bounds, if they are.
    warning: Option<String>,
}

/// The scene file the studio shows.
#[derive(Clone, Debug)]
struct Opened {
    /// The scene file opened (Save writes it), if any.
    path: Option<PathBuf>,
    /// The scene's name in messages.
    name: String,
    /// Where "render final" writes its images: `PREFIX.0001.png`,
    /// `PREFIX.0002.png`, … (the prefix is `DIR/STEM.final`).
    final_prefix: PathBuf,
}

impl Opened {
    /// The scene file at `path`, its final renders beside it.
    fn file(path: &Path) -> Opened {
        let stem = path
            .file_stem()
            .map_or_else(|| "scene".into(), |s| s.to_string_lossy().into_owned());
        let dir = match path.parent() {
            Some(d) if !d.as_os_str().is_empty() => d.to_path_buf(),
            _ => PathBuf::from("."),
        };
        let prefix = dir.join(format!("{stem}.final"));
        let prefix = std::path::absolute(&prefix).unwrap_or(prefix);
        Opened {
            path: Some(path.to_path_buf()),
            name: path.display().to_string(),
            final_prefix: prefix,
        }
    }
}

/// The studio of a service.
pub struct Studio {
    /// The scene shown (a leaf lock: taken after the live state's, and
    /// changed with it held).
    opened: Mutex<Opened>,
    /// The final renders handed out, by number: their files.
    finals: Mutex<BTreeMap<u32, PathBuf>>,
    /// The scenes of the browsed directory and their thumbnails (none when
    /// the studio browses no directory). Taken after the live state's lock,
    /// before the farm's.
    catalogue: Option<Mutex<scenes::Catalogue>>,
    /// The directory browsed, if any.
    root: Option<PathBuf>,
    /// Whether the page opens with the scene browser shown.
    browse_first: bool,
    live: Mutex<Live>,
    raw: mpsc::UnboundedSender<RawTile>,
    raw_rx: Mutex<Option<mpsc::UnboundedReceiver<RawTile>>>,
    events: broadcast::Sender<Arc<Event>>,
    farm: OnceLock<Arc<Shared>>,
    next_job: AtomicU64,
    token: Option<String>,
    /// The files the live text names.
    files: Mutex<Files>,
    /// The scene file's text as the studio last read or wrote it (`None`:
    /// no file there): Save does not write over a file changed since.
    on_disk: Mutex<Option<String>>,
}

/// A change asked by the page.
#[derive(Clone, Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Change {
    /// New scene text (knobs take its defaults); absent: the current text.
    #[serde(default)]
    pub text: Option<String>,
    /// Knob values (over the current text).
    #[serde(default)]
    pub knobs: BTreeMap<String, f64>,
    /// Numeric parameters by path ([`params::numbers`]), written into the
    /// text (the new one, or the current one).
    #[serde(default)]
    pub params: BTreeMap<String, f64>,
    /// Structural edits of the text (points added or deleted, words set),
    /// made after `params` on the text of version `base`: the edit is then
    /// that text's, merged like any text edit.
    #[serde(default)]
    pub edits: Vec<ShapeEdit>,
    /// `interactive` while a slider moves, `high` once it rests.
    pub quality: Quality,
    /// The version the edit was made on ([`SceneView`]'s `version`); absent:
    /// the current one. A stale edit is merged or refused as a conflict.
    #[serde(default)]
    pub base: Option<u64>,
    /// The tab that made it, echoed in the `scene` event so that the tab can
    /// tell its own edits from others'.
    #[serde(default)]
    pub tab: Option<String>,
    /// The gesture of the tab it belongs to (a slider's drag, an orbit, a
    /// burst of typing): the edits of one gesture are one undo step.
    #[serde(default)]
    pub gesture: Option<String>,
    /// The frame of the sequence to show; absent: the one shown.
    #[serde(default)]
    pub frame: Option<u32>,
    /// A preview, asked while a pointer holds a control: an interactive
    /// frame at half the width and height (a quarter of the pixels, drawn
    /// scaled up), so that a drag renders more of the values it passes
    /// through. The edits' rest draws the whole frame at high quality.
    #[serde(default)]
    pub preview: bool,
}

impl Change {
    /// Sets `text` (knob values as its defaults) at high quality, from `tab`,
    /// at `frame` (none: the frame shown): an edit of its own undo step.
    fn set_text(text: String, tab: Option<String>, frame: Option<u32>) -> Change {
        Change {
            text: Some(text),
            knobs: BTreeMap::new(),
            params: BTreeMap::new(),
            edits: Vec::new(),
            quality: Quality::High,
            base: None,
            tab,
            gesture: None,
            frame,
            preview: false,
        }
    }
}

/// A knob as the page shows it.
#[derive(Clone, Debug, Serialize)]
pub struct KnobView {
    name: String,
    value: f64,
    min: f64,
    max: f64,
    default: f64,
}

/// The scene browser as the page shows it.
#[derive(Clone, Debug, Serialize)]
pub struct BrowserView {
    /// The directory browsed.
    root: String,
    /// The page opens with the browser shown.
    first: bool,
    /// The scene shown, relative to `root` (none: not a file inside it).
    path: Option<String>,
}

/// The scene as the page shows it.
#[derive(Clone, Debug, Serialize)]
pub struct SceneView {
    name: String,
    /// Whether Save can write the file.
    savable: bool,
    /// The scene browser, when the studio browses a directory.
    browser: Option<BrowserView>,
    /// The text for the current knob values.
    text: String,
    knobs: Vec<KnobView>,
    /// A slider per numeric parameter of the object, modulations,
    /// distortion, camera, lights and shading.
    params: Vec<Param>,
    /// The curves, with their control points.
    curves: Vec<Curve>,
    /// The distortions: each one's vector field, and each term's operator
    /// and `enabled` switch.
    distortions: Vec<DistortionView>,
    /// The 2D shape transfer functions' grids.
    grids: Vec<GridView>,
    error: Option<String>,
    generation: u64,
    /// The version of the text and knob values shown.
    version: u64,
    /// The frame of the sequence shown.
    frame: u32,
    /// How many steps undo and redo can take (one history for every tab).
    undo: usize,
    redo: usize,
    snapshots: Vec<SnapshotView>,
    /// An object of the scene goes on past the march's bounds (cut flat).
    warning: Option<String>,
}

/// An error answered as `{"error": …}`.
struct Refused(StatusCode, String);

impl IntoResponse for Refused {
    fn into_response(self) -> Response {
        (self.0, Json(serde_json::json!({ "error": self.1 }))).into_response()
    }
}

/// Final render `number` of `prefix`: `PREFIX.NNNN.png`.
fn final_path(prefix: &Path, number: u32) -> PathBuf {
    let mut name = prefix.as_os_str().to_os_string();
    name.push(format!(".{number:04}.png"));
    PathBuf::from(name)
}

/// The highest N of the `PREFIX.N.png` files on disk (0: none).
fn highest_final(prefix: &Path) -> u32 {
    let (Some(dir), Some(stem)) = (prefix.parent(), prefix.file_name()) else {
        return 0;
    };
    let stem = format!("{}.", stem.to_string_lossy());
    u32::try_from(highest_numbered(dir, &stem, ".png")).unwrap_or(u32::MAX)
}

/// The highest N of the files `PREFIX N SUFFIX` in `dir` (0: none).
fn highest_numbered(dir: &Path, prefix: &str, suffix: &str) -> u64 {
    std::fs::read_dir(dir)
        .into_iter()
        .flatten()
        .flatten()
        .filter_map(|entry| {
            let file = entry.file_name();
            let number = file.to_str()?.strip_prefix(prefix)?.strip_suffix(suffix)?;
            number.parse::<u64>().ok()
        })
        .max()
        .unwrap_or(0)
}

/// Why Save wrote nothing.
enum SaveRefused {
    /// The file changed on disk since the studio read or wrote it.
    Changed(String),
    /// Anything else (no file open, the file system's error).
    Other(String),
}

/// The next numbered backup of `path`: `NAME.~N~`, N one past the highest
/// beside it.
fn next_backup(path: &Path) -> PathBuf {
    let name = path
        .file_name()
        .map_or_else(|| "scene".into(), |n| n.to_string_lossy().into_owned());
    let dir = match path.parent() {
        Some(d) if !d.as_os_str().is_empty() => d,
        _ => Path::new("."),
    };
    let prefix = format!("{name}.~");
    let highest = highest_numbered(dir, &prefix, "~");
    dir.join(format!("{prefix}{}~", highest + 1))
}

/// `text` with each knob's `default:` set to `values` (the knobs' map found
/// after `knobs:`); `None` when the text does not have that shape.
pub fn with_knob_values(text: &str, values: &BTreeMap<String, f64>) -> Option<String> {
    let knobs_at = find_field(text, "knobs")?;
    let mut edits: Vec<(usize, usize, String)> = Vec::new();
    for (name, value) in values {
        let quoted = format!("\"{name}\"");
        let at = knobs_at + text[knobs_at..].find(&quoted)?;
        let default_at = at + text[at..].find("default")?;
        let after = default_at + "default".len();
        let rest = &text[after..];
        let colon = rest.find(':')?;
        if !rest[..colon].trim().is_empty() {
            return None;
        }
        let start =
            after + colon + 1 + (rest[colon + 1..].len() - rest[colon + 1..].trim_start().len());
        let len = text[start..]
            .find(|c: char| !(c.is_ascii_digit() || matches!(c, '-' | '+' | '.' | 'e' | 'E')))
            .unwrap_or(text.len() - start);
        if len == 0 {
            return None;
        }
        // A number already of this value keeps its bytes (`0.50` stays).
        if text[start..start + len].parse::<f64>() == Ok(*value) {
            continue;
        }
        edits.push((start, start + len, format!("{value:?}")));
    }
    edits.sort_by_key(|e| std::cmp::Reverse(e.0));
    let mut out = text.to_string();
    for (start, end, with) in edits {
        out.replace_range(start..end, &with);
    }
    Some(out)
}

/// `text` with a change's parameters written in, its structural edits made
/// and its knob values written as the knobs' defaults: the text of an edit
/// that changes the scene's shape.
fn shaped(text: &str, change: &Change) -> Result<String, String> {
    let text = if change.params.is_empty() {
        text.to_string()
    } else {
        params::with_values(text, &change.params)?
    };
    let text = shape::apply(&text, &change.edits)?;
    Ok(with_knob_values(&text, &change.knobs).unwrap_or(text))
}

/// The byte offset just after `name:` as a field (not in a comment or a string).
fn find_field(text: &str, name: &str) -> Option<usize> {
    let mut from = 0;
    while let Some(i) = text[from..].find(name) {
        let at = from + i;
        let line_start = text[..at].rfind('\n').map_or(0, |n| n + 1);
        let before = &text[line_start..at];
        let after = text[at + name.len()..].trim_start();
        if !before.contains("//") && before.trim().is_empty() && after.starts_with(':') {
            return Some(at + name.len());
        }
        from = at + name.len();
    }
    None
}

/// A checked change: the scene built, its knobs and the text to show.
struct Checked {
    text: String,
    knobs: BTreeMap<String, f64>,
    declared: BTreeMap<String, KnobDesc>,
    shown: String,
    /// The scene, and the request the farm's workers get.
    built: hypertexture_proto::request::Built,
    /// The files the scene names, as the farm serves them to workers.
    files: Vec<farm::Asset>,
}

/// The files (meshes) a scene names, read beside the scene file the studio
/// opened, kept while the text names the same ones: a slider's change
/// neither reads them again nor rebuilds their meshes.
#[derive(Default)]
struct Files {
    /// The paths as the scene writes them, in the scene's order.
    paths: Vec<String>,
    /// Their meshes, for building the scene.
    assets: hypertexture::scene::Assets,
    /// Their bytes, for the workers.
    sent: Vec<farm::Asset>,
}

/// Makes `files` hold the files `text` names, read beside the scene file
/// `name`. A text that does not parse keeps the files: its build gives the
/// parse error.
fn load_files(text: &str, name: &str, files: &mut Files) -> Result<(), String> {
    let Ok(desc) = hypertexture::scene::parse(text, name) else {
        return Ok(());
    };
    let paths = desc.mesh_paths();
    if paths == files.paths {
        return Ok(());
    }
    let assets = hypertexture::scene::Assets::load(&desc, name, Default::default())
        .map_err(|e| e.to_string())?;
    let sent = farm::Asset::read_all(&assets.hashes(), name)?;
    *files = Files {
        paths,
        assets,
        sent,
    };
    Ok(())
}

/// The size a live frame is rendered at.
#[derive(Clone, Copy, Debug)]
enum Size {
    /// The scene's own.
    Scene,
    /// Half its width and height (rounded up): a preview.
    Half,
    /// This width and height (a thumbnail).
    Exactly(u32, u32),
}

/// Parses and builds `text` at `quality` with `knobs` (clamped to their
/// ranges; absent ones at their defaults): the CLI's parser and messages.
fn check(
    text: &str,
    name: &str,
    knobs: &BTreeMap<String, f64>,
    (quality, frame, size): (Quality, u32, Size),
    files: &Files,
) -> Result<Checked, String> {
    let desc = hypertexture::scene::parse(text, name).map_err(|e| e.to_string())?;
    let values: BTreeMap<String, f64> = desc
        .knobs
        .iter()
        .map(|(k, d)| {
            let v = knobs.get(k).copied().unwrap_or(d.default);
            let v = if v.is_finite() {
                v.clamp(d.min, d.max)
            } else {
                d.default
            };
            (k.clone(), v)
        })
        .collect();
    let (width, height) = match size {
        Size::Scene => (None, None),
        Size::Half => (
            Some(desc.image.width.div_ceil(2)),
            Some(desc.image.height.div_ceil(2)),
        ),
        Size::Exactly(w, h) => (Some(w), Some(h)),
    };
    let request = RenderRequest {
        overrides: Overrides {
            width,
            height,
            quality: Some(quality),
            knobs: overrides(&values, &desc.knobs),
            ..Overrides::default()
        },
        // A live frame is drawn in the page: 8-bit colour is all it needs.
        pixel_format: PixelFormat::Srgb8,
        frames: FrameRange::one(frame),
        ..RenderRequest::new(text, name)
    };
    // Only the files read beside the scene file are used: a scene whose
    // studio opened no file (or that names a file not beside it) is refused.
    let built = hypertexture_proto::request::build(&request, Some(&files.assets))
        .map_err(|e| e.to_string())?;
    let shown = with_knob_values(text, &values).unwrap_or_else(|| text.to_string());
    Ok(Checked {
        text: text.to_string(),
        knobs: values,
        declared: desc.knobs,
        shown,
        built,
        files: files.sent.clone(),
    })
}

/// The knobs whose value is not their default, as a request holds them
/// ([`Overrides::knob_list`]).
fn overrides(
    values: &BTreeMap<String, f64>,
    declared: &BTreeMap<String, KnobDesc>,
) -> Vec<(String, f64)> {
    Overrides::knob_list(
        values
            .iter()
            .filter(|(k, v)| declared.get(*k).is_none_or(|d| d.default != **v))
            .map(|(k, v)| (k.clone(), *v)),
    )
}

/// Puts the frame of `checked` on the farm as live job `job` of `units`, at
/// `priority`.
fn submit(
    shared: &Shared,
    checked: &Checked,
    (job, priority): (JobId, i32),
    units: Vec<WorkUnit>,
) -> Result<(), String> {
    let (width, height) = (checked.built.scene.width(), checked.built.scene.height());
    let frame_job = farm::FrameJob {
        request: checked.built.request.clone(),
        frames: vec![farm::FrameOut {
            frame: checked.built.request.frames.first,
            out: PathBuf::new(),
        }],
        // A live frame is drawn in the page, never written to a file.
        metadata: Arc::new(crate::image::output::ImageMetadata::without_scene(
            width, height, None, None,
        )),
        assets: checked.files.clone(),
    };
    shared
        .add_live_frame(
            (job, checked.built.request.frames.first, priority),
            units,
            (width, height),
            PixelFormat::Srgb8,
            WireJob::of(&frame_job),
        )
        .map_err(|e| e.to_string())
}

impl Studio {
    /// A studio of the scene at `path` (none: an empty editor), whose final
    /// renders go beside the scene (or into the working directory).
    pub fn new(path: Option<&Path>, data: &Path, token: Option<String>) -> Result<Studio, String> {
        let (text, opened) = match path {
            Some(p) => {
                let text = std::fs::read_to_string(p)
                    .map_err(|e| format!("{}: cannot read the scene: {e}", p.display()))?;
                (text, Opened::file(p))
            }
            // Without a scene, in the directory serve runs in (an output root).
            None => (
                String::new(),
                Opened {
                    path: None,
                    name: "scene.ron".to_string(),
                    final_prefix: std::path::absolute("studio.final")
                        .unwrap_or_else(|_| data.join("studio.final")),
                },
            ),
        };
        let text_read = text.clone();
        let (raw, raw_rx) = mpsc::unbounded_channel();
        Ok(Studio {
            opened: Mutex::new(opened),
            finals: Mutex::new(BTreeMap::new()),
            catalogue: None,
            root: None,
            browse_first: false,
            live: Mutex::new(Live {
                shown: text.clone(),
                text,
                knobs: BTreeMap::new(),
                declared: BTreeMap::new(),
                error: None,
                quality: Quality::High,
                params: Vec::new(),
                curves: Vec::new(),
                distortions: Vec::new(),
                grids: Vec::new(),
                ranges: BTreeMap::new(),
                frame: None,
                finishing: None,
                generation: 0,
                versions: Versions::new(&text_read),
                frame_number: 0,
                snapshots: Snapshots::default(),
                warning: None,
            }),
            raw,
            raw_rx: Mutex::new(Some(raw_rx)),
            events: broadcast::channel(BROADCAST_CAPACITY).0,
            farm: OnceLock::new(),
            next_job: AtomicU64::new(LIVE_JOBS),
            token,
            files: Mutex::new(Files::default()),
            on_disk: Mutex::new(path.map(|_| text_read)),
        })
    }

    /// The studio with a scene browser over the directory `root`; the page
    /// opens with it shown when `first`.
    pub fn browsing(self, root: PathBuf, first: bool) -> Studio {
        Studio {
            catalogue: Some(Mutex::new(scenes::Catalogue::new(root.clone()))),
            root: Some(root),
            browse_first: first,
            ..self
        }
    }

    fn opened(&self) -> Opened {
        self.opened
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .clone()
    }

    /// The message of the current text's error, if it has one (the same the
    /// page shows at its line and column).
    pub fn error(&self) -> Option<String> {
        self.live().error.clone()
    }

    fn live(&self) -> std::sync::MutexGuard<'_, Live> {
        self.live.lock().unwrap_or_else(|p| p.into_inner())
    }

    /// Whether `job` is a live frame of the studio.
    pub fn owns(&self, job: JobId) -> bool {
        job >= LIVE_JOBS
    }

    /// Connects the studio to the running farm: starts the recorder and, when
    /// a scene is open, its first frame at high quality.
    pub fn attach(self: &Arc<Self>, shared: Arc<Shared>) {
        let _ = self.farm.set(shared);
        if let Some(rx) = self.raw_rx.lock().unwrap_or_else(|p| p.into_inner()).take() {
            tokio::spawn(Arc::clone(self).record(rx));
        }
        // Started on a directory, the thumbnails start with the studio; on a
        // file, when the page first lists the scenes.
        if self.catalogue.is_some() && self.browse_first {
            let studio = Arc::clone(self);
            tokio::task::spawn_blocking(move || studio.scan_scenes());
        }
        let text = self.live().text.clone();
        if !text.is_empty() {
            let _ = self.change(Change {
                text: Some(text),
                knobs: BTreeMap::new(),
                params: BTreeMap::new(),
                edits: Vec::new(),
                quality: Quality::High,
                base: None,
                tab: None,
                gesture: None,
                frame: None,
                preview: false,
            });
        }
    }

    /// Hands a live frame's accepted tile to the recorder (called with the
    /// farm's state locked: a copy and a channel send).
    pub fn tile(&self, a: &Accepted, pixels: &[u8]) {
        let _ = self.raw.send(RawTile {
            job: a.job,
            unit: a.unit,
            worker: a.worker.clone(),
            pixels: pixels.to_vec(),
        });
    }

    /// A live frame is complete in the scheduler, or given up: it leaves it.
    pub fn leave(&self, job: JobId, gave_up: Option<String>) {
        if let Some(shared) = self.farm.get() {
            shared.remove_job(job);
        }
        if let Some(why) = gave_up {
            self.snapshot_gave_up(job, &why);
            self.thumbnail_gave_up(job, &why);
            self.send(Event {
                name: "error",
                data: serde_json::json!({ "error": why }).to_string(),
            });
        }
    }

    /// Takes the frames in flight out of the farm (the service is stopping).
    pub fn stop(&self) {
        let live = self.live();
        let jobs = [&live.frame, &live.finishing].map(|f| f.as_ref().map(|f| f.job));
        if let Some(shared) = self.farm.get() {
            for job in jobs.into_iter().flatten() {
                shared.remove_job(job);
            }
        }
    }

    fn send(&self, event: Event) -> Arc<Event> {
        let event = Arc::new(event);
        let _ = self.events.send(Arc::clone(&event));
        event
    }

    /// Records tiles as they come: makes each one's event once, keeps it for
    /// browsers that connect later and broadcasts it. A high-quality frame's
    /// tiles go out together, at most [`BATCH_EVERY`] after the first of them
    /// (one `tiles` event), and at once with its last tile.
    async fn record(self: Arc<Self>, mut rx: mpsc::UnboundedReceiver<RawTile>) {
        loop {
            let due = self.live().frame.as_ref().and_then(|f| f.flush_at);
            let raw = match due {
                Some(at) => tokio::select! {
                    raw = rx.recv() => raw,
                    () = tokio::time::sleep_until(at.into()) => {
                        if let Some(frame) = self.live().frame.as_mut() {
                            self.flush(frame);
                        }
                        continue;
                    }
                },
                None => rx.recv().await,
            };
            let Some(raw) = raw else {
                return;
            };
            let mut live = self.live();
            if self.snapshot_tile(&mut live, &raw) || self.thumbnail_tile(&raw) {
                continue;
            }
            let live = &mut *live;
            let frame = match (live.frame.as_mut(), live.finishing.as_mut()) {
                (Some(f), _) if f.job == raw.job => f,
                (_, Some(f)) if f.job == raw.job => f,
                _ => continue,
            };
            if frame.recorded.get(raw.unit) != Some(&false) {
                continue;
            }
            let unit = frame.units[raw.unit];
            frame.recorded[raw.unit] = true;
            frame.remaining -= 1;
            let mut data = serde_json::json!({
                "generation": frame.generation,
                "unit": raw.unit,
                "index": frame.pixels.len(),
                "bytes": raw.pixels.len(),
                "set": unit.set.index,
                "first_row": unit.first_row,
                "row_count": unit.row_count,
                "row_stride": unit.row_stride,
                "worker": raw.worker,
            });
            // An interactive frame is steered: its tiles carry their pixels,
            // drawn as they come. A high-quality one is watched while the
            // workers take the machine: its events are small, and the page
            // fetches the pixels when it draws (`GET /studio/tiles`).
            if frame.quality == Quality::Interactive {
                data["pixels"] = base64::engine::general_purpose::STANDARD
                    .encode(&raw.pixels)
                    .into();
                frame.pixels.push(Arc::new(raw.pixels));
                let event = self.send(Event {
                    name: "tile",
                    data: data.to_string(),
                });
                frame.events.push(event);
            } else {
                frame.pixels.push(Arc::new(raw.pixels));
                frame.batch.push(data);
                frame
                    .flush_at
                    .get_or_insert_with(|| Instant::now() + BATCH_EVERY);
            }
            if frame.remaining == 0 {
                self.flush(frame);
                let data = serde_json::json!({
                    "generation": frame.generation,
                    "seconds": frame.started.elapsed().as_secs_f64(),
                });
                let event = self.send(Event {
                    name: "done",
                    data: data.to_string(),
                });
                frame.events.push(event);
            }
            if live.finishing.as_ref().is_some_and(|f| f.remaining == 0) {
                live.finishing = None;
            }
        }
    }

    /// Sends the frame's tiles waiting in its batch as one `tiles` event.
    fn flush(&self, frame: &mut LiveFrame) {
        frame.flush_at = None;
        if frame.batch.is_empty() {
            return;
        }
        let data = serde_json::json!({
            "generation": frame.generation,
            "tiles": std::mem::take(&mut frame.batch),
        });
        let event = self.send(Event {
            name: "tiles",
            data: data.to_string(),
        });
        frame.events.push(event);
    }

    /// Applies a change from the page: the text is parsed and built; when it
    /// is good, the frame in flight leaves the farm and the new one starts.
    /// The error (with line:column) is the CLI's.
    pub fn change(&self, change: Change) -> Result<SceneView, String> {
        let mut live = self.live();
        self.change_live(&mut live, change)
    }

    /// A tab's edit: made on its `base` version, merged onto the current one
    /// (409 when another tab changed the same value since), then applied.
    fn edit(&self, change: Change) -> Result<SceneView, Refused> {
        let mut live = self.live();
        let conflict = |stale| match stale {
            Stale::Conflict(why) => Refused(StatusCode::CONFLICT, why),
            Stale::Unknown(why) => Refused(StatusCode::CONFLICT, why),
        };
        let edit = if change.edits.is_empty() {
            Edit {
                text: change.text.clone(),
                knobs: change.knobs.clone(),
                params: change.params.clone(),
            }
        } else {
            let base = live.versions.at(change.base).map_err(conflict)?;
            let text = shaped(change.text.as_deref().unwrap_or(&base.shown), &change)
                .map_err(|e| Refused(StatusCode::BAD_REQUEST, e))?;
            Edit {
                text: Some(text),
                ..Edit::default()
            }
        };
        let edit = live.versions.rebase(change.base, edit).map_err(conflict)?;
        let change = Change {
            text: edit.text,
            knobs: edit.knobs,
            params: edit.params,
            edits: Vec::new(),
            base: None,
            ..change
        };
        self.change_live(&mut live, change)
            .map_err(|e| Refused(StatusCode::BAD_REQUEST, e))
    }

    /// Once the edits have rested for [`REST`]: if frame `generation` is
    /// still the live one and was drawn at interactive quality, the same
    /// scene is drawn at high quality. The service does this itself, so a
    /// tab closed or reloaded within the rest still leaves every viewer the
    /// high-quality frame.
    pub fn rested(&self, generation: u64) {
        let mut live = self.live();
        if live.generation != generation
            || live.quality != Quality::Interactive
            || live.error.is_some()
        {
            return;
        }
        let change = Change {
            text: None,
            knobs: live.knobs.clone(),
            params: BTreeMap::new(),
            edits: Vec::new(),
            quality: Quality::High,
            base: None,
            tab: None,
            gesture: None,
            frame: None,
            preview: false,
        };
        if let Err(e) = self.change_live(&mut live, change) {
            tracing::warn!("the high-quality frame of {}: {e}", self.opened().name);
        }
    }

    /// [`Studio::change`] on the live state, locked by the caller.
    fn change_live(&self, live: &mut Live, change: Change) -> Result<SceneView, String> {
        let origin = Origin::Edit {
            tab: change.tab.clone(),
            gesture: change.gesture.clone(),
        };
        self.apply(live, change, origin)
    }

    /// [`Studio::change_live`] of a state made by `origin` (an edit, an undo
    /// or a redo: see [`versions`]).
    fn apply(&self, live: &mut Live, change: Change, origin: Origin) -> Result<SceneView, String> {
        let shared = self
            .farm
            .get()
            .ok_or_else(|| "the farm is starting".to_string())?;
        let checked = match self.check_change(live, &change) {
            Ok(c) => c,
            Err(e) => {
                live.error = Some(e.clone());
                return Err(e);
            }
        };
        let frame_number = checked.built.request.frames.first;
        let same = live.frame.is_some()
            && live.text == checked.text
            && live.knobs == checked.knobs
            && live.quality == change.quality
            && live.frame_number == frame_number;
        live.error = None;
        if !same {
            self.start_frame(shared, live, &checked, (change.quality, change.preview))?;
            live.warning = bounds::warning(&checked.built.scene, frame_number);
        }
        live.frame_number = frame_number;
        live.text = checked.text;
        live.knobs = checked.knobs;
        live.shown = checked.shown;
        live.declared = checked.declared;
        live.quality = change.quality;
        let Live {
            text,
            ranges,
            params,
            curves,
            ..
        } = live;
        (*params, *curves) = params::controls(text, ranges);
        (live.distortions, live.grids) = shape::looks(&live.text);
        let view = self.view(live);
        if live.versions.record_as(&live.shown, &live.knobs, origin) {
            let view = self.view(live);
            self.send(Event {
                name: "scene",
                data: serde_json::json!({ "tab": change.tab, "view": view }).to_string(),
            });
            return Ok(view);
        }
        Ok(view)
    }

    /// The scene `change` asks for, built: its new text (knobs at their
    /// defaults) or the live text with its knobs, with its parameters
    /// written in.
    fn check_change(&self, live: &Live, change: &Change) -> Result<Checked, String> {
        let (text, knobs) = match &change.text {
            Some(text) => (text.clone(), BTreeMap::new()),
            None => (live.text.clone(), change.knobs.clone()),
        };
        let text = if change.params.is_empty() {
            text
        } else {
            params::with_values(&text, &change.params)?
        };
        let mut files = self.files.lock().unwrap_or_else(|p| p.into_inner());
        let name = self.read_files(&text, &mut files)?;
        let frame = change.frame.unwrap_or(live.frame_number);
        let size = if change.preview && change.quality == Quality::Interactive {
            Size::Half
        } else {
            Size::Scene
        };
        check(&text, &name, &knobs, (change.quality, frame, size), &files)
    }

    /// Makes `files` hold the files `text` names, read beside the opened
    /// scene file (nothing when the studio opened none); answers the scene's
    /// name.
    fn read_files(&self, text: &str, files: &mut Files) -> Result<String, String> {
        let opened = self.opened();
        if opened.path.is_some() {
            load_files(text, &opened.name, files)?;
        }
        Ok(opened.name)
    }

    /// Takes the frame in flight off the farm and puts the frame of
    /// `checked` on it, telling the page its size and units.
    fn start_frame(
        &self,
        shared: &Arc<Shared>,
        live: &mut Live,
        checked: &Checked,
        (quality, preview): (Quality, bool),
    ) -> Result<(), String> {
        Self::retire(shared, live, quality);
        live.generation += 1;
        let job = self.next_job.fetch_add(1, Ordering::Relaxed);
        let (interleave, expected) = shared.unit_layout();
        let (width, height) = (checked.built.scene.width(), checked.built.scene.height());
        let units = farm_units(width, height, interleave, expected);
        let frame_units = units.clone();
        let data = serde_json::json!({
            "generation": live.generation,
            "width": width,
            "height": height,
            "interleave": interleave,
            "units": units.len(),
            "quality": quality,
            "preview": preview && quality == Quality::Interactive,
            "frame": checked.built.request.frames.first,
        });
        let event = self.send(Event {
            name: "frame",
            data: data.to_string(),
        });
        live.frame = Some(LiveFrame {
            job,
            generation: live.generation,
            recorded: vec![false; units.len()],
            remaining: units.len(),
            units,
            started: Instant::now(),
            quality,
            events: vec![event],
            pixels: Vec::new(),
            batch: Vec::new(),
            flush_at: None,
            _scene: Arc::clone(&checked.built.scene),
        });
        submit(shared, checked, (job, farm::LIVE_PRIORITY), frame_units)
    }

    /// Takes the frames in flight out of the farm before a frame of
    /// `quality` starts, but for a steered one: an interactive frame that an
    /// interactive one follows renders to its end, and the new frame waits
    /// behind it in the farm (the scheduler serves ties oldest first). So
    /// the workers go from one frame of a drag to the next without waiting
    /// for the page, and a frame the page has begun to draw is drawn whole.
    /// One frame at most finishes so, the newest one begun: a frame that
    /// never began gives its place to the new one, and one older than a
    /// frame begun (the page draws the newer) leaves the farm.
    fn retire(shared: &Shared, live: &mut Live, quality: Quality) {
        let before = live.finishing.take().filter(|f| f.remaining > 0);
        let old = live.frame.take().filter(|f| f.remaining > 0);
        let steered = quality == Quality::Interactive
            && old
                .as_ref()
                .is_some_and(|f| f.quality == Quality::Interactive);
        let (keep, leave) = match (steered, old, before) {
            (false, old, before) => (None, [old, before]),
            (true, old, None) => (old, [None, None]),
            (true, Some(old), Some(before)) if old.remaining < old.units.len() => {
                (Some(old), [Some(before), None])
            }
            (true, old, before) => (before, [old, None]),
        };
        live.finishing = keep;
        for frame in leave.into_iter().flatten() {
            shared.remove_job(frame.job);
        }
    }

    fn view(&self, live: &Live) -> SceneView {
        let opened = self.opened();
        let browser = self.root.as_ref().map(|root| BrowserView {
            root: root.display().to_string(),
            first: self.browse_first,
            path: opened
                .path
                .as_deref()
                .and_then(|p| {
                    // `studio fur.ron` browses `.`, and names the file without it.
                    let here = root.as_os_str() == "." && p.is_relative();
                    p.strip_prefix(root).ok().or(here.then_some(p))
                })
                .map(|p| p.to_string_lossy().replace('\\', "/")),
        });
        SceneView {
            name: opened.name,
            savable: opened.path.is_some(),
            browser,
            text: live.shown.clone(),
            knobs: live
                .declared
                .iter()
                .map(|(name, d)| KnobView {
                    name: name.clone(),
                    value: live.knobs.get(name).copied().unwrap_or(d.default),
                    min: d.min,
                    max: d.max,
                    default: d.default,
                })
                .collect(),
            params: live.params.clone(),
            curves: live.curves.clone(),
            distortions: live.distortions.clone(),
            grids: live.grids.clone(),
            error: live.error.clone(),
            generation: live.generation,
            version: live.versions.current().number,
            frame: live.frame_number,
            undo: live.versions.steps().0,
            redo: live.versions.steps().1,
            snapshots: live.snapshots.views(),
            warning: live.warning.clone(),
        }
    }

    /// Writes the shown text to the scene file. The file's text before goes
    /// to the next numbered backup (`SCENE.~1~`, `SCENE.~2~`, …); a save that
    /// changes nothing writes nothing. Unless `over`, a file changed on disk
    /// since the studio read or wrote it is refused ([`SaveRefused::Changed`]).
    fn save(&self, over: bool) -> Result<String, SaveRefused> {
        // The text and its file, together (an open switches both).
        let (text, path) = {
            let live = self.live();
            (live.shown.clone(), self.opened().path)
        };
        let path = path.ok_or_else(|| {
            SaveRefused::Other(
                "no scene file is open (start with `coordinator studio SCENE`)".to_string(),
            )
        })?;
        let path = &path;
        let mut known = self.on_disk.lock().unwrap_or_else(|p| p.into_inner());
        let disk = match std::fs::read_to_string(path) {
            Ok(t) => Some(t),
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => None,
            Err(e) => return Err(SaveRefused::Other(format!("{}: {e}", path.display()))),
        };
        if !over && disk != *known {
            return Err(SaveRefused::Changed(format!(
                "{} changed on disk since the studio read or wrote it: Reload takes the file's \
                 text, Save over it writes the studio's (the file's text is kept as a backup)",
                path.display()
            )));
        }
        if disk.as_deref() == Some(text.as_str()) {
            *known = disk;
            return Ok(format!("{} is saved", path.display()));
        }
        let io = |p: &Path, e: std::io::Error| SaveRefused::Other(format!("{}: {e}", p.display()));
        let backup = match &disk {
            Some(before) => {
                let backup = next_backup(path);
                std::fs::write(&backup, before).map_err(|e| io(&backup, e))?;
                Some(backup)
            }
            None => None,
        };
        let mut tmp = path.as_os_str().to_os_string();
        tmp.push(".tmp");
        let tmp = PathBuf::from(tmp);
        std::fs::write(&tmp, &text).map_err(|e| io(&tmp, e))?;
        std::fs::rename(&tmp, path).map_err(|e| io(path, e))?;
        *known = Some(text);
        Ok(match backup {
            Some(b) => format!(
                "saved {} (the file before is {})",
                path.display(),
                b.display()
            ),
            None => format!("saved {}", path.display()),
        })
    }

    /// The job of "render final": the shown text at the scene's own size,
    /// quality and samples, into the next free `PREFIX.NNNN.png` (past every
    /// one on disk and every one handed out), with that number.
    fn final_job(&self) -> (JobSpec, u32) {
        let (shown, opened) = {
            let live = self.live();
            (live.shown.clone(), self.opened())
        };
        let mut finals = self.finals.lock().unwrap_or_else(|p| p.into_inner());
        let last = finals.keys().next_back().copied().unwrap_or(0);
        let number = last.max(highest_final(&opened.final_prefix)) + 1;
        let out = final_path(&opened.final_prefix, number);
        finals.insert(number, out.clone());
        let spec = JobSpec {
            request: RenderRequest::new(shown, opened.name),
            out: out.display().to_string(),
            priority: 0,
            require_tags: Vec::new(),
        };
        (spec, number)
    }

    /// The bytes of final render `number`, once handed out and written.
    fn final_png(&self, number: u32) -> Result<Vec<u8>, Refused> {
        let path = self
            .finals
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .get(&number)
            .cloned()
            .ok_or_else(|| Refused(StatusCode::NOT_FOUND, format!("no final render {number}")))?;
        std::fs::read(&path)
            .map_err(|e| Refused(StatusCode::NOT_FOUND, format!("{}: {e}", path.display())))
    }

    /// Takes the scene file's text from disk, as an edit of the text.
    fn reload(&self) -> Result<SceneView, String> {
        // The file and the text it replaces, together (an open switches both).
        let mut live = self.live();
        let path = self.opened().path;
        let path = path.as_ref().ok_or_else(|| {
            "no scene file is open (start with `coordinator studio SCENE`)".to_string()
        })?;
        let text = std::fs::read_to_string(path)
            .map_err(|e| format!("{}: cannot read the scene: {e}", path.display()))?;
        let mut known = self.on_disk.lock().unwrap_or_else(|p| p.into_inner());
        let view = self.change_live(
            &mut live,
            Change {
                text: Some(text.clone()),
                knobs: BTreeMap::new(),
                params: BTreeMap::new(),
                edits: Vec::new(),
                quality: Quality::High,
                base: None,
                tab: None,
                gesture: None,
                frame: None,
                preview: false,
            },
        )?;
        *known = Some(text);
        Ok(view)
    }

    /// The events of the frame so far, and a receiver of those to come (taken
    /// under one lock: none is missed or sent twice).
    /// The pixels of the tiles of `range`, one after another: 410 when its
    /// frame is no longer the current one, 400 past the tiles recorded.
    fn tile_pixels(&self, range: &TileRange) -> Result<Vec<u8>, Refused> {
        let parts: Vec<Arc<Vec<u8>>> = {
            let live = self.live();
            let frame = live
                .frame
                .as_ref()
                .filter(|f| f.generation == range.generation)
                .ok_or_else(|| {
                    Refused(
                        StatusCode::GONE,
                        format!("frame {} is no longer the current one", range.generation),
                    )
                })?;
            if range.from > range.to || range.to > frame.pixels.len() {
                return Err(Refused(
                    StatusCode::BAD_REQUEST,
                    format!(
                        "tiles {}..{}: frame {} has {} tiles so far",
                        range.from,
                        range.to,
                        range.generation,
                        frame.pixels.len()
                    ),
                ));
            }
            frame.pixels[range.from..range.to].to_vec()
        };
        let mut body = Vec::with_capacity(parts.iter().map(|p| p.len()).sum());
        for p in &parts {
            body.extend_from_slice(p);
        }
        Ok(body)
    }

    fn subscribe(&self) -> (Vec<Arc<Event>>, broadcast::Receiver<Arc<Event>>) {
        let live = self.live();
        let rx = self.events.subscribe();
        let backlog = live
            .frame
            .as_ref()
            .map(|f| f.events.clone())
            .unwrap_or_default();
        (backlog, rx)
    }
}

/// Undo, redo and snapshots ([`versions`], [`snapshots`]).
impl Studio {
    /// Undo (`back`) or redo: the text and values set to the state of the
    /// step, byte for byte, at high quality, as a new version every tab
    /// follows. 409 when there is no step to take.
    fn step(&self, back: bool, tab: Option<String>) -> Result<SceneView, Refused> {
        let mut live = self.live();
        let (target, origin, what) = if back {
            (live.versions.undo_to(), Origin::Undo, "undo")
        } else {
            (live.versions.redo_to(), Origin::Redo, "redo")
        };
        let target = target
            .cloned()
            .ok_or_else(|| Refused(StatusCode::CONFLICT, format!("nothing to {what}")))?;
        // The shown text holds the knob values as defaults: set back, it
        // gives the same values and the same text.
        let change = Change::set_text(target.shown, tab, None);
        self.apply(&mut live, change, origin)
            .map_err(|e| Refused(StatusCode::BAD_REQUEST, format!("cannot {what}: {e}")))
    }

    /// A snapshot named `name` of the state shown; its image is put on the
    /// farm at high quality. Answers every snapshot.
    fn take_snapshot(&self, name: &str) -> Result<Vec<SnapshotView>, Refused> {
        let bad = |e: String| Refused(StatusCode::BAD_REQUEST, e);
        let shared = self
            .farm
            .get()
            .ok_or_else(|| bad("the farm is starting".into()))?;
        let mut live = self.live();
        let name = live.snapshots.check_name(name).map_err(bad)?;
        let checked = {
            let mut files = self.files.lock().unwrap_or_else(|p| p.into_inner());
            let name = self.read_files(&live.text, &mut files).map_err(bad)?;
            let at = (Quality::High, live.frame_number, Size::Scene);
            check(&live.text, &name, &live.knobs, at, &files).map_err(bad)?
        };
        let job = self.next_job.fetch_add(1, Ordering::Relaxed);
        let (interleave, expected) = shared.unit_layout();
        let (width, height) = (checked.built.scene.width(), checked.built.scene.height());
        let units = farm_units(width, height, interleave, expected);
        let render = Render::new(
            job,
            units.clone(),
            (width, height, interleave),
            Arc::clone(&checked.built.scene),
        );
        submit(shared, &checked, (job, farm::LIVE_PRIORITY), units).map_err(bad)?;
        let snapshot = Snapshot {
            id: 0,
            name,
            version: live.versions.current().number,
            shown: live.shown.clone(),
            frame: live.frame_number,
            render,
        };
        live.snapshots.add(snapshot);
        Ok(self.send_snapshots(&live))
    }

    /// Sends every tab the snapshots (a `snapshots` event); returns them.
    fn send_snapshots(&self, live: &Live) -> Vec<SnapshotView> {
        let views = live.snapshots.views();
        self.send(Event {
            name: "snapshots",
            data: serde_json::json!({ "snapshots": views }).to_string(),
        });
        views
    }

    /// Sets snapshot `id`'s text and frame back, as an edit of its own step.
    fn restore(&self, id: u64, tab: Option<String>) -> Result<SceneView, Refused> {
        let mut live = self.live();
        let snapshot = live
            .snapshots
            .get(id)
            .ok_or_else(|| Refused(StatusCode::NOT_FOUND, format!("no snapshot {id}")))?;
        let change = Change::set_text(snapshot.shown.clone(), tab, Some(snapshot.frame));
        self.change_live(&mut live, change)
            .map_err(|e| Refused(StatusCode::BAD_REQUEST, e))
    }

    /// Snapshot `id`'s image, once rendered.
    fn snapshot_pixels(&self, id: u64) -> Result<Arc<Vec<u8>>, Refused> {
        let live = self.live();
        let snapshot = live
            .snapshots
            .get(id)
            .ok_or_else(|| Refused(StatusCode::NOT_FOUND, format!("no snapshot {id}")))?;
        snapshot.render.pixels().cloned().ok_or_else(|| {
            Refused(
                StatusCode::CONFLICT,
                format!("snapshot {id} (`{}`) is still rendering", snapshot.name),
            )
        })
    }

    /// Stores `raw` when it is a tile of a snapshot's image; returns whether
    /// it was. The tab learns that an image is whole by a `snapshots` event.
    fn snapshot_tile(&self, live: &mut Live, raw: &RawTile) -> bool {
        let Some(snapshot) = live.snapshots.rendered_by(raw.job) else {
            return false;
        };
        if snapshot.render.store(raw.unit, &raw.pixels) {
            self.send_snapshots(live);
        }
        true
    }

    /// The farm gave job `job` up: if it rendered a snapshot, its list says why.
    fn snapshot_gave_up(&self, job: JobId, why: &str) {
        let mut live = self.live();
        if let Some(snapshot) = live.snapshots.rendered_by(job) {
            snapshot.render.fail(why.to_string());
            self.send_snapshots(&live);
        }
    }
}

/// The first scene (in path order) under `dir`, relative to it.
pub fn first_scene(dir: &Path) -> Option<String> {
    scenes::list(dir).into_iter().next()
}

/// Thumbnails go to the farm below the live frames: they never slow
/// steering.
const THUMBNAIL_PRIORITY: i32 = farm::LIVE_PRIORITY - 1;

/// `POST /studio/open`'s body.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct OpenScene {
    /// The scene's path relative to the browsed directory.
    path: String,
    /// The version the page showed; absent: the current one.
    #[serde(default)]
    base: Option<u64>,
    /// Open even when the shown scene has unsaved edits (they are lost).
    #[serde(default)]
    discard: bool,
    /// The tab that asked (echoed in the `scene` event).
    #[serde(default)]
    tab: Option<String>,
}

/// The scene browser ([`scenes`]).
impl Studio {
    fn catalogue(&self) -> Result<std::sync::MutexGuard<'_, scenes::Catalogue>, Refused> {
        let catalogue = self.catalogue.as_ref().ok_or_else(|| {
            Refused(
                StatusCode::NOT_FOUND,
                "the studio browses no directory (start it with `coordinator studio DIR`)"
                    .to_string(),
            )
        })?;
        Ok(catalogue.lock().unwrap_or_else(|p| p.into_inner()))
    }

    /// Lists the browsed directory's scenes again (read without a lock) and
    /// puts the thumbnails of contents not seen before on the farm.
    fn scan_scenes(&self) -> Result<Vec<scenes::SceneEntry>, Refused> {
        let root = self.catalogue()?.root().to_path_buf();
        let found = scenes::read(&root);
        let start = self.catalogue()?.update(found);
        for (text, name, key) in start {
            let Some(shared) = self.farm.get() else {
                self.catalogue()?.not_started(key);
                continue;
            };
            let built = self.thumbnail_job(shared, &text, &name);
            let mut catalogue = self.catalogue()?;
            let render = built.and_then(|(checked, units, render)| {
                let job = (render.job, THUMBNAIL_PRIORITY);
                submit(shared, &checked, job, units).map(|()| render)
            });
            catalogue.started(key, render);
        }
        Ok(self.catalogue()?.entries())
    }

    /// The thumbnail's frame of scene `text` (named `name`, its files read
    /// beside it): built at interactive quality within [`scenes::THUMB`]
    /// pixels, its units and its render.
    fn thumbnail_job(
        &self,
        shared: &Shared,
        text: &str,
        name: &str,
    ) -> Result<(Checked, Vec<WorkUnit>, Render), String> {
        let desc = hypertexture::scene::parse(text, name).map_err(|e| e.to_string())?;
        let size = scenes::thumbnail_size(desc.image.width, desc.image.height);
        let mut files = Files::default();
        load_files(text, name, &mut files)?;
        let at = (Quality::Interactive, 0, Size::Exactly(size.0, size.1));
        let checked = check(text, name, &BTreeMap::new(), at, &files)?;
        let job = self.next_job.fetch_add(1, Ordering::Relaxed);
        let (interleave, expected) = shared.unit_layout();
        let (width, height) = (checked.built.scene.width(), checked.built.scene.height());
        let units = farm_units(width, height, interleave, expected);
        let render = Render::new(
            job,
            units.clone(),
            (width, height, interleave),
            Arc::clone(&checked.built.scene),
        );
        Ok((checked, units, render))
    }

    /// Stores `raw` when it is a tile of a thumbnail; returns whether it
    /// was. Every tab learns that a thumbnail is ready by a `scenes` event.
    fn thumbnail_tile(&self, raw: &RawTile) -> bool {
        let Some(catalogue) = &self.catalogue else {
            return false;
        };
        let stored = catalogue.lock().unwrap_or_else(|p| p.into_inner()).store(
            raw.job,
            raw.unit,
            &raw.pixels,
        );
        match stored {
            None => false,
            Some(ready) => {
                if ready {
                    self.send_scenes_changed();
                }
                true
            }
        }
    }

    fn thumbnail_gave_up(&self, job: JobId, why: &str) {
        let Some(catalogue) = &self.catalogue else {
            return;
        };
        let failed = catalogue
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .fail(job, why);
        if failed {
            self.send_scenes_changed();
        }
    }

    fn send_scenes_changed(&self) {
        self.send(Event {
            name: "scenes",
            data: "{}".to_string(),
        });
    }

    /// Scene `path`'s thumbnail (PNG): 400 for a path outside the browsed
    /// directory, 404 for one not listed or a scene without a thumbnail
    /// (its error), 409 while it renders.
    fn thumbnail(&self, path: &str) -> Result<Arc<Vec<u8>>, Refused> {
        let catalogue = self.catalogue()?;
        if let Err(scenes::Bad::Outside(why)) = scenes::confine(catalogue.root(), path) {
            return Err(Refused(StatusCode::BAD_REQUEST, why));
        }
        catalogue.thumbnail(path).map_err(|(listed, why)| {
            let rendering = listed && why.ends_with("still rendering");
            let code = if rendering {
                StatusCode::CONFLICT
            } else {
                StatusCode::NOT_FOUND
            };
            Refused(code, why)
        })
    }

    /// Makes scene `ask.path` of the browsed directory the live scene: its
    /// text, a new frame, a history and snapshots of its own (those of the
    /// scene before are dropped), and every tab follows. Refused: a path
    /// outside the directory (400), no such scene (404), a page on an older
    /// version or unsaved edits of the shown scene unless `discard` (409).
    fn open(&self, ask: &OpenScene) -> Result<SceneView, Refused> {
        let root = self.catalogue()?.root().to_path_buf();
        let path = scenes::confine(&root, &ask.path).map_err(|bad| match bad {
            scenes::Bad::Outside(why) => Refused(StatusCode::BAD_REQUEST, why),
            scenes::Bad::Missing(why) => Refused(StatusCode::NOT_FOUND, why),
        })?;
        let text = std::fs::read_to_string(&path).map_err(|e| {
            Refused(
                StatusCode::NOT_FOUND,
                format!("{}: cannot read the scene: {e}", path.display()),
            )
        })?;
        let mut live = self.live();
        let now = live.versions.current().number;
        if let Some(base) = ask.base.filter(|&b| b != now) {
            return Err(Refused(
                StatusCode::CONFLICT,
                format!(
                    "the page shows version {base} and the studio is at version {now}: \
                     look at the current scene before opening another"
                ),
            ));
        }
        if !ask.discard {
            self.unsaved(&live)?;
        }
        *self.opened.lock().unwrap_or_else(|p| p.into_inner()) = Opened::file(&path);
        *self.on_disk.lock().unwrap_or_else(|p| p.into_inner()) = Some(text.clone());
        *self.files.lock().unwrap_or_else(|p| p.into_inner()) = Files::default();
        self.forget(&mut live, &text);
        let mut change = Change::set_text(text, ask.tab.clone(), Some(0));
        change.quality = Quality::Interactive;
        // A scene that does not build opens all the same: its error shows.
        if let Err(e) = self.change_live(&mut live, change) {
            tracing::info!("opened {}: {e}", path.display());
        }
        let view = self.view(&live);
        self.send(Event {
            name: "scene",
            data: serde_json::json!({ "tab": ask.tab, "view": view }).to_string(),
        });
        Ok(view)
    }

    /// 409 when the shown text differs from its file on disk.
    fn unsaved(&self, live: &Live) -> Result<(), Refused> {
        let opened = self.opened();
        let Some(path) = &opened.path else {
            return Ok(());
        };
        if std::fs::read_to_string(path).ok().as_deref() == Some(live.shown.as_str()) {
            return Ok(());
        }
        let name = path
            .file_name()
            .map_or_else(|| opened.name.clone(), |n| n.to_string_lossy().into_owned());
        Err(Refused(
            StatusCode::CONFLICT,
            format!(
                "unsaved edits to {name}: save them first, or open the other scene discarding \
                 them"
            ),
        ))
    }

    /// Clears what belongs to the scene shown before an open: its frame
    /// (off the farm), its undo history, its snapshots (their renders off
    /// the farm), its controls and its sliders' ranges. The text becomes
    /// `text`, at frame 0.
    fn forget(&self, live: &mut Live, text: &str) {
        if let Some(shared) = self.farm.get() {
            let frame = live.frame.take().map(|f| f.job);
            for job in frame.into_iter().chain(live.snapshots.jobs()) {
                shared.remove_job(job);
            }
        }
        live.frame = None;
        live.snapshots.clear();
        live.versions.restart(text);
        live.text = text.to_string();
        live.shown = text.to_string();
        live.knobs.clear();
        live.declared.clear();
        live.error = None;
        live.params.clear();
        live.curves.clear();
        live.distortions.clear();
        live.grids.clear();
        live.ranges.clear();
        live.frame_number = 0;
        live.warning = None;
    }
}

/// The router's state.
#[derive(Clone)]
struct Ctx {
    studio: Arc<Studio>,
    control: Arc<dyn Control>,
}

/// The studio's routes: the page, its files, and its data routes (behind the
/// token: see [`check_token`]).
pub fn router(studio: Arc<Studio>, control: Arc<dyn Control>) -> Router {
    let ctx = Ctx { studio, control };
    let data = Router::new()
        .route(
            "/studio/scene",
            axum::routing::get(get_scene).post(post_scene),
        )
        .route("/studio/save", axum::routing::post(save))
        .route("/studio/reload", axum::routing::post(reload))
        .route("/studio/final", axum::routing::post(render_final))
        .route("/studio/final/{number}", axum::routing::get(final_png))
        .route("/studio/events", axum::routing::get(events))
        .route("/studio/tiles", axum::routing::get(tiles))
        .route("/studio/undo", axum::routing::post(undo))
        .route("/studio/redo", axum::routing::post(redo))
        .route("/studio/snapshots", axum::routing::post(take_snapshot))
        .route(
            "/studio/snapshots/{id}/restore",
            axum::routing::post(restore_snapshot),
        )
        .route(
            "/studio/snapshots/{id}/pixels",
            axum::routing::get(snapshot_pixels),
        )
        .route("/studio/scenes", axum::routing::get(list_scenes))
        .route("/studio/scenes/thumbnail", axum::routing::get(thumbnail))
        .route("/studio/open", axum::routing::post(open_scene))
        .layer(middleware::from_fn_with_state(ctx.clone(), check_token));
    Router::new()
        .route("/", axum::routing::get(page))
        .route("/studio/studio.js", axum::routing::get(script))
        .route("/studio/studio.css", axum::routing::get(style))
        .merge(data)
        .with_state(ctx)
}

async fn page() -> Response {
    static_file(
        "text/html; charset=utf-8",
        include_str!("../../../studio/index.html"),
    )
}

async fn script() -> Response {
    static_file(
        "text/javascript; charset=utf-8",
        include_str!("../../../studio/studio.js"),
    )
}

async fn style() -> Response {
    static_file(
        "text/css; charset=utf-8",
        include_str!("../../../studio/studio.css"),
    )
}

fn static_file(content_type: &'static str, body: &'static str) -> Response {
    (
        [
            (header::CONTENT_TYPE, content_type),
            (header::CACHE_CONTROL, "no-cache"),
        ],
        body,
    )
        .into_response()
}

/// Refuses a data route without the token (401): it comes in
/// `Authorization: Bearer <token>`, or for `GET /studio/events` alone in
/// `?token=<token>` ([`crate::guard::admits`]).
async fn check_token(State(ctx): State<Ctx>, request: Request, next: Next) -> Response {
    let Some(token) = &ctx.studio.token else {
        return next.run(request).await;
    };
    if crate::guard::admits(
        request.method(),
        request.uri(),
        request.headers(),
        token.as_bytes(),
    ) {
        return next.run(request).await;
    }
    Refused(
        StatusCode::UNAUTHORIZED,
        "missing or wrong token: send `Authorization: Bearer <token>` \
         (the event stream alone also takes `?token=<token>`)"
            .into(),
    )
    .into_response()
}

async fn get_scene(State(ctx): State<Ctx>) -> Json<SceneView> {
    let live = ctx.studio.live();
    Json(ctx.studio.view(&live))
}

async fn post_scene(
    State(ctx): State<Ctx>,
    body: Result<Json<Change>, axum::extract::rejection::JsonRejection>,
) -> Response {
    let Json(change) = match body {
        Ok(b) => b,
        Err(e) => return Refused(StatusCode::BAD_REQUEST, e.body_text()).into_response(),
    };
    let interactive = change.quality == Quality::Interactive;
    match ctx.studio.edit(change) {
        Ok(view) => {
            if interactive {
                high_once_rested(&ctx.studio, view.generation);
            }
            Json(view).into_response()
        }
        Err(refused) => refused.into_response(),
    }
}

/// Draws frame `generation` at high quality once the edits rest
/// ([`Studio::rested`]).
fn high_once_rested(studio: &Arc<Studio>, generation: u64) {
    let studio = Arc::clone(studio);
    tokio::spawn(async move {
        tokio::time::sleep(REST).await;
        let _ = tokio::task::spawn_blocking(move || studio.rested(generation)).await;
    });
}

/// The browsed directory's scenes, listed again: `{"root", "scenes"}`.
async fn list_scenes(State(ctx): State<Ctx>) -> Response {
    match blocking(&ctx.studio, Studio::scan_scenes).await {
        Ok(scenes) => {
            let root = ctx.studio.root.as_ref().map(|r| r.display().to_string());
            Json(serde_json::json!({ "root": root, "scenes": scenes })).into_response()
        }
        Err(refused) => refused,
    }
}

/// `f` of the studio on a blocking thread: its answer, or the refusal's
/// response.
async fn blocking<T: Send + 'static>(
    studio: &Arc<Studio>,
    f: impl FnOnce(&Studio) -> Result<T, Refused> + Send + 'static,
) -> Result<T, Response> {
    let studio = Arc::clone(studio);
    match tokio::task::spawn_blocking(move || f(&studio)).await {
        Ok(answer) => answer.map_err(IntoResponse::into_response),
        Err(e) => Err(Refused(StatusCode::INTERNAL_SERVER_ERROR, e.to_string()).into_response()),
    }
}

/// `GET /studio/scenes/thumbnail`'s query.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct ScenePath {
    path: String,
}

async fn thumbnail(
    State(ctx): State<Ctx>,
    query: Result<Query<ScenePath>, axum::extract::rejection::QueryRejection>,
) -> Response {
    let path = match query {
        Ok(Query(q)) => q.path,
        Err(e) => return Refused(StatusCode::BAD_REQUEST, e.body_text()).into_response(),
    };
    match ctx.studio.thumbnail(&path) {
        Ok(png) => (
            [
                (header::CONTENT_TYPE, "image/png"),
                (header::CACHE_CONTROL, "no-cache"),
            ],
            png.as_slice().to_vec(),
        )
            .into_response(),
        Err(refused) => refused.into_response(),
    }
}

async fn open_scene(
    State(ctx): State<Ctx>,
    body: Result<Json<OpenScene>, axum::extract::rejection::JsonRejection>,
) -> Response {
    let Json(ask) = match body {
        Ok(b) => b,
        Err(e) => return Refused(StatusCode::BAD_REQUEST, e.body_text()).into_response(),
    };
    match blocking(&ctx.studio, move |studio| studio.open(&ask)).await {
        Ok(view) => {
            high_once_rested(&ctx.studio, view.generation);
            Json(view).into_response()
        }
        Err(refused) => refused,
    }
}

/// The tab an undo, a redo or a restore comes from (echoed in its `scene`
/// event).
#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
struct TabQuery {
    #[serde(default)]
    tab: Option<String>,
}

type TabQueryResult = Result<Query<TabQuery>, axum::extract::rejection::QueryRejection>;

async fn undo(State(ctx): State<Ctx>, query: TabQueryResult) -> Response {
    step(ctx, query, true).await
}

async fn redo(State(ctx): State<Ctx>, query: TabQueryResult) -> Response {
    step(ctx, query, false).await
}

async fn step(ctx: Ctx, query: TabQueryResult, back: bool) -> Response {
    let tab = match query {
        Ok(Query(q)) => q.tab,
        Err(e) => return Refused(StatusCode::BAD_REQUEST, e.body_text()).into_response(),
    };
    match blocking(&ctx.studio, move |studio| studio.step(back, tab)).await {
        Ok(view) => Json(view).into_response(),
        Err(refused) => refused,
    }
}

/// `POST /studio/snapshots`'s body.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct SnapshotName {
    name: String,
}

async fn take_snapshot(
    State(ctx): State<Ctx>,
    body: Result<Json<SnapshotName>, axum::extract::rejection::JsonRejection>,
) -> Response {
    let Json(SnapshotName { name }) = match body {
        Ok(b) => b,
        Err(e) => return Refused(StatusCode::BAD_REQUEST, e.body_text()).into_response(),
    };
    match blocking(&ctx.studio, move |studio| studio.take_snapshot(&name)).await {
        Ok(list) => Json(serde_json::json!({ "snapshots": list })).into_response(),
        Err(refused) => refused,
    }
}

type IdPath = Result<axum::extract::Path<u64>, axum::extract::rejection::PathRejection>;

async fn restore_snapshot(State(ctx): State<Ctx>, id: IdPath, query: TabQueryResult) -> Response {
    let (id, tab) = match (id, query) {
        (Ok(axum::extract::Path(id)), Ok(Query(q))) => (id, q.tab),
        (Err(e), _) => return Refused(StatusCode::BAD_REQUEST, e.body_text()).into_response(),
        (_, Err(e)) => return Refused(StatusCode::BAD_REQUEST, e.body_text()).into_response(),
    };
    match blocking(&ctx.studio, move |studio| studio.restore(id, tab)).await {
        Ok(view) => Json(view).into_response(),
        Err(refused) => refused,
    }
}

async fn snapshot_pixels(State(ctx): State<Ctx>, id: IdPath) -> Response {
    let id = match id {
        Ok(axum::extract::Path(id)) => id,
        Err(e) => return Refused(StatusCode::BAD_REQUEST, e.body_text()).into_response(),
    };
    match ctx.studio.snapshot_pixels(id) {
        Ok(pixels) => (
            [(header::CONTENT_TYPE, "application/octet-stream")],
            pixels.as_slice().to_vec(),
        )
            .into_response(),
        Err(refused) => refused.into_response(),
    }
}

/// `POST /studio/save`'s query: `over=true` writes over a file changed on
/// disk.
#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
struct SaveQuery {
    #[serde(default)]
    over: bool,
}

async fn save(
    State(ctx): State<Ctx>,
    query: Result<Query<SaveQuery>, axum::extract::rejection::QueryRejection>,
) -> Response {
    let over = match query {
        Ok(Query(q)) => q.over,
        Err(e) => return Refused(StatusCode::BAD_REQUEST, e.body_text()).into_response(),
    };
    let studio = Arc::clone(&ctx.studio);
    match tokio::task::spawn_blocking(move || studio.save(over)).await {
        Ok(Ok(message)) => Json(serde_json::json!({ "saved": message })).into_response(),
        Ok(Err(SaveRefused::Changed(e))) => Refused(StatusCode::CONFLICT, e).into_response(),
        Ok(Err(SaveRefused::Other(e))) => Refused(StatusCode::BAD_REQUEST, e).into_response(),
        Err(e) => Refused(StatusCode::INTERNAL_SERVER_ERROR, e.to_string()).into_response(),
    }
}

/// Queues "render final" on the service; answers the job and its number.
async fn render_final(State(ctx): State<Ctx>) -> Response {
    let (spec, number) = ctx.studio.final_job();
    let control = Arc::clone(&ctx.control);
    match tokio::task::spawn_blocking(move || control.submit(spec)).await {
        Ok(Ok(job)) => Json(serde_json::json!({ "job": job, "number": number })).into_response(),
        Ok(Err(e)) => crate::service::api::Refusal::from(e).into_response(),
        Err(e) => Refused(StatusCode::INTERNAL_SERVER_ERROR, e.to_string()).into_response(),
    }
}

/// A final render's PNG, for the page to show and download.
async fn final_png(
    State(ctx): State<Ctx>,
    number: Result<axum::extract::Path<u32>, axum::extract::rejection::PathRejection>,
) -> Response {
    let number = match number {
        Ok(axum::extract::Path(n)) => n,
        Err(e) => return Refused(StatusCode::BAD_REQUEST, e.body_text()).into_response(),
    };
    match ctx.studio.final_png(number) {
        Ok(png) => ([(header::CONTENT_TYPE, "image/png")], png).into_response(),
        Err(refused) => refused.into_response(),
    }
}

async fn reload(State(ctx): State<Ctx>) -> Response {
    let studio = Arc::clone(&ctx.studio);
    match tokio::task::spawn_blocking(move || studio.reload()).await {
        Ok(Ok(view)) => Json(view).into_response(),
        Ok(Err(e)) => Refused(StatusCode::BAD_REQUEST, e).into_response(),
        Err(e) => Refused(StatusCode::INTERNAL_SERVER_ERROR, e.to_string()).into_response(),
    }
}

/// Which tiles `GET /studio/tiles` sends: those recorded `from` up to
/// (not including) `to`, of frame `generation`.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct TileRange {
    generation: u64,
    from: usize,
    to: usize,
}

/// The pixels of a range of the current frame's tiles, one after another
/// (each tile's 8-bit sRGB RGBA, as many bytes as its event's `bytes`).
async fn tiles(
    State(ctx): State<Ctx>,
    range: Result<axum::extract::Query<TileRange>, axum::extract::rejection::QueryRejection>,
) -> Response {
    let range = match range {
        Ok(axum::extract::Query(r)) => r,
        Err(e) => return Refused(StatusCode::BAD_REQUEST, e.body_text()).into_response(),
    };
    match ctx.studio.tile_pixels(&range) {
        Ok(body) => (
            [
                (header::CONTENT_TYPE, "application/octet-stream"),
                (header::CACHE_CONTROL, "no-store"),
            ],
            body,
        )
            .into_response(),
        Err(refused) => refused.into_response(),
    }
}

/// What each browser's event stream holds.
struct Stream {
    backlog: VecDeque<Arc<Event>>,
    rx: broadcast::Receiver<Arc<Event>>,
    status: tokio::time::Interval,
    ctx: Ctx,
    sent: StatusSent,
}

/// What a stream's status events have told its browser: a hash of each
/// job's JSON and of the workers' (the first event is full).
#[derive(Default)]
struct StatusSent {
    jobs: std::collections::HashMap<u64, u64>,
    workers: Option<u64>,
}

fn json_hash(value: &impl serde::Serialize) -> u64 {
    use std::hash::{BuildHasher as _, BuildHasherDefault};
    let text = serde_json::to_string(value).unwrap_or_default();
    BuildHasherDefault::<std::collections::hash_map::DefaultHasher>::default().hash_one(text)
}

fn sse(event: &Event) -> SseEvent {
    SseEvent::default().event(event.name).data(&event.data)
}

/// The changes to the workers (pixels per second) and the job queue since
/// the stream's last status event: the workers when they changed, the jobs
/// new or changed, the ids of jobs gone; `None` when nothing changed. The
/// first event holds every job (`full`).
fn status(ctx: &Ctx, sent: &mut StatusSent) -> Option<SseEvent> {
    let full = sent.workers.is_none();
    let workers = ctx.control.workers();
    let workers_hash = json_hash(&workers);
    let workers = (sent.workers != Some(workers_hash)).then_some(workers);
    sent.workers = Some(workers_hash);
    let mut seen = std::collections::HashSet::new();
    let mut changed = Vec::new();
    for job in ctx.control.jobs() {
        let hash = json_hash(&job);
        seen.insert(job.id);
        if sent.jobs.insert(job.id, hash) != Some(hash) {
            changed.push(job);
        }
    }
    let mut gone: Vec<u64> = sent
        .jobs
        .keys()
        .filter(|id| !seen.contains(id))
        .copied()
        .collect();
    gone.sort_unstable();
    for id in &gone {
        sent.jobs.remove(id);
    }
    if !full && workers.is_none() && changed.is_empty() && gone.is_empty() {
        return None;
    }
    let mut data = serde_json::json!({ "jobs": changed });
    if full {
        data["full"] = true.into();
    }
    if let Some(workers) = workers {
        data["workers"] = serde_json::json!(workers);
    }
    if !gone.is_empty() {
        data["gone"] = serde_json::json!(gone);
    }
    Some(SseEvent::default().event("status").data(data.to_string()))
}

async fn events(
    State(ctx): State<Ctx>,
) -> Sse<impl futures_util::Stream<Item = Result<SseEvent, std::convert::Infallible>>> {
    let (backlog, rx) = ctx.studio.subscribe();
    let stream = Stream {
        backlog: backlog.into(),
        rx,
        status: tokio::time::interval(STATUS_EVERY),
        ctx,
        sent: StatusSent::default(),
    };
    let events = futures_util::stream::unfold(stream, |mut s| async move {
        if let Some(e) = s.backlog.pop_front() {
            return Some((Ok(sse(&e)), s));
        }
        loop {
            tokio::select! {
                received = s.rx.recv() => return match received {
                    Ok(e) => Some((Ok(sse(&e)), s)),
                    // Fallen behind (or closing): end the stream; the browser
                    // reconnects and is sent the frame again.
                    Err(_) => None,
                },
                _ = s.status.tick() => {
                    if let Some(e) = status(&s.ctx, &mut s.sent) {
                        return Some((Ok(e), s));
                    }
                }
            }
        }
    });
    Sse::new(events).keep_alive(KeepAlive::default())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn knob_values_are_written_into_the_text() {
        let text = std::fs::read_to_string(concat!(
            env!("CARGO_MANIFEST_DIR"),
            "/../scenes/pse/fur.ron"
        ))
        .unwrap();
        let values: BTreeMap<String, f64> =
            [("curliness".to_string(), 0.6), ("length".to_string(), 0.5)].into();
        let shown = with_knob_values(&text, &values).unwrap();
        let desc = hypertexture::scene::parse(&shown, "fur.ron").unwrap();
        assert_eq!(desc.knobs["curliness"].default, 0.6);
        assert_eq!(desc.knobs["length"].default, 0.5);
        assert_eq!(desc.knobs["fineness"].default, 40.0);
        assert_eq!(shown.len(), text.len());
    }

    #[test]
    fn a_high_quality_frames_pixels_are_fetched_by_range_of_the_current_frame() {
        let dir = std::env::temp_dir().join(format!("studio-tiles-{}", std::process::id()));
        let studio = Studio::new(None, &dir, None).unwrap();
        studio.live().frame = Some(LiveFrame {
            job: LIVE_JOBS,
            generation: 3,
            units: Vec::new(),
            recorded: Vec::new(),
            remaining: 0,
            started: Instant::now(),
            quality: Quality::High,
            events: Vec::new(),
            pixels: vec![
                Arc::new(vec![1, 2, 3, 4]),
                Arc::new(vec![5; 8]),
                Arc::new(vec![9; 4]),
            ],
            batch: Vec::new(),
            flush_at: None,
            _scene: Arc::new(
                hypertexture::RenderRequest::new(
                    include_str!("../../../../scenes/noisy_sphere.ron"),
                    "noisy_sphere.ron",
                )
                .build(None)
                .unwrap(),
            ),
        });
        let range = |generation, from, to| TileRange {
            generation,
            from,
            to,
        };
        assert_eq!(
            studio.tile_pixels(&range(3, 1, 3)).ok(),
            Some(vec![5, 5, 5, 5, 5, 5, 5, 5, 9, 9, 9, 9])
        );
        assert_eq!(
            studio.tile_pixels(&range(3, 0, 1)).ok(),
            Some(vec![1, 2, 3, 4])
        );
        assert_eq!(studio.tile_pixels(&range(3, 2, 2)).ok(), Some(vec![]));
        let Err(Refused(code, why)) = studio.tile_pixels(&range(2, 0, 1)) else {
            panic!("a superseded frame's tiles are gone");
        };
        assert_eq!(code, StatusCode::GONE);
        assert_eq!(why, "frame 2 is no longer the current one");
        for (from, to) in [(0, 4), (2, 1)] {
            let Err(Refused(code, why)) = studio.tile_pixels(&range(3, from, to)) else {
                panic!("tiles {from}..{to} are refused");
            };
            assert_eq!(code, StatusCode::BAD_REQUEST);
            assert_eq!(
                why,
                format!("tiles {from}..{to}: frame 3 has 3 tiles so far")
            );
        }
    }
}
