//! The files a user names on the command line: read with a cap (a device that
//! never ends, or a huge file named by mistake, fails at once with the file and
//! the cap in the message), and the output's directory checked writable before
//! any rendering.

use std::io::Read as _;
use std::path::Path;

/// The largest PEM file read (certificates, keys, CAs).
pub const MAX_PEM_BYTES: u64 = 1 << 20;

/// The largest EXR `recolor` reads.
pub const MAX_EXR_BYTES: u64 = 1 << 30;

/// The largest image `grid --png` reads.
pub const MAX_GRID_IMAGE_BYTES: u64 = 64 << 20;

/// Why a named file could not be used.
#[derive(Debug, thiserror::Error)]
pub enum FileError {
    /// The file could not be read.
    #[error("{path}: cannot read the {what}: {source}")]
    Read {
        /// The file.
        path: String,
        /// What it holds (`TLS certificate`, `EXR`…).
        what: &'static str,
        /// What the OS said.
        source: std::io::Error,
    },
    /// The file is larger than its cap.
    #[error("{path}: the {what} is larger than {cap} bytes, the most read")]
    TooLarge {
        /// The file.
        path: String,
        /// What it holds.
        what: &'static str,
        /// The cap in bytes.
        cap: u64,
    },
    /// The output's directory cannot take the image.
    #[error("{dir}: cannot write the output there: {source}")]
    NotWritable {
        /// The directory.
        dir: String,
        /// What the OS said.
        source: std::io::Error,
    },
}

/// The bytes of `path`, at most `cap` of them: a file whose metadata says it
/// is larger fails before reading, and no more than `cap + 1` bytes are read
/// from anything else (pipes and devices have no size).
pub fn read_capped(path: &Path, cap: u64, what: &'static str) -> Result<Vec<u8>, FileError> {
    let name = || path.display().to_string();
    let read = |source| FileError::Read {
        path: name(),
        what,
        source,
    };
    let too_large = || FileError::TooLarge {
        path: name(),
        what,
        cap,
    };
    let file = std::fs::File::open(path).map_err(read)?;
    if file.metadata().map_err(read)?.len() > cap {
        return Err(too_large());
    }
    let mut bytes = Vec::new();
    file.take(cap + 1).read_to_end(&mut bytes).map_err(read)?;
    if bytes.len() as u64 > cap {
        return Err(too_large());
    }
    Ok(bytes)
}

/// Checks that an image can be written at `out`: its directory exists and a
/// file can be created there (one is created and removed at once).
pub fn check_writable(out: &Path) -> Result<(), FileError> {
    let dir = match out.parent() {
        Some(d) if !d.as_os_str().is_empty() => d,
        _ => Path::new("."),
    };
    let fail = |source| FileError::NotWritable {
        dir: dir.display().to_string(),
        source,
    };
    let probe = dir.join(format!(".hypertexture-probe-{}", std::process::id()));
    std::fs::OpenOptions::new()
        .write(true)
        .create_new(true)
        .open(&probe)
        .map_err(fail)?;
    std::fs::remove_file(&probe).map_err(fail)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn endless_files_fail_at_the_cap() {
        let e = read_capped(Path::new("/dev/zero"), 1000, "EXR").unwrap_err();
        assert_eq!(
            e.to_string(),
            "/dev/zero: the EXR is larger than 1000 bytes, the most read"
        );
        let e = check_writable(Path::new("/no/such/dir/x.png")).unwrap_err();
        assert!(
            e.to_string().starts_with("/no/such/dir: cannot write"),
            "{e}"
        );
        check_writable(Path::new("x.png")).unwrap();
    }
}
