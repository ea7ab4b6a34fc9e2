//! Where a job's images may go: its output pattern checked at submission
//! (the `#` runs, the lengths the file system allows, on the longest
//! expansion), each frame's file expanded only when it is written, and the
//! output roots every file must resolve inside, after `..` and symlinks.

use std::path::{Component, Path, PathBuf};

use hypertexture::FrameRange;

/// The longest run of `#`: a frame number (a `u32`, at most 10 digits) padded
/// to 9 digits covers every sequence of fewer than a billion frames.
pub const MAX_HASH_RUN: usize = 9;

/// The most bytes of a path (Linux's `PATH_MAX` counts the closing NUL).
pub const PATH_MAX: usize = libc::PATH_MAX as usize - 1;

/// The most bytes of one component of a path (Linux's `NAME_MAX`).
pub const NAME_MAX: usize = 255;

/// Why an output pattern or path is refused.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum OutputError {
    /// The pattern cannot be expanded, or its files could not be created.
    #[error("out {}: {message}", shown(pattern))]
    Pattern {
        /// The pattern as given.
        pattern: String,
        /// What is wrong.
        message: String,
    },
    /// The path lies outside every output root (the same message whether or
    /// not it exists).
    #[error(
        "out {}: outputs are written only inside the output roots ({roots})",
        shown(pattern)
    )]
    Outside {
        /// The pattern as given.
        pattern: String,
        /// The roots, comma-separated.
        roots: String,
    },
}

/// A pattern as messages quote it: at most 120 characters, then `…`.
fn shown(pattern: &str) -> String {
    match pattern.char_indices().nth(120) {
        Some((cut, _)) => format!("{:?}…", &pattern[..cut]),
        None => format!("{pattern:?}"),
    }
}

/// The file of `frame` for an output pattern: each run of `#` is the frame
/// number padded with zeros to the run's length (`fur.####.exr`, 7 →
/// `fur.0007.exr`).
pub fn expand_pattern(pattern: &str, frame: u32) -> String {
    let digits = frame.to_string();
    let mut out = String::with_capacity(pattern.len() + digits.len());
    let mut chars = pattern.chars().peekable();
    while let Some(c) = chars.next() {
        if c == '#' {
            let mut width: usize = 1;
            while chars.peek() == Some(&'#') {
                chars.next();
                width += 1;
            }
            out.extend(std::iter::repeat_n('0', width.saturating_sub(digits.len())));
            out.push_str(&digits);
        } else {
            out.push(c);
        }
    }
    out
}

/// Checks an output pattern for `frames`: every run of `#` at most
/// [`MAX_HASH_RUN`] long, and the longest expansion (that of the last frame:
/// a number never has fewer digits than a smaller one) at most [`PATH_MAX`]
/// bytes in all and [`NAME_MAX`] a component, made absolute against `base`.
pub fn check_pattern(pattern: &str, frames: FrameRange, base: &Path) -> Result<(), OutputError> {
    let refuse = |message: String| OutputError::Pattern {
        pattern: pattern.to_string(),
        message,
    };
    let longest_run = pattern.split(|c| c != '#').map(str::len).max().unwrap_or(0);
    if longest_run > MAX_HASH_RUN {
        return Err(refuse(format!(
            "a run of {longest_run} # is longer than {MAX_HASH_RUN}, the most digits a frame number is padded to"
        )));
    }
    if frames.len() > 1 && longest_run == 0 {
        return Err(refuse(format!(
            "{} frames need a # in the name (e.g. out/fur.####.png)",
            frames.len()
        )));
    }
    let last = frames.last;
    let path = base.join(expand_pattern(pattern, last));
    let bytes = path.as_os_str().len();
    if bytes > PATH_MAX {
        return Err(refuse(format!(
            "the path of frame {last} is {bytes} bytes; PATH_MAX allows {PATH_MAX}"
        )));
    }
    for component in path.components() {
        let name = component.as_os_str();
        if name.len() > NAME_MAX {
            let shown: String = name.to_string_lossy().chars().take(40).collect();
            return Err(refuse(format!(
                "the name {shown:?}… of frame {last} is {} bytes; NAME_MAX allows {NAME_MAX} a component",
                name.len()
            )));
        }
    }
    Ok(())
}

/// The directories outputs may be written in (`serve --output-root`), each
/// held resolved (absolute, without symlinks).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct OutputRoots {
    roots: Vec<PathBuf>,
}

impl OutputRoots {
    /// The roots `dirs` (each must exist), resolved.
    pub fn new(dirs: &[PathBuf]) -> Result<OutputRoots, String> {
        let mut roots = Vec::new();
        for dir in dirs {
            let resolved = std::fs::canonicalize(dir)
                .map_err(|e| format!("--output-root {}: {e}", dir.display()))?;
            if !resolved.is_dir() {
                return Err(format!("--output-root {}: not a directory", dir.display()));
            }
            if !roots.contains(&resolved) {
                roots.push(resolved);
            }
        }
        Ok(OutputRoots { roots })
    }

    /// The roots of a service started in `cwd` with `--output-root` naming
    /// `given`: those, or `cwd` when none is named, but never `/` by default.
    pub fn for_serve(given: &[PathBuf], cwd: &Path) -> Result<OutputRoots, String> {
        if !given.is_empty() {
            return OutputRoots::new(given);
        }
        if cwd.parent().is_none() {
            return Err(format!(
                "serve was started in {}, and outputs are written only inside the output roots: \
                 name the directories jobs may write to with --output-root DIR (repeatable)",
                cwd.display()
            ));
        }
        OutputRoots::new(&[cwd.to_path_buf()])
    }

    /// The roots, as resolved.
    pub fn roots(&self) -> &[PathBuf] {
        &self.roots
    }

    /// The roots for messages: `/a, /b`.
    fn names(&self) -> String {
        let names: Vec<String> = self.roots.iter().map(|r| r.display().to_string()).collect();
        names.join(", ")
    }

    /// Where `path` (relative ones against `base`) resolves: its longest
    /// existing ancestor with `..` and symlinks resolved, then the rest,
    /// which may hold no `..`. Refused ([`OutputError::Outside`]) unless
    /// the directory lies inside a root; the file itself is not looked at.
    pub fn resolve(&self, pattern: &str, path: &Path, base: &Path) -> Result<PathBuf, OutputError> {
        let outside = || OutputError::Outside {
            pattern: pattern.to_string(),
            roots: self.names(),
        };
        let path = base.join(path);
        let (Some(dir), Some(name)) = (path.parent(), path.file_name()) else {
            return Err(outside());
        };
        let mut existing = dir;
        let mut rest = Vec::new();
        let resolved = loop {
            match std::fs::canonicalize(existing) {
                Ok(r) => break r,
                Err(_) => {
                    let (Some(parent), Some(last)) = (existing.parent(), existing.file_name())
                    else {
                        return Err(outside());
                    };
                    rest.push(last.to_os_string());
                    existing = parent;
                }
            }
        };
        let mut resolved = resolved;
        for part in rest.iter().rev() {
            match Path::new(part).components().next() {
                Some(Component::Normal(_)) => resolved.push(part),
                _ => return Err(outside()),
            }
        }
        if !self.roots.iter().any(|root| resolved.starts_with(root)) {
            return Err(outside());
        }
        resolved.push(name);
        Ok(resolved)
    }

    /// [`OutputRoots::resolve`], then the missing directories created (each
    /// checked again once made, so nothing placed meanwhile leads outside).
    pub fn prepare(&self, pattern: &str, path: &Path, base: &Path) -> Result<PathBuf, OutputError> {
        let resolved = self.resolve(pattern, path, base)?;
        if let Some(dir) = resolved.parent() {
            std::fs::create_dir_all(dir).map_err(|e| OutputError::Pattern {
                pattern: pattern.to_string(),
                message: format!("cannot create its directory: {}", e.kind()),
            })?;
        }
        self.resolve(pattern, &resolved, base)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn runs_of_hashes_are_padded_frame_numbers() {
        assert_eq!(expand_pattern("fur.####.exr", 7), "fur.0007.exr");
        assert_eq!(expand_pattern("a#b##", 123), "a123b123");
        assert_eq!(expand_pattern("x.png", 5), "x.png");
        // A long run never panics, checked or not.
        assert_eq!(expand_pattern(&"#".repeat(70_000), 1).len(), 70_000);
    }

    #[test]
    fn patterns_are_checked_on_their_longest_expansion() {
        let base = Path::new("/tmp");
        check_pattern("f.#########.png", FrameRange::new(0, 99_999), base).unwrap();
        let e = check_pattern("f.##########.png", FrameRange::one(0), base).unwrap_err();
        assert!(e.to_string().contains("run of 10 #"), "{e}");
        let e = check_pattern("f.png", FrameRange::new(0, 1), base).unwrap_err();
        assert!(e.to_string().contains("need a #"), "{e}");
        // 251 + 4 bytes is NAME_MAX exactly; 6-digit frames make it longer.
        let name = format!("{}#.png", "n".repeat(250));
        check_pattern(&name, FrameRange::new(0, 9), base).unwrap();
        let e = check_pattern(&name, FrameRange::new(0, 10), base).unwrap_err();
        assert!(e.to_string().contains("NAME_MAX allows 255"), "{e}");
        let deep = format!("{}/x.png", vec!["d".repeat(200); 21].join("/"));
        let e = check_pattern(&deep, FrameRange::one(0), base).unwrap_err();
        assert!(e.to_string().contains("PATH_MAX allows 4095"), "{e}");
    }

    #[test]
    fn outputs_resolve_inside_a_root_after_dots_and_symlinks() {
        let dir = std::env::temp_dir().join(format!("ht-roots-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        let root = dir.join("root");
        std::fs::create_dir_all(root.join("sub")).unwrap();
        std::fs::create_dir_all(dir.join("other")).unwrap();
        std::os::unix::fs::symlink(dir.join("other"), root.join("link")).unwrap();
        let roots = OutputRoots::new(std::slice::from_ref(&root)).unwrap();
        let base = root.clone();
        let inside = roots.resolve("p", Path::new("sub/a.png"), &base).unwrap();
        assert_eq!(inside, root.canonicalize().unwrap().join("sub/a.png"));
        roots
            .resolve("p", Path::new("new/dir/a.png"), &base)
            .unwrap();
        for outside in [
            "../other/a.png",
            "link/a.png",
            "link/missing/a.png",
            "/etc/a.png",
            "/no/such/dir/a.png",
            "new/../../other/a.png",
        ] {
            let e = roots.resolve("p", Path::new(outside), &base).unwrap_err();
            assert!(matches!(e, OutputError::Outside { .. }), "{outside}: {e}");
        }
        let made = roots
            .prepare("p", Path::new("made/here/a.png"), &base)
            .unwrap();
        assert!(made.parent().unwrap().is_dir());
        let e = OutputRoots::for_serve(&[], Path::new("/")).unwrap_err();
        assert!(e.contains("--output-root"), "{e}");
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
