//! The scene browser: the `*.ron` scenes under the directory the studio
//! browses (`coordinator studio DIR`, or a scene file's own directory), each
//! listed with a thumbnail the farm renders.
//!
//! A scene's *key* hashes its text and the bytes of the files it names
//! (meshes, read beside it): a thumbnail is rendered once per key, at
//! interactive quality within [`THUMB`] pixels, on the farm below the live
//! frame's priority, and kept as a PNG. A scene that does not parse or build
//! gets no thumbnail; the listing shows its error (the CLI's, with its
//! line:column).
//!
//! Paths are relative to the browsed directory, `/`-separated; [`confine`]
//! refuses any that leaves it (`..`, absolute paths, symlinks out). The
//! listing skips hidden files and directories (a name starting with `.`)
//! and links to directories; a linked scene is listed when it lies inside.

use std::collections::HashMap;
use std::path::{Component, Path, PathBuf};
use std::sync::Arc;

use serde::Serialize;

use super::snapshots::Render;
use crate::farm::JobId;

/// A thumbnail's longer side, in pixels (the scene's aspect is kept).
pub const THUMB: u32 = 96;

/// The most scenes listed (the first ones in path order).
pub const MOST: usize = 500;

/// How deep the listing goes below the browsed directory.
const DEPTH: usize = 16;

/// Why a path given for a scene is refused.
#[derive(Debug, PartialEq)]
pub enum Bad {
    /// Not a relative path of a scene inside the browsed directory (400).
    Outside(String),
    /// Inside, but no such file (404).
    Missing(String),
}

/// The `*.ron` files under `root`, as `/`-separated paths relative to it,
/// sorted (at most [`MOST`]).
pub fn list(root: &Path) -> Vec<String> {
    let mut found = Vec::new();
    walk(root, root, "", 0, &mut found);
    found.sort();
    found.truncate(MOST);
    found
}

fn walk(root: &Path, dir: &Path, prefix: &str, depth: usize, found: &mut Vec<String>) {
    let Ok(entries) = std::fs::read_dir(dir) else {
        return;
    };
    for entry in entries.flatten() {
        let name = entry.file_name();
        let Some(name) = name.to_str() else {
            continue;
        };
        let Ok(kind) = entry.file_type() else {
            continue;
        };
        if name.starts_with('.') {
            continue;
        }
        let rel = if prefix.is_empty() {
            name.to_string()
        } else {
            format!("{prefix}/{name}")
        };
        if kind.is_dir() {
            if depth < DEPTH {
                walk(root, &entry.path(), &rel, depth + 1, found);
            }
        } else if name.ends_with(".ron")
            && (kind.is_file() || (kind.is_symlink() && confine(root, &rel).is_ok()))
        {
            found.push(rel);
        }
    }
}

/// The file of scene `rel` under `root`: a relative path of normal
/// components naming a `.ron` file that exists and, links followed, lies
/// inside `root`.
pub fn confine(root: &Path, rel: &str) -> Result<PathBuf, Bad> {
    let shown = if rel.chars().count() > 200 {
        format!("{}…", rel.chars().take(200).collect::<String>())
    } else {
        rel.to_string()
    };
    let outside = || {
        Bad::Outside(format!(
            "`{shown}` is not a scene's path inside {}: give it relative to that directory, \
             without `..`",
            root.display()
        ))
    };
    let path = Path::new(rel);
    if rel.is_empty()
        || rel.contains(['\\', '\0'])
        || !path.components().all(|c| matches!(c, Component::Normal(_)))
    {
        return Err(outside());
    }
    if !rel.ends_with(".ron") {
        return Err(Bad::Outside(format!(
            "`{shown}` is not a scene: scenes are `.ron` files"
        )));
    }
    let file = root.join(path);
    let real = file
        .canonicalize()
        .map_err(|e| Bad::Missing(format!("no scene `{shown}` in {}: {e}", root.display())))?;
    let root_real = root
        .canonicalize()
        .map_err(|e| Bad::Missing(format!("{}: {e}", root.display())))?;
    if !real.starts_with(&root_real) {
        return Err(Bad::Outside(format!(
            "`{shown}` leads outside {} (a link to {})",
            root.display(),
            real.display()
        )));
    }
    if !real.is_file() {
        return Err(Bad::Missing(format!(
            "`{shown}` in {} is not a file",
            root.display()
        )));
    }
    Ok(file)
}

/// A thumbnail's size for a `width` × `height` scene: its aspect within
/// [`THUMB`] pixels (a smaller scene keeps its size).
pub fn thumbnail_size(width: u32, height: u32) -> (u32, u32) {
    let longer = width.max(height).max(1);
    if longer <= THUMB {
        return (width.max(1), height.max(1));
    }
    let scale = |side: u32| {
        ((u64::from(side) * u64::from(THUMB) + u64::from(longer) / 2) / u64::from(longer)).max(1)
            as u32
    };
    (scale(width), scale(height))
}

/// The first line of the scene's leading comment, if it starts with one.
fn title(text: &str) -> Option<String> {
    let line = text.trim_start().lines().next()?;
    let title = line.strip_prefix("//")?.trim();
    let title: String = title.chars().take(120).collect();
    (!title.is_empty()).then_some(title)
}

/// A scene as read from disk by [`read`].
pub struct Found {
    /// Its path relative to the browsed directory.
    pub path: String,
    /// Its name in messages and for the files it names: the browsed
    /// directory joined with `path`.
    pub name: String,
    pub title: Option<String>,
    /// Its text, when it parses.
    pub text: Option<String>,
    /// Its key, when it parses.
    pub key: Option<u64>,
    /// Why it cannot be read or parsed.
    pub error: Option<String>,
}

/// Reads every scene under `root` ([`list`]): its text, title and key, or
/// its error.
pub fn read(root: &Path) -> Vec<Found> {
    list(root)
        .into_iter()
        .map(|path| {
            let name = root.join(&path).display().to_string();
            let mut found = Found {
                path,
                name,
                title: None,
                text: None,
                key: None,
                error: None,
            };
            match std::fs::read_to_string(&found.name) {
                Err(e) => found.error = Some(format!("{}: cannot read the scene: {e}", found.name)),
                Ok(text) => {
                    found.title = title(&text);
                    match hypertexture::scene::parse(&text, &found.name) {
                        Err(e) => found.error = Some(e.to_string()),
                        Ok(desc) => {
                            found.key = Some(key(&text, &found.name, &desc.mesh_paths()));
                            found.text = Some(text);
                        }
                    }
                }
            }
            found
        })
        .collect()
}

/// The hash of `text` and of the files `paths` it names (read beside the
/// scene file `name`; a file that cannot be read counts by its error).
fn key(text: &str, name: &str, paths: &[String]) -> u64 {
    let mut hasher = xxhash_rust::xxh3::Xxh3::new();
    hasher.update(text.as_bytes());
    for path in paths {
        hasher.update(b"\0");
        hasher.update(path.as_bytes());
        hasher.update(b"\0");
        match hypertexture::scene::read_asset(&hypertexture::scene::asset_path(name, path)) {
            Ok(bytes) => hasher.update(&bytes),
            Err(e) => hasher.update(e.as_bytes()),
        }
    }
    hasher.digest()
}

/// A thumbnail, by key.
enum Thumb {
    /// Its scene is being built (by the scan that found the key).
    Building,
    Rendering(Render),
    /// Its PNG.
    Ready(Arc<Vec<u8>>),
    /// Why it has none: the scene does not build, or the farm gave it up.
    Failed(String),
}

/// A scene as the page lists it.
#[derive(Clone, Debug, Serialize, PartialEq)]
pub struct SceneEntry {
    /// Relative to the browsed directory.
    pub path: String,
    /// Its file's name without `.ron`.
    pub name: String,
    /// The first line of its leading comment.
    pub title: Option<String>,
    /// Its thumbnail is rendered (`GET /studio/scenes/thumbnail?path=PATH`).
    pub ready: bool,
    /// Its key, in hex: a new one means a new thumbnail.
    pub key: Option<String>,
    /// Why it has no thumbnail.
    pub error: Option<String>,
}

/// The scenes listed last and their thumbnails.
pub struct Catalogue {
    root: PathBuf,
    listed: Vec<(Found, Option<u64>)>,
    thumbs: HashMap<u64, Thumb>,
}

impl Catalogue {
    pub fn new(root: PathBuf) -> Catalogue {
        Catalogue {
            root,
            listed: Vec::new(),
            thumbs: HashMap::new(),
        }
    }

    pub fn root(&self) -> &Path {
        &self.root
    }

    /// Takes a new listing ([`read`]); answers the scenes whose thumbnails
    /// are to be built, marked as building (their text, name and key).
    /// Thumbnails of keys no longer listed are dropped (unless rendering).
    pub fn update(&mut self, found: Vec<Found>) -> Vec<(String, String, u64)> {
        let mut start = Vec::new();
        for f in &found {
            if let (Some(key), Some(text)) = (f.key, &f.text)
                && !self.thumbs.contains_key(&key)
            {
                self.thumbs.insert(key, Thumb::Building);
                start.push((text.clone(), f.name.clone(), key));
            }
        }
        let keys: std::collections::HashSet<u64> = found.iter().filter_map(|f| f.key).collect();
        self.thumbs
            .retain(|k, t| keys.contains(k) || matches!(t, Thumb::Building | Thumb::Rendering(_)));
        self.listed = found
            .into_iter()
            .map(|mut f| {
                f.text = None;
                let key = f.key;
                (f, key)
            })
            .collect();
        start
    }

    /// Thumbnail `key` is on the farm (`Ok`), or cannot be (`Err`: why).
    pub fn started(&mut self, key: u64, render: Result<Render, String>) {
        let thumb = match render {
            Ok(r) => Thumb::Rendering(r),
            Err(e) => Thumb::Failed(e),
        };
        self.thumbs.insert(key, thumb);
    }

    /// Thumbnail `key` was not started (the farm is not attached yet): a
    /// later listing starts it.
    pub fn not_started(&mut self, key: u64) {
        self.thumbs.remove(&key);
    }

    /// The scenes as the page lists them.
    pub fn entries(&self) -> Vec<SceneEntry> {
        self.listed
            .iter()
            .map(|(f, key)| {
                let thumb = key.and_then(|k| self.thumbs.get(&k));
                let error = match thumb {
                    Some(Thumb::Failed(e)) => Some(e.clone()),
                    _ => f.error.clone(),
                };
                SceneEntry {
                    path: f.path.clone(),
                    name: f
                        .path
                        .rsplit('/')
                        .next()
                        .unwrap_or(&f.path)
                        .trim_end_matches(".ron")
                        .to_string(),
                    title: f.title.clone(),
                    ready: matches!(thumb, Some(Thumb::Ready(_))),
                    key: key.map(|k| format!("{k:016x}")),
                    error,
                }
            })
            .collect()
    }

    /// Scene `path`'s thumbnail, as PNG: `Err((false, why))` for a path not
    /// listed, `Err((true, why))` while it renders or when it has none.
    pub fn thumbnail(&self, path: &str) -> Result<Arc<Vec<u8>>, (bool, String)> {
        let Some((found, key)) = self.listed.iter().find(|(f, _)| f.path == path) else {
            return Err((
                false,
                format!("no scene `{path}` is listed in {}", self.root.display()),
            ));
        };
        let none = |why: &str| Err((true, format!("`{path}` has no thumbnail: {why}")));
        match key.and_then(|k| self.thumbs.get(&k)) {
            Some(Thumb::Ready(png)) => Ok(Arc::clone(png)),
            Some(Thumb::Failed(e)) => none(e),
            Some(Thumb::Building | Thumb::Rendering(_)) => {
                Err((true, format!("`{path}`'s thumbnail is still rendering")))
            }
            None => none(found.error.as_deref().unwrap_or("not rendered yet")),
        }
    }

    /// Stores a tile of the thumbnail the farm's `job` renders; returns
    /// `None` when `job` renders none, else whether the thumbnail became
    /// ready (or failed to encode).
    pub fn store(&mut self, job: JobId, unit: usize, tile: &[u8]) -> Option<bool> {
        let (key, render) = self.rendered_by(job)?;
        if !render.store(unit, tile) {
            return Some(false);
        }
        let (width, height) = render.size();
        let pixels = render.pixels().map(Arc::clone).unwrap_or_default();
        let meta = crate::image::output::ImageMetadata::without_scene(width, height, None, None);
        let thumb = match crate::image::output::encode_srgb8_png(&pixels, width, height, &meta) {
            Ok(png) => Thumb::Ready(Arc::new(png)),
            Err(e) => Thumb::Failed(e.to_string()),
        };
        self.thumbs.insert(key, thumb);
        Some(true)
    }

    /// The farm gave `job` up: returns whether it rendered a thumbnail.
    pub fn fail(&mut self, job: JobId, why: &str) -> bool {
        let Some((key, _)) = self.rendered_by(job) else {
            return false;
        };
        self.thumbs.insert(key, Thumb::Failed(why.to_string()));
        true
    }

    fn rendered_by(&mut self, job: JobId) -> Option<(u64, &mut Render)> {
        self.thumbs.iter_mut().find_map(|(k, t)| match t {
            Thumb::Rendering(r) if r.job == job => Some((*k, r)),
            _ => None,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn dir(name: &str) -> PathBuf {
        let dir = std::env::temp_dir().join(format!("studio-scenes-{name}-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(&dir).unwrap();
        dir
    }

    #[test]
    fn the_listing_holds_every_scene_below_sorted_and_skips_hidden_directories() {
        let root = dir("list");
        for file in [
            "b.ron",
            "a.ron",
            "sub/c.ron",
            "sub/deeper/d.ron",
            ".hidden/e.ron",
            "notes.txt",
            "b.ron.~1~",
            "meshes/spot.obj",
        ] {
            let path = root.join(file);
            std::fs::create_dir_all(path.parent().unwrap()).unwrap();
            std::fs::write(&path, "Scene()").unwrap();
        }
        assert_eq!(
            list(&root),
            ["a.ron", "b.ron", "sub/c.ron", "sub/deeper/d.ron"]
        );
        assert!(list(&root.join("nothing-here")).is_empty());
    }

    #[test]
    fn paths_are_confined_to_the_browsed_directory() {
        let root = dir("confine");
        let outside = dir("confine-outside");
        std::fs::create_dir_all(root.join("sub")).unwrap();
        std::fs::write(root.join("a.ron"), "").unwrap();
        std::fs::write(root.join("sub/b.ron"), "").unwrap();
        std::fs::write(outside.join("x.ron"), "").unwrap();
        std::os::unix::fs::symlink(outside.join("x.ron"), root.join("link.ron")).unwrap();
        std::os::unix::fs::symlink(root.join("a.ron"), root.join("inside.ron")).unwrap();
        assert_eq!(confine(&root, "a.ron"), Ok(root.join("a.ron")));
        assert_eq!(confine(&root, "sub/b.ron"), Ok(root.join("sub/b.ron")));
        assert_eq!(confine(&root, "inside.ron"), Ok(root.join("inside.ron")));
        for bad in [
            "../x.ron",
            "sub/../a.ron",
            "./a.ron",
            "/etc/passwd.ron",
            "",
            "a\\b.ron",
            "a.txt",
        ] {
            assert!(
                matches!(confine(&root, bad), Err(Bad::Outside(_))),
                "{bad:?}: {:?}",
                confine(&root, bad)
            );
        }
        let Err(Bad::Outside(why)) = confine(&root, "link.ron") else {
            panic!("a link out is refused");
        };
        assert!(why.contains("leads outside"), "{why}");
        assert!(matches!(confine(&root, "none.ron"), Err(Bad::Missing(_))));
        assert_eq!(list(&root), ["a.ron", "inside.ron", "sub/b.ron"]);
    }

    #[test]
    fn thumbnails_keep_the_aspect_within_the_size() {
        assert_eq!(thumbnail_size(512, 512), (96, 96));
        assert_eq!(thumbnail_size(640, 480), (96, 72));
        assert_eq!(thumbnail_size(100, 2000), (5, 96));
        assert_eq!(thumbnail_size(24, 32), (24, 32));
    }

    #[test]
    fn a_listing_names_each_scene_its_title_and_its_error() {
        let root = dir("read");
        std::fs::write(
            root.join("good.ron"),
            include_str!("../../../../scenes/noisy_sphere.ron"),
        )
        .unwrap();
        std::fs::write(
            root.join("broken.ron"),
            "Scene(image: (width: 8, height: 8),\n  camera: oops,\n)\n",
        )
        .unwrap();
        let mut catalogue = Catalogue::new(root.clone());
        let start = catalogue.update(read(&root));
        assert_eq!(start.len(), 1, "the good scene's thumbnail is started");
        let entries = catalogue.entries();
        assert_eq!(entries[0].path, "broken.ron");
        let error = entries[0].error.as_deref().unwrap();
        assert!(
            error.contains("broken.ron:2:11: expected camera"),
            "{error}"
        );
        assert_eq!(entries[1].name, "good");
        assert!(
            entries[1]
                .title
                .as_deref()
                .unwrap()
                .starts_with("Noisy sphere")
        );
        assert!(!entries[1].ready);
        assert!(catalogue.update(read(&root)).is_empty(), "once per content");
        assert!(catalogue.thumbnail("good.ron").unwrap_err().0, "listed");
        assert!(
            !catalogue.thumbnail("other.ron").unwrap_err().0,
            "not listed"
        );
        catalogue.not_started(start[0].2);
        assert_eq!(catalogue.update(read(&root)).len(), 1, "started again");
    }
}
