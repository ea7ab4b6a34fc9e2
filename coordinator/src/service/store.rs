//! The service's persistent store: the job queue and the tiles of the frames
//! in flight, in one SQLite database `DIR/farm.sqlite`.
//!
//! # Durability
//!
//! Every method is one SQLite transaction. The database runs in WAL journal
//! mode with `synchronous=NORMAL`: a committed transaction is in the WAL file
//! (in the operating system's page cache) before the method returns, so it
//! survives a kill of the process at any moment, SIGKILL included; on the next
//! [`Store::open`] SQLite replays the WAL, and a transaction cut short leaves
//! no trace. A power loss or an operating-system crash may lose the last
//! transactions committed since the WAL was last synced (at each checkpoint);
//! `synchronous=FULL` would prevent that at the cost of an `fsync` per
//! transaction, i.e. per stored tile.
//!
//! # Size
//!
//! A frame's tiles are deleted when the frame is finished
//! ([`Store::finish_frame`]) and a job's remaining tiles when it ends
//! ([`Store::set_state`] with a final state), in the same transaction. SQLite
//! reuses the freed pages, so the file stays as large as the most tiles held
//! at once, i.e. bounded by the frames in flight.
//!
//! # One coordinator per directory
//!
//! [`Store::open`] takes an exclusive `flock` on `DIR/lock` and holds it for
//! the store's lifetime; the file holds the owner's pid for the message of a
//! refused open. The operating system releases the lock when the process
//! exits however it exits (SIGKILL included), so a stale lock never needs
//! cleaning up, and a second coordinator cannot interleave its writes with
//! the first's. The lock file is opened close-on-exec, so child processes
//! (local workers) do not inherit the lock.
//!
//! # Schema
//!
//! `PRAGMA user_version` holds the store version ([`STORE_VERSION`]). A fresh
//! database gets the current version; a newer one is refused; a database whose
//! tables or columns differ from the expected ones is refused as corrupt. The
//! tables:
//!
//! - `jobs(id, spec_json, priority, state, error, frames_done, submitted_unix_ms)`;
//!   `id` is `AUTOINCREMENT`, so ids are never reused, even after deletes.
//! - `outputs(job, frame, seq, path)`: the files written, `seq` giving their order.
//! - `tiles(job, frame, unit, pixels, checksum)`: the units received of
//!   unfinished frames, each with the XXH3-64 of its bytes (version 3): a tile
//!   read back whose bytes no longer match is dropped and rendered again.
//! - `redo(job, frame)`: finished frames to render again, because a worker
//!   caught lying had delivered some of their tiles (version 2).
//! - `meta(key, value)`: `generation`, the highest job id given out
//!   (version 3).
//!
//! An older store is brought to the current version when opened (version 1
//! gains `redo`; version 2 gains the checksums, computed from the bytes as
//! they are then, and `meta`).
//!
//! # Checks
//!
//! Every write is checked, its commit included: a write that fails (disk
//! full, I/O error) is an error, never a value. [`Store::open`] runs SQLite's
//! `PRAGMA quick_check` and refuses a damaged file with a message naming it
//! and what to do; [`check`] runs the full `integrity_check` and every tile's
//! checksum (`coordinator store check`).
//!
//! # Generation
//!
//! The highest job id given out is kept both in the database and in a small
//! file beside it, `DIR/generation` (written by a rename, after each job's
//! commit). A database that comes back older than the file — its WAL lost or
//! truncated, an old copy put back — has lost committed jobs: it is refused
//! ([`StoreError::Older`]) unless opened with `accept_older`, which also
//! moves the id sequence past the file's value, so no id is given twice.
//!
//! # At rest
//!
//! [`Store::checkpoint`] (at a clean stop) copies the WAL into the database
//! and truncates it, so `farm.sqlite` alone holds everything; [`backup`]
//! copies a consistent snapshot of a store in use with SQLite's online
//! backup API.

use std::fs::{File, OpenOptions};
use std::io::{Read, Write};
use std::os::fd::AsRawFd;
use std::path::{Path, PathBuf};
use std::time::Duration;

use rusqlite::{Connection, ErrorCode, OpenFlags, OptionalExtension, params};

use crate::service::jobs::JobState;

/// The store version this build writes and the newest it reads.
pub const STORE_VERSION: i64 = 3;

/// The database file's name inside the data directory.
pub const DB_FILE: &str = "farm.sqlite";

/// The lock file's name inside the data directory.
pub const LOCK_FILE: &str = "lock";

/// The generation file's name inside the data directory: the highest job id
/// given out, as decimal text.
pub const GENERATION_FILE: &str = "generation";

/// What to do about a damaged store, for every message that reports one.
const RESTORE_HINT: &str = "restore it from a backup (`coordinator store backup`, deploy/README.md) \
                            or start with --data in another directory";

/// How long a statement waits for a lock held by another connection.
const BUSY_TIMEOUT: Duration = Duration::from_secs(5);

/// The WAL file is truncated back to this size after a checkpoint.
const JOURNAL_SIZE_LIMIT: i64 = 64 << 20;

/// The schema of [`STORE_VERSION`].
const SCHEMA: &str = "
CREATE TABLE jobs (
    id INTEGER PRIMARY KEY AUTOINCREMENT,
    spec_json TEXT NOT NULL,
    priority INTEGER NOT NULL,
    state TEXT NOT NULL,
    error TEXT,
    frames_done INTEGER NOT NULL DEFAULT 0,
    submitted_unix_ms INTEGER NOT NULL
);
CREATE TABLE outputs (
    job INTEGER NOT NULL REFERENCES jobs(id) ON DELETE CASCADE,
    frame INTEGER NOT NULL,
    seq INTEGER NOT NULL,
    path TEXT NOT NULL,
    PRIMARY KEY (job, frame)
) WITHOUT ROWID;
CREATE TABLE tiles (
    job INTEGER NOT NULL REFERENCES jobs(id) ON DELETE CASCADE,
    frame INTEGER NOT NULL,
    unit INTEGER NOT NULL,
    pixels BLOB NOT NULL,
    checksum INTEGER NOT NULL,
    PRIMARY KEY (job, frame, unit)
);
CREATE TABLE redo (
    job INTEGER NOT NULL REFERENCES jobs(id) ON DELETE CASCADE,
    frame INTEGER NOT NULL,
    PRIMARY KEY (job, frame)
) WITHOUT ROWID;
CREATE TABLE meta (
    key TEXT PRIMARY KEY,
    value INTEGER NOT NULL
) WITHOUT ROWID;
INSERT INTO meta (key, value) VALUES ('generation', 0);
";

/// What version 2 added to version 1's schema.
const SCHEMA_1_TO_2: &str = "
CREATE TABLE redo (
    job INTEGER NOT NULL REFERENCES jobs(id) ON DELETE CASCADE,
    frame INTEGER NOT NULL,
    PRIMARY KEY (job, frame)
) WITHOUT ROWID;
";

/// What version 3 added to version 2's schema (the checksums are filled in
/// by [`Store::prepare`]).
const SCHEMA_2_TO_3: &str = "
ALTER TABLE tiles ADD COLUMN checksum INTEGER NOT NULL DEFAULT 0;
CREATE TABLE meta (
    key TEXT PRIMARY KEY,
    value INTEGER NOT NULL
) WITHOUT ROWID;
INSERT INTO meta (key, value)
    VALUES ('generation', coalesce((SELECT seq FROM sqlite_sequence WHERE name = 'jobs'), 0));
";

/// The tables of [`SCHEMA`] and their columns, in order: what [`Store::open`]
/// checks an existing database against.
const TABLES: [(&str, &[&str]); 5] = [
    (
        "jobs",
        &[
            "id",
            "spec_json",
            "priority",
            "state",
            "error",
            "frames_done",
            "submitted_unix_ms",
        ],
    ),
    ("outputs", &["job", "frame", "seq", "path"]),
    ("tiles", &["job", "frame", "unit", "pixels", "checksum"]),
    ("redo", &["job", "frame"]),
    ("meta", &["key", "value"]),
];

/// The checksum stored with a tile: the XXH3-64 of its bytes, as SQLite's
/// signed integer.
pub fn tile_checksum(pixels: &[u8]) -> i64 {
    xxhash_rust::xxh3::xxh3_64(pixels) as i64
}

/// Why the store failed. Every message names the data directory or the
/// database file.
#[derive(Debug, thiserror::Error)]
pub enum StoreError {
    /// The data directory cannot be created, or files cannot be created in it.
    #[error("{dir}: cannot use as the data directory: {source}")]
    Dir {
        /// The data directory.
        dir: PathBuf,
        /// What the operating system said.
        source: std::io::Error,
    },
    /// The lock file could not be locked or written (for a reason other than
    /// another coordinator holding it).
    #[error("{file}: cannot lock the data directory: {source}")]
    Lock {
        /// The lock file.
        file: PathBuf,
        /// What the operating system said.
        source: std::io::Error,
    },
    /// Another coordinator (or another [`Store`] in this process) holds the lock.
    #[error(
        "{dir} is in use by another coordinator (pid {}): stop it first, or choose another --data",
        pid.map_or_else(|| "unknown".to_string(), |p| p.to_string())
    )]
    InUse {
        /// The data directory.
        dir: PathBuf,
        /// The holder's pid, as written in the lock file (`None` if unreadable).
        pid: Option<u32>,
    },
    /// The database was written by a newer coordinator.
    #[error(
        "{file} was written by a newer coordinator (store version {version}; this build reads up to {STORE_VERSION})"
    )]
    Newer {
        /// The database file.
        file: PathBuf,
        /// Its store version.
        version: i64,
    },
    /// The file is not a SQLite database, or not one of the store's schema, or
    /// holds a row the store cannot read.
    #[error("{file}: the store is damaged or not a coordinator store: {message}; {RESTORE_HINT}")]
    Corrupt {
        /// The database file.
        file: PathBuf,
        /// SQLite's message, or what is wrong with the schema or row.
        message: String,
    },
    /// No job has this id.
    #[error("{file}: no job {id}")]
    NoJob {
        /// The database file.
        file: PathBuf,
        /// The id asked for.
        id: u64,
    },
    /// SQLite cannot keep the database in WAL journal mode (on a file system
    /// without shared memory, for one).
    #[error("{file}: cannot use SQLite's WAL journal mode (the database stays in mode {mode})")]
    NoWal {
        /// The database file.
        file: PathBuf,
        /// The journal mode SQLite kept.
        mode: String,
    },
    /// The database holds fewer jobs than were given out: its WAL was lost or
    /// truncated, or an older copy was put back.
    #[error(
        "{file}: the store is older than its generation file {generation_file}: it has given out \
         job ids up to {stored}, the file says {expected}, so jobs committed since are missing (a \
         lost or truncated {file}-wal, or an older copy put back). Restore the latest backup, or \
         start with --accept-older-store to go on with what the store holds"
    )]
    Older {
        /// The database file.
        file: PathBuf,
        /// The generation file.
        generation_file: PathBuf,
        /// The highest id the database has given out.
        stored: u64,
        /// The highest id the generation file records.
        expected: u64,
    },
    /// The generation file cannot be read or written, or holds no number.
    #[error("{file}: cannot use the store's generation file: {message}")]
    Generation {
        /// The generation file.
        file: PathBuf,
        /// What is wrong.
        message: String,
    },
    /// SQLite cannot read the file at open (an I/O error).
    #[error(
        "{file}: cannot read the store ({source}): check the disk it is on; if the file is damaged, {RESTORE_HINT}"
    )]
    Unreadable {
        /// The database file.
        file: PathBuf,
        /// SQLite's error.
        source: rusqlite::Error,
    },
    /// SQLite failed (disk full, I/O error, …).
    #[error("{file}: {source}")]
    Sqlite {
        /// The database file.
        file: PathBuf,
        /// SQLite's error.
        source: rusqlite::Error,
    },
}

/// A job as stored.
#[derive(Clone, Debug, PartialEq)]
pub struct StoredJob {
    /// The job's id (increasing, never reused).
    pub id: u64,
    /// The [`JobSpec`](crate::service::jobs::JobSpec) as submitted, as JSON.
    pub spec_json: String,
    /// Its priority.
    pub priority: i32,
    /// Its state.
    pub state: JobState,
    /// Why it failed.
    pub error: Option<String>,
    /// Frames finished and written.
    pub frames_done: u32,
    /// The files written, in the order they were finished.
    pub outputs: Vec<String>,
    /// Finished frames to render again (they hold a liar's tiles).
    pub redo: Vec<u32>,
    /// When it was submitted (milliseconds since the Unix epoch).
    pub submitted_unix_ms: u64,
}

/// The persistent store: one SQLite connection, and the lock on the data
/// directory held as long as the store lives.
///
/// `Send` but not `Sync` (the connection caches prepared statements): share it
/// behind a `Mutex`.
pub struct Store {
    /// The connection; declared before `_lock` so that it closes first.
    conn: Connection,
    /// The database file.
    path: PathBuf,
    /// The locked `DIR/lock`; closing it releases the lock.
    _lock: File,
}

impl std::fmt::Debug for Store {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Store").field("path", &self.path).finish()
    }
}

impl StoreError {
    /// Whether the failure is the disk's room (SQLITE_FULL): the service
    /// answers 507 rather than 503.
    pub fn is_full(&self) -> bool {
        matches!(self, StoreError::Sqlite { source, .. }
            if source.sqlite_error_code() == Some(ErrorCode::DiskFull))
    }
}

/// The tiles of a frame as read back: those whose bytes match their checksum
/// (`(unit, pixels)` by unit), and the units of those that do not.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct FrameTiles {
    /// The sound tiles.
    pub tiles: Vec<(u32, Vec<u8>)>,
    /// The units whose stored bytes no longer match their checksum.
    pub rotten: Vec<u32>,
}

impl Store {
    /// Opens the store in `dir` (created if missing): locks `dir/lock`, then
    /// opens `dir/farm.sqlite`, creating the schema if the database is new and
    /// checking the store version, the schema, SQLite's `quick_check` and the
    /// generation if not. An older store than its generation file is refused.
    pub fn open(dir: &Path) -> Result<Store, StoreError> {
        Store::open_with(dir, false)
    }

    /// [`Store::open`]; with `accept_older`, a store older than its generation
    /// file is opened (with a warning) and its id sequence moved past the
    /// file's value.
    pub fn open_with(dir: &Path, accept_older: bool) -> Result<Store, StoreError> {
        let dir_error = |source| StoreError::Dir {
            dir: dir.to_path_buf(),
            source,
        };
        std::fs::create_dir_all(dir).map_err(dir_error)?;
        let lock = lock_dir(dir)?;
        let path = dir.join(DB_FILE);
        let conn = Connection::open(&path).map_err(|source| StoreError::Sqlite {
            file: path.clone(),
            source,
        })?;
        let store = Store {
            conn,
            path,
            _lock: lock,
        };
        store.prepare()?;
        store.quick_check()?;
        store.check_generation(accept_older)?;
        Ok(store)
    }

    /// The generation file beside the database.
    fn generation_file(&self) -> PathBuf {
        self.path.with_file_name(GENERATION_FILE)
    }

    /// The highest job id the database has given out.
    fn generation(&self) -> Result<u64, StoreError> {
        let g: i64 = self
            .conn
            .prepare_cached("SELECT value FROM meta WHERE key = 'generation'")
            .and_then(|mut s| s.query_row([], |r| r.get(0)))
            .optional()
            .map_err(|e| self.opening(e))?
            .ok_or_else(|| self.corrupt("the generation row of table meta is missing".into()))?;
        u64::try_from(g).map_err(|_| self.corrupt(format!("negative generation {g}")))
    }

    /// Compares the database's generation with the file's (refusing an older
    /// database unless `accept_older`), then writes the file.
    fn check_generation(&self, accept_older: bool) -> Result<(), StoreError> {
        let file = self.generation_file();
        let bad = |message: String| StoreError::Generation {
            file: file.clone(),
            message,
        };
        let expected = match std::fs::read_to_string(&file) {
            Ok(text) => Some(text.trim().parse::<u64>().map_err(|_| {
                bad(format!(
                    "it holds {:?}, not a number; if the store is sound, delete the file",
                    text.trim()
                ))
            })?),
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => None,
            Err(e) => return Err(bad(e.to_string())),
        };
        let stored = self.generation()?;
        match expected {
            Some(expected) if expected > stored && !accept_older => {
                return Err(StoreError::Older {
                    file: self.path.clone(),
                    generation_file: file,
                    stored,
                    expected,
                });
            }
            Some(expected) if expected > stored => {
                tracing::warn!(
                    "{}: the store is older than its generation file (ids up to {stored}, the file \
                     says {expected}): going on with what it holds (--accept-older-store); new \
                     job ids start after {expected}",
                    self.path.display()
                );
                self.transaction(|conn| {
                    conn.execute(
                        "UPDATE meta SET value = ?1 WHERE key = 'generation'",
                        params![expected],
                    )?;
                    conn.execute(
                        "UPDATE sqlite_sequence SET seq = ?1 WHERE name = 'jobs' AND seq < ?1",
                        params![expected],
                    )?;
                    conn.execute(
                        "INSERT INTO sqlite_sequence (name, seq) SELECT 'jobs', ?1 \
                         WHERE NOT EXISTS (SELECT 1 FROM sqlite_sequence WHERE name = 'jobs')",
                        params![expected],
                    )?;
                    Ok(())
                })?;
            }
            _ => {}
        }
        let generation = self.generation()?;
        if expected == Some(generation) {
            // Nothing to write (a full disk does not stop a restart).
            return Ok(());
        }
        write_generation(&file, generation).map_err(|e| bad(e.to_string()))
    }

    /// SQLite's `quick_check` (every page's structure, not the rows' values):
    /// a damaged file is refused.
    fn quick_check(&self) -> Result<(), StoreError> {
        let found: Vec<String> = self
            .conn
            .prepare("PRAGMA quick_check(5)")
            .and_then(|mut s| s.query_map([], |r| r.get(0))?.collect())
            .map_err(|e| match e.sqlite_error_code() {
                // Damage the check cannot walk past.
                Some(ErrorCode::DatabaseCorrupt) => {
                    self.corrupt(format!("SQLite's quick_check stopped: {e}"))
                }
                _ => self.opening(e),
            })?;
        if found.len() == 1 && found[0] == "ok" {
            return Ok(());
        }
        Err(self.corrupt(format!("SQLite's quick_check found: {}", found.join("; "))))
    }

    /// Copies the WAL into the database and truncates it (a clean stop), so
    /// the database file alone holds everything.
    pub fn checkpoint(&self) -> Result<(), StoreError> {
        let (busy, _, _): (i64, i64, i64) = self
            .conn
            .query_row("PRAGMA wal_checkpoint(TRUNCATE)", [], |r| {
                Ok((r.get(0)?, r.get(1)?, r.get(2)?))
            })
            .map_err(|e| self.sqlite(e))?;
        if busy != 0 {
            return Err(self.sqlite(rusqlite::Error::SqliteFailure(
                rusqlite::ffi::Error::new(rusqlite::ffi::SQLITE_BUSY),
                Some("the checkpoint could not finish: another connection reads the store".into()),
            )));
        }
        Ok(())
    }

    /// A write of a large tile's size (a row added and deleted in one
    /// committed transaction), to learn whether the store can take tiles
    /// again.
    pub fn probe(&self) -> Result<(), StoreError> {
        self.transaction(|conn| {
            conn.prepare_cached(
                "INSERT OR REPLACE INTO meta (key, value) VALUES ('probe', zeroblob(262144))",
            )?
            .execute([])?;
            conn.prepare_cached("DELETE FROM meta WHERE key = 'probe'")?
                .execute([])?;
            Ok(())
        })
    }

    /// The database file.
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// Adds a queued job; returns its id, greater than every id given before.
    /// The id is returned only once its transaction is committed; the
    /// generation file then records it.
    pub fn insert_job(
        &self,
        spec_json: &str,
        priority: i32,
        submitted_unix_ms: u64,
    ) -> Result<u64, StoreError> {
        let id: i64 = self.transaction(|conn| {
            let id: i64 = conn
                .prepare_cached(
                    "INSERT INTO jobs (spec_json, priority, state, submitted_unix_ms) \
                     VALUES (?1, ?2, ?3, ?4) RETURNING id",
                )?
                .query_row(
                    params![
                        spec_json,
                        priority,
                        JobState::Queued.as_str(),
                        submitted_unix_ms
                    ],
                    |r| r.get(0),
                )?;
            conn.prepare_cached("UPDATE meta SET value = max(value, ?1) WHERE key = 'generation'")?
                .execute(params![id])?;
            Ok(id)
        })?;
        let id = u64::try_from(id).map_err(|_| self.corrupt(format!("negative job id {id}")))?;
        if let Err(e) = write_generation(&self.generation_file(), id) {
            // The job is committed; the file lags, which only weakens the
            // check of a later open.
            tracing::warn!(
                "{}: cannot record generation {id}: {e}",
                self.generation_file().display()
            );
        }
        Ok(id)
    }

    /// Sets a job's state and error. A final state (done, failed, cancelled)
    /// also deletes the job's remaining tiles, in the same transaction.
    pub fn set_state(
        &self,
        id: u64,
        state: JobState,
        error: Option<&str>,
    ) -> Result<(), StoreError> {
        self.transaction(|conn| {
            let changed = conn
                .prepare_cached("UPDATE jobs SET state = ?2, error = ?3 WHERE id = ?1")?
                .execute(params![id, state.as_str(), error])?;
            if changed == 0 {
                return Ok(Err(id));
            }
            if state.is_final() {
                conn.prepare_cached("DELETE FROM tiles WHERE job = ?1")?
                    .execute(params![id])?;
            }
            Ok(Ok(()))
        })?
        .map_err(|id| self.no_job(id))
    }

    /// Stores the tile of unit `unit` of frame `frame` of job `job`. A second
    /// put of the same unit replaces the first. A tile of a job that does not
    /// exist or has ended is not stored (a worker's late answer after a cancel
    /// must not leave tiles that nothing deletes).
    pub fn put_tile(
        &self,
        job: u64,
        frame: u32,
        unit: u32,
        pixels: &[u8],
    ) -> Result<(), StoreError> {
        let checksum = tile_checksum(pixels);
        // One statement in autocommit mode: it commits in its own step, and
        // `execute` returns that step's error, a failed commit included.
        self.conn
            .prepare_cached(
                "INSERT OR REPLACE INTO tiles (job, frame, unit, pixels, checksum) \
                 SELECT ?1, ?2, ?3, ?4, ?5 FROM jobs \
                 WHERE id = ?1 AND state IN ('queued', 'running')",
            )
            .and_then(|mut s| s.execute(params![job, frame, unit, pixels, checksum]))
            .map_err(|e| self.sqlite(e))?;
        Ok(())
    }

    /// Records that finished frames of job `job` are to be rendered again
    /// (a worker caught lying had delivered some of their tiles), until
    /// [`Store::finish_frame`] records each of them again.
    pub fn add_redo(&self, job: u64, frames: &[u32]) -> Result<(), StoreError> {
        self.transaction(|conn| {
            let mut insert = conn.prepare_cached(
                "INSERT OR IGNORE INTO redo (job, frame) SELECT ?1, ?2 FROM jobs \
                 WHERE id = ?1 AND state IN ('queued', 'running')",
            )?;
            for &frame in frames {
                insert.execute(params![job, frame])?;
            }
            Ok(())
        })
    }

    /// Records frame `frame` of job `job` as written to `output`, in one
    /// transaction: deletes the frame's tiles, appends `output` to the job's
    /// outputs and counts the frame in `frames_done`. Finishing a frame already
    /// finished deletes its tiles and its place among the frames to render
    /// again (it is not counted twice).
    pub fn finish_frame(&self, job: u64, frame: u32, output: &str) -> Result<(), StoreError> {
        self.transaction(|conn| {
            let done: Option<u32> = conn
                .prepare_cached("SELECT frames_done FROM jobs WHERE id = ?1")?
                .query_row(params![job], |r| r.get(0))
                .optional()?;
            let Some(done) = done else {
                return Ok(Err(job));
            };
            conn.prepare_cached("DELETE FROM tiles WHERE job = ?1 AND frame = ?2")?
                .execute(params![job, frame])?;
            conn.prepare_cached("DELETE FROM redo WHERE job = ?1 AND frame = ?2")?
                .execute(params![job, frame])?;
            let added = conn
                .prepare_cached(
                    "INSERT INTO outputs (job, frame, seq, path) VALUES (?1, ?2, ?3, ?4) \
                     ON CONFLICT (job, frame) DO NOTHING",
                )?
                .execute(params![job, frame, done, output])?;
            if added == 1 {
                conn.prepare_cached("UPDATE jobs SET frames_done = frames_done + 1 WHERE id = ?1")?
                    .execute(params![job])?;
            }
            Ok(Ok(()))
        })?
        .map_err(|id| self.no_job(id))
    }

    /// Deletes a job with its outputs and tiles. Its id is not given again.
    pub fn delete_job(&self, id: u64) -> Result<(), StoreError> {
        self.transaction(|conn| {
            // The foreign keys cascade to `outputs` and `tiles`.
            let changed = conn
                .prepare_cached("DELETE FROM jobs WHERE id = ?1")?
                .execute(params![id])?;
            Ok(if changed == 0 { Err(id) } else { Ok(()) })
        })?
        .map_err(|id| self.no_job(id))
    }

    /// Every job, by id ascending.
    pub fn jobs(&self) -> Result<Vec<StoredJob>, StoreError> {
        type Row = (u64, String, i32, String, Option<String>, u32, u64);
        // One read transaction: the rows and the outputs are of the same moment.
        let (rows, outputs, redo) = self
            .transaction(|conn| {
                let rows: Vec<Row> = conn
                .prepare_cached(
                    "SELECT id, spec_json, priority, state, error, frames_done, submitted_unix_ms \
                     FROM jobs ORDER BY id",
                )?
                .query_map([], |r| {
                    Ok((
                        r.get(0)?,
                        r.get(1)?,
                        r.get(2)?,
                        r.get(3)?,
                        r.get(4)?,
                        r.get(5)?,
                        r.get(6)?,
                    ))
                })?
                .collect::<rusqlite::Result<_>>()?;
                let outputs: Vec<(u64, String)> = conn
                    .prepare_cached("SELECT job, path FROM outputs ORDER BY job, seq")?
                    .query_map([], |r| Ok((r.get(0)?, r.get(1)?)))?
                    .collect::<rusqlite::Result<_>>()?;
                let redo: Vec<(u64, u32)> = conn
                    .prepare_cached("SELECT job, frame FROM redo ORDER BY job, frame")?
                    .query_map([], |r| Ok((r.get(0)?, r.get(1)?)))?
                    .collect::<rusqlite::Result<_>>()?;
                Ok((rows, outputs, redo))
            })
            .map_err(|e| match e {
                StoreError::Sqlite { source, .. } => self.reading(source),
                e => e,
            })?;
        let mut jobs = rows
            .into_iter()
            .map(
                |(id, spec_json, priority, state, error, frames_done, submitted)| {
                    let state = JobState::parse(&state).ok_or_else(|| {
                        self.corrupt(format!("job {id} has an unknown state {state:?}"))
                    })?;
                    Ok(StoredJob {
                        id,
                        spec_json,
                        priority,
                        state,
                        error,
                        frames_done,
                        outputs: Vec::new(),
                        redo: Vec::new(),
                        submitted_unix_ms: submitted,
                    })
                },
            )
            .collect::<Result<Vec<_>, StoreError>>()?;
        for (job, path) in outputs {
            // Both lists are sorted by job; the foreign key guarantees the job.
            if let Ok(i) = jobs.binary_search_by_key(&job, |j| j.id) {
                jobs[i].outputs.push(path);
            }
        }
        for (job, frame) in redo {
            if let Ok(i) = jobs.binary_search_by_key(&job, |j| j.id) {
                jobs[i].redo.push(frame);
            }
        }
        Ok(jobs)
    }

    /// The frames of job `job` that are finished, in the order they were.
    pub fn finished_frames(&self, job: u64) -> Result<Vec<u32>, StoreError> {
        self.conn
            .prepare_cached("SELECT frame FROM outputs WHERE job = ?1 ORDER BY seq")
            .and_then(|mut s| s.query_map(params![job], |r| r.get(0))?.collect())
            .map_err(|e| self.sqlite(e))
    }

    /// The `(frame, unit)` of every tile stored for job `job`, in order,
    /// without reading the pixels.
    pub fn tile_keys(&self, job: u64) -> Result<Vec<(u32, u32)>, StoreError> {
        self.conn
            .prepare_cached("SELECT frame, unit FROM tiles WHERE job = ?1 ORDER BY frame, unit")
            .and_then(|mut s| {
                s.query_map(params![job], |r| Ok((r.get(0)?, r.get(1)?)))?
                    .collect()
            })
            .map_err(|e| self.sqlite(e))
    }

    /// The stored tiles of frame `frame` of job `job`, each checked against
    /// its checksum: the sound ones, and the units of those that are not.
    pub fn tiles(&self, job: u64, frame: u32) -> Result<FrameTiles, StoreError> {
        let rows: Vec<(u32, Vec<u8>, i64)> = self
            .conn
            .prepare_cached(
                "SELECT unit, pixels, checksum FROM tiles WHERE job = ?1 AND frame = ?2 ORDER BY unit",
            )
            .and_then(|mut s| {
                s.query_map(params![job, frame], |r| Ok((r.get(0)?, r.get(1)?, r.get(2)?)))?
                    .collect()
            })
            .map_err(|e| self.reading(e))?;
        let mut out = FrameTiles::default();
        for (unit, pixels, checksum) in rows {
            if tile_checksum(&pixels) == checksum {
                out.tiles.push((unit, pixels));
            } else {
                out.rotten.push(unit);
            }
        }
        Ok(out)
    }

    /// Deletes the tiles of `units` of frame `frame` of job `job` (tiles
    /// found rotten).
    pub fn drop_tiles(&self, job: u64, frame: u32, units: &[u32]) -> Result<(), StoreError> {
        self.transaction(|conn| {
            let mut delete = conn
                .prepare_cached("DELETE FROM tiles WHERE job = ?1 AND frame = ?2 AND unit = ?3")?;
            for &unit in units {
                delete.execute(params![job, frame, unit])?;
            }
            Ok(())
        })
    }

    /// How many tiles are stored, over every job.
    pub fn tile_count(&self) -> Result<u64, StoreError> {
        self.conn
            .prepare_cached("SELECT count(*) FROM tiles")
            .and_then(|mut s| s.query_row([], |r| r.get(0)))
            .map_err(|e| self.sqlite(e))
    }

    /// Configures the connection and brings the database to the current
    /// schema (new database) or checks it (existing one).
    fn prepare(&self) -> Result<(), StoreError> {
        let conn = &self.conn;
        conn.busy_timeout(BUSY_TIMEOUT)
            .map_err(|e| self.sqlite(e))?;
        // The first read of the file: a file that is not a database fails here.
        let version: i64 = conn
            .pragma_query_value(None, "user_version", |r| r.get(0))
            .map_err(|e| self.opening(e))?;
        if version > STORE_VERSION {
            return Err(StoreError::Newer {
                file: self.path.clone(),
                version,
            });
        }
        let tables: i64 = conn
            .query_row("SELECT count(*) FROM sqlite_master", [], |r| r.get(0))
            .map_err(|e| self.opening(e))?;
        if version == 0 && tables > 0 {
            return Err(self.corrupt(format!(
                "it holds {tables} schema objects but no store version"
            )));
        }
        if version < 0 {
            return Err(self.corrupt(format!("store version {version}")));
        }
        let mode: String = conn
            .pragma_update_and_check(None, "journal_mode", "WAL", |r| r.get(0))
            .map_err(|e| self.opening(e))?;
        if !mode.eq_ignore_ascii_case("wal") {
            return Err(StoreError::NoWal {
                file: self.path.clone(),
                mode,
            });
        }
        conn.execute_batch(&format!(
            "PRAGMA synchronous = NORMAL; PRAGMA foreign_keys = ON; \
             PRAGMA journal_size_limit = {JOURNAL_SIZE_LIMIT};"
        ))
        .map_err(|e| self.sqlite(e))?;
        conn.set_prepared_statement_cache_capacity(32);
        if version == 0 {
            self.transaction(|conn| {
                conn.execute_batch(SCHEMA)?;
                conn.pragma_update(None, "user_version", STORE_VERSION)?;
                Ok(())
            })
        } else {
            if version == 1 {
                // Version 1's tables must be sound before they are extended.
                self.check_tables(&[TABLES[0], TABLES[1], ("tiles", &TABLES[2].1[..4])])?;
                self.transaction(|conn| {
                    conn.execute_batch(SCHEMA_1_TO_2)?;
                    conn.pragma_update(None, "user_version", 2)?;
                    Ok(())
                })?;
            }
            if version <= 2 {
                self.check_tables(&[
                    TABLES[0],
                    TABLES[1],
                    ("tiles", &TABLES[2].1[..4]),
                    TABLES[3],
                ])?;
                self.transaction(|conn| {
                    conn.execute_batch(SCHEMA_2_TO_3)?;
                    // Each tile's checksum, from its bytes as they are now.
                    let keys: Vec<i64> = conn
                        .prepare("SELECT rowid FROM tiles")?
                        .query_map([], |r| r.get(0))?
                        .collect::<rusqlite::Result<_>>()?;
                    let mut read = conn.prepare("SELECT pixels FROM tiles WHERE rowid = ?1")?;
                    let mut write =
                        conn.prepare("UPDATE tiles SET checksum = ?2 WHERE rowid = ?1")?;
                    for key in keys {
                        let pixels: Vec<u8> = read.query_row(params![key], |r| r.get(0))?;
                        write.execute(params![key, tile_checksum(&pixels)])?;
                    }
                    conn.pragma_update(None, "user_version", STORE_VERSION)?;
                    Ok(())
                })?;
            }
            self.check_schema()
        }
    }

    /// Checks that every table of the schema is there with its columns.
    fn check_schema(&self) -> Result<(), StoreError> {
        self.check_tables(&TABLES)
    }

    /// Checks that each of `tables` is there with its columns.
    fn check_tables(&self, tables: &[(&str, &[&str])]) -> Result<(), StoreError> {
        for &(table, expected) in tables {
            let columns: Vec<String> = self
                .conn
                .prepare("SELECT name FROM pragma_table_info(?1) ORDER BY cid")
                .and_then(|mut s| s.query_map([table], |r| r.get(0))?.collect())
                .map_err(|e| self.opening(e))?;
            if columns.is_empty() {
                return Err(self.corrupt(format!("table {table} is missing")));
            }
            if columns != expected {
                return Err(self.corrupt(format!(
                    "table {table} has columns ({}), expected ({})",
                    columns.join(", "),
                    expected.join(", ")
                )));
            }
        }
        Ok(())
    }

    /// Runs `f` in one transaction, committed if `f` returns `Ok` (whatever
    /// the value inside), rolled back otherwise.
    fn transaction<T>(
        &self,
        f: impl FnOnce(&Connection) -> rusqlite::Result<T>,
    ) -> Result<T, StoreError> {
        let tx = self
            .conn
            .unchecked_transaction()
            .map_err(|e| self.sqlite(e))?;
        let value = f(&tx).map_err(|e| self.sqlite(e))?;
        tx.commit().map_err(|e| self.sqlite(e))?;
        Ok(value)
    }

    fn sqlite(&self, source: rusqlite::Error) -> StoreError {
        StoreError::Sqlite {
            file: self.path.clone(),
            source,
        }
    }

    fn corrupt(&self, message: String) -> StoreError {
        StoreError::Corrupt {
            file: self.path.clone(),
            message,
        }
    }

    fn no_job(&self, id: u64) -> StoreError {
        StoreError::NoJob {
            file: self.path.clone(),
            id,
        }
    }

    /// An error while reading an existing database at open: a file that is not
    /// a database or is damaged is corrupt; any other failure is SQLite's.
    fn opening(&self, e: rusqlite::Error) -> StoreError {
        match e.sqlite_error_code() {
            Some(ErrorCode::NotADatabase | ErrorCode::DatabaseCorrupt) => {
                self.corrupt(e.to_string())
            }
            Some(ErrorCode::SystemIoFailure) => StoreError::Unreadable {
                file: self.path.clone(),
                source: e,
            },
            _ => self.reading(e),
        }
    }

    /// An error while reading rows: a value of the wrong type or bytes that
    /// are not text are a damaged store, as is a damaged page.
    fn reading(&self, e: rusqlite::Error) -> StoreError {
        match &e {
            rusqlite::Error::FromSqlConversionFailure(..)
            | rusqlite::Error::InvalidColumnType(..)
            | rusqlite::Error::Utf8Error(..)
            | rusqlite::Error::IntegralValueOutOfRange(..) => {
                self.corrupt(format!("a row cannot be read: {e}"))
            }
            _ if matches!(
                e.sqlite_error_code(),
                Some(ErrorCode::NotADatabase | ErrorCode::DatabaseCorrupt)
            ) =>
            {
                self.corrupt(e.to_string())
            }
            _ => self.sqlite(e),
        }
    }
}

/// Writes `generation` to `file` through a temporary file and a rename, so
/// the file always holds a whole number.
fn write_generation(file: &Path, generation: u64) -> std::io::Result<()> {
    let tmp = file.with_extension("tmp");
    std::fs::write(&tmp, format!("{generation}\n"))?;
    std::fs::rename(&tmp, file)
}

/// Opens `dir/farm.sqlite` read-only, without the lock (a running
/// coordinator may hold it): for [`check`] and [`backup`].
fn open_read_only(dir: &Path) -> Result<(Connection, PathBuf), StoreError> {
    let path = dir.join(DB_FILE);
    if !path.is_file() {
        return Err(StoreError::Dir {
            dir: dir.to_path_buf(),
            source: std::io::Error::new(
                std::io::ErrorKind::NotFound,
                format!("no store: {} does not exist", path.display()),
            ),
        });
    }
    let conn = Connection::open_with_flags(
        &path,
        OpenFlags::SQLITE_OPEN_READ_ONLY | OpenFlags::SQLITE_OPEN_NO_MUTEX,
    )
    .map_err(|source| StoreError::Unreadable {
        file: path.clone(),
        source,
    })?;
    conn.busy_timeout(BUSY_TIMEOUT)
        .map_err(|source| StoreError::Sqlite {
            file: path.clone(),
            source,
        })?;
    Ok((conn, path))
}

/// What [`check`] found.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct CheckReport {
    /// The database file.
    pub file: PathBuf,
    /// Jobs stored.
    pub jobs: u64,
    /// Tiles whose checksum was checked.
    pub tiles: u64,
    /// What is wrong: SQLite's `integrity_check` findings, then each tile
    /// whose bytes do not match its checksum. Empty when sound.
    pub problems: Vec<String>,
}

/// `coordinator store check`: SQLite's full `integrity_check` of the store
/// in `dir`, and every stored tile's checksum. Reads only; a running
/// coordinator may keep writing meanwhile.
pub fn check(dir: &Path) -> Result<CheckReport, StoreError> {
    let (conn, path) = open_read_only(dir)?;
    let damaged = |e: rusqlite::Error| StoreError::Corrupt {
        file: path.clone(),
        message: e.to_string(),
    };
    let version: i64 = conn
        .pragma_query_value(None, "user_version", |r| r.get(0))
        .map_err(damaged)?;
    if version != STORE_VERSION {
        return Err(StoreError::Corrupt {
            file: path.clone(),
            message: format!(
                "store version {version}; `store check` reads version {STORE_VERSION} (start \
                 the coordinator on it once to bring it up to date)"
            ),
        });
    }
    let mut report = CheckReport {
        file: path.clone(),
        ..CheckReport::default()
    };
    let found: Vec<String> = conn
        .prepare("PRAGMA integrity_check(100)")
        .and_then(|mut s| s.query_map([], |r| r.get(0))?.collect())
        .map_err(damaged)?;
    if !(found.len() == 1 && found[0] == "ok") {
        report
            .problems
            .extend(found.into_iter().map(|f| format!("integrity_check: {f}")));
    }
    report.jobs = conn
        .query_row("SELECT count(*) FROM jobs", [], |r| r.get(0))
        .map_err(damaged)?;
    let mut rows = conn
        .prepare("SELECT job, frame, unit, pixels, checksum FROM tiles ORDER BY job, frame, unit")
        .map_err(damaged)?;
    let mut rows = rows.query([]).map_err(damaged)?;
    while let Some(row) = rows.next().map_err(damaged)? {
        let key: (u64, u32, u32) = (
            row.get(0).map_err(damaged)?,
            row.get(1).map_err(damaged)?,
            row.get(2).map_err(damaged)?,
        );
        let pixels = row.get_ref(3).map_err(damaged)?.as_blob().map_err(|e| {
            damaged(rusqlite::Error::FromSqlConversionFailure(
                3,
                rusqlite::types::Type::Blob,
                Box::new(e),
            ))
        })?;
        let checksum: i64 = row.get(4).map_err(damaged)?;
        report.tiles += 1;
        if tile_checksum(pixels) != checksum {
            report.problems.push(format!(
                "job {} frame {} unit {}: the tile's bytes do not match its checksum (it is \
                 dropped and rendered again when the job resumes)",
                key.0, key.1, key.2
            ));
        }
    }
    Ok(report)
}

/// `coordinator store backup`: a consistent copy of the store in `dir` to
/// `dest` (SQLite's online backup API, in one step, so the copy is of one
/// moment even while a coordinator writes), written beside `dest` and renamed
/// onto it. Returns the copy's highest job id.
pub fn backup(dir: &Path, dest: &Path) -> Result<u64, StoreError> {
    let (src, path) = open_read_only(dir)?;
    let tmp = dest.with_extension("partial");
    let dest_error = |source: rusqlite::Error| StoreError::Sqlite {
        file: dest.to_path_buf(),
        source,
    };
    let _ = std::fs::remove_file(&tmp);
    {
        let mut out = Connection::open(&tmp).map_err(dest_error)?;
        copy_all(&src, &mut out).map_err(|source| StoreError::Sqlite {
            file: path.clone(),
            source,
        })?;
        // The copy is one file: its own journal in rollback mode while moved.
        out.pragma_update(None, "journal_mode", "DELETE")
            .map_err(dest_error)?;
    }
    let generation: i64 = Connection::open_with_flags(&tmp, OpenFlags::SQLITE_OPEN_READ_ONLY)
        .and_then(|c| {
            c.query_row("SELECT value FROM meta WHERE key = 'generation'", [], |r| {
                r.get(0)
            })
        })
        .map_err(dest_error)?;
    std::fs::rename(&tmp, dest).map_err(|source| StoreError::Dir {
        dir: dest.to_path_buf(),
        source,
    })?;
    Ok(generation.max(0) as u64)
}

/// Copies every page of `src` to `out` in one backup step (one read
/// transaction, so one moment of the source), retrying while a writer holds
/// the lock (at most 200 times 50 ms).
fn copy_all(src: &Connection, out: &mut Connection) -> rusqlite::Result<()> {
    use rusqlite::backup::{Backup, StepResult};
    let backup = Backup::new(src, out)?;
    for _ in 0..200 {
        match backup.step(-1)? {
            StepResult::Done => return Ok(()),
            StepResult::More | StepResult::Busy | StepResult::Locked => {
                std::thread::sleep(Duration::from_millis(50));
            }
            _ => std::thread::sleep(Duration::from_millis(50)),
        }
    }
    Err(rusqlite::Error::SqliteFailure(
        rusqlite::ffi::Error::new(rusqlite::ffi::SQLITE_BUSY),
        Some("the store stayed locked for 10 s".into()),
    ))
}

/// Takes the exclusive lock on `dir/lock` (without waiting) and writes this
/// process's pid into it.
fn lock_dir(dir: &Path) -> Result<File, StoreError> {
    let path = dir.join(LOCK_FILE);
    let mut file = OpenOptions::new()
        .read(true)
        .write(true)
        .create(true)
        .truncate(false)
        .open(&path)
        .map_err(|source| StoreError::Dir {
            dir: dir.to_path_buf(),
            source,
        })?;
    // SAFETY: flock only reads the descriptor, which `file` keeps open.
    let locked = unsafe { libc::flock(file.as_raw_fd(), libc::LOCK_EX | libc::LOCK_NB) };
    if locked != 0 {
        let err = std::io::Error::last_os_error();
        if err.raw_os_error() == Some(libc::EWOULDBLOCK) {
            let mut text = String::new();
            let pid = file
                .read_to_string(&mut text)
                .ok()
                .and_then(|_| text.trim().parse().ok());
            return Err(StoreError::InUse {
                dir: dir.to_path_buf(),
                pid,
            });
        }
        return Err(StoreError::Lock {
            file: path,
            source: err,
        });
    }
    let lock_error = |source| StoreError::Lock {
        file: path.clone(),
        source,
    };
    file.set_len(0).map_err(lock_error)?;
    file.write_all(format!("{}\n", std::process::id()).as_bytes())
        .map_err(lock_error)?;
    Ok(file)
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::sync::atomic::{AtomicU64, Ordering};

    /// A fresh directory under the system's temporary directory, removed on drop.
    struct TempDir(PathBuf);

    impl TempDir {
        fn new(name: &str) -> TempDir {
            static COUNTER: AtomicU64 = AtomicU64::new(0);
            let n = COUNTER.fetch_add(1, Ordering::Relaxed);
            let path = std::env::temp_dir().join(format!(
                "coordinator-store-{}-{n}-{name}",
                std::process::id()
            ));
            let _ = std::fs::remove_dir_all(&path);
            TempDir(path)
        }
    }

    impl Drop for TempDir {
        fn drop(&mut self) {
            let _ = std::fs::remove_dir_all(&self.0);
        }
    }

    /// Version 1's schema: jobs and outputs as now, tiles without checksums.
    fn schema_1() -> String {
        let jobs_and_outputs = SCHEMA
            .split("CREATE TABLE tiles")
            .next()
            .unwrap_or_default();
        format!(
            "{jobs_and_outputs}
            CREATE TABLE tiles (
                job INTEGER NOT NULL REFERENCES jobs(id) ON DELETE CASCADE,
                frame INTEGER NOT NULL,
                unit INTEGER NOT NULL,
                pixels BLOB NOT NULL,
                PRIMARY KEY (job, frame, unit)
            );"
        )
    }

    fn open(dir: &TempDir) -> Store {
        match Store::open(&dir.0) {
            Ok(s) => s,
            Err(e) => panic!("open: {e}"),
        }
    }

    #[test]
    fn jobs_states_and_outputs_round_trip() -> Result<(), StoreError> {
        let dir = TempDir::new("round-trip");
        let store = open(&dir);
        assert_eq!(store.path(), dir.0.join("farm.sqlite"));
        assert!(store.jobs()?.is_empty());
        let a = store.insert_job(r#"{"scene":"a","out":"a.png"}"#, 3, 1_700_000_000_000)?;
        let b = store.insert_job(r#"{"scene":"b","out":"b_##.exr"}"#, -2, 1_700_000_000_001)?;
        assert!(b > a);
        store.set_state(a, JobState::Running, None)?;
        store.finish_frame(a, 0, "a.png")?;
        store.set_state(a, JobState::Done, None)?;
        store.set_state(b, JobState::Running, None)?;
        store.finish_frame(b, 7, "b_07.exr")?;
        store.finish_frame(b, 5, "b_05.exr")?;
        // A repeat is not counted twice.
        store.finish_frame(b, 7, "b_07.exr")?;
        store.set_state(b, JobState::Failed, Some("the scene failed: x"))?;
        let jobs = store.jobs()?;
        assert_eq!(
            jobs,
            vec![
                StoredJob {
                    id: a,
                    spec_json: r#"{"scene":"a","out":"a.png"}"#.into(),
                    priority: 3,
                    state: JobState::Done,
                    error: None,
                    frames_done: 1,
                    outputs: vec!["a.png".into()],
                    redo: Vec::new(),
                    submitted_unix_ms: 1_700_000_000_000,
                },
                StoredJob {
                    id: b,
                    spec_json: r#"{"scene":"b","out":"b_##.exr"}"#.into(),
                    priority: -2,
                    state: JobState::Failed,
                    error: Some("the scene failed: x".into()),
                    frames_done: 2,
                    outputs: vec!["b_07.exr".into(), "b_05.exr".into()],
                    redo: Vec::new(),
                    submitted_unix_ms: 1_700_000_000_001,
                },
            ]
        );
        assert_eq!(store.finished_frames(b)?, vec![7, 5]);
        for state in JobState::ALL {
            store.set_state(a, state, None)?;
            assert_eq!(store.jobs()?[0].state, state);
        }
        Ok(())
    }

    #[test]
    fn unknown_jobs_are_refused() -> Result<(), StoreError> {
        let dir = TempDir::new("unknown");
        let store = open(&dir);
        let e = store.set_state(42, JobState::Running, None);
        assert!(matches!(e, Err(StoreError::NoJob { id: 42, .. })), "{e:?}");
        let e = store.finish_frame(42, 0, "x.png");
        assert!(matches!(e, Err(StoreError::NoJob { id: 42, .. })), "{e:?}");
        let e = store.delete_job(42);
        assert!(matches!(e, Err(StoreError::NoJob { id: 42, .. })), "{e:?}");
        if let Err(e) = store.delete_job(u64::MAX) {
            assert!(e.to_string().contains("farm.sqlite"), "{e}");
        }
        // A tile of no job is not stored.
        store.put_tile(42, 0, 0, b"x")?;
        assert_eq!(store.tile_count()?, 0);
        Ok(())
    }

    #[test]
    fn tiles_are_stored_and_deleted_when_their_frame_or_job_ends() -> Result<(), StoreError> {
        let dir = TempDir::new("tiles");
        let store = open(&dir);
        let a = store.insert_job("{}", 0, 0)?;
        let b = store.insert_job("{}", 0, 0)?;
        store.put_tile(a, 0, 2, &[2; 100])?;
        store.put_tile(a, 0, 0, &[0; 50])?;
        store.put_tile(a, 1, 0, &[10; 10])?;
        store.put_tile(b, 0, 0, &[20; 20])?;
        store.put_tile(b, 3, 1, &[21; 20])?;
        // Idempotent: the second put replaces the first.
        store.put_tile(a, 0, 2, &[3; 100])?;
        assert_eq!(store.tile_count()?, 5);
        assert_eq!(
            store.tiles(a, 0)?.tiles,
            vec![(0, vec![0; 50]), (2, vec![3; 100])]
        );
        assert_eq!(store.tiles(a, 5)?, FrameTiles::default());
        assert_eq!(store.tile_keys(a)?, vec![(0, 0), (0, 2), (1, 0)]);
        store.finish_frame(a, 0, "a0.png")?;
        assert_eq!(store.tiles(a, 0)?, FrameTiles::default());
        assert_eq!(store.tiles(a, 1)?.tiles, vec![(0, vec![10; 10])]);
        assert_eq!(store.tile_count()?, 3);
        // A running state keeps the tiles; a final one deletes them.
        store.set_state(b, JobState::Running, None)?;
        assert_eq!(store.tile_count()?, 3);
        store.set_state(b, JobState::Cancelled, None)?;
        assert_eq!(store.tile_keys(b)?, vec![]);
        assert_eq!(store.tile_count()?, 1);
        // A late tile of an ended job is not stored.
        store.put_tile(b, 0, 0, &[1; 10])?;
        assert_eq!(store.tile_count()?, 1);
        store.delete_job(a)?;
        assert_eq!(store.tile_count()?, 0);
        assert_eq!(store.jobs()?.len(), 1);
        Ok(())
    }

    #[test]
    fn frames_to_render_again_last_until_finished_again() -> Result<(), StoreError> {
        let dir = TempDir::new("redo");
        let store = open(&dir);
        let a = store.insert_job("{}", 0, 0)?;
        store.set_state(a, JobState::Running, None)?;
        for f in 0..3 {
            store.finish_frame(a, f, &format!("a{f}.png"))?;
        }
        store.add_redo(a, &[2, 0])?;
        store.add_redo(a, &[0])?;
        drop(store);
        let store = open(&dir);
        let job = &store.jobs()?[0];
        assert_eq!(job.redo, vec![0, 2]);
        assert_eq!(job.frames_done, 3);
        // Finished again: no longer to render, and not counted twice.
        store.finish_frame(a, 2, "a2.png")?;
        let job = &store.jobs()?[0];
        assert_eq!((job.redo.clone(), job.frames_done), (vec![0], 3));
        assert_eq!(job.outputs, vec!["a0.png", "a1.png", "a2.png"]);
        // An ended job takes none; deleting a job deletes its list.
        store.set_state(a, JobState::Done, None)?;
        store.add_redo(a, &[1])?;
        assert_eq!(store.jobs()?[0].redo, vec![0]);
        store.delete_job(a)?;
        assert!(store.jobs()?.is_empty());
        Ok(())
    }

    #[test]
    fn a_version_1_store_gains_the_redo_table() -> Result<(), Box<dyn std::error::Error>> {
        let dir = TempDir::new("upgrade");
        std::fs::create_dir_all(&dir.0)?;
        let path = dir.0.join("farm.sqlite");
        {
            let conn = Connection::open(&path)?;
            conn.execute_batch(&schema_1())?;
            conn.pragma_update(None, "user_version", 1)?;
            conn.execute(
                "INSERT INTO jobs (spec_json, priority, state, submitted_unix_ms) \
                 VALUES ('{}', 0, 'running', 0)",
                [],
            )?;
        }
        let store = open(&dir);
        let id = store.jobs()?[0].id;
        store.add_redo(id, &[4])?;
        assert_eq!(store.jobs()?[0].redo, vec![4]);
        drop(store);
        let version: i64 =
            Connection::open(&path)?.pragma_query_value(None, "user_version", |r| r.get(0))?;
        assert_eq!(version, STORE_VERSION);
        Ok(())
    }

    #[test]
    fn committed_data_survives_a_drop_and_ids_keep_increasing() -> Result<(), StoreError> {
        let dir = TempDir::new("reopen");
        let (a, b) = {
            let store = open(&dir);
            let a = store.insert_job("{\"a\":1}", 1, 5)?;
            let b = store.insert_job("{\"b\":2}", 2, 6)?;
            store.set_state(a, JobState::Running, None)?;
            store.put_tile(a, 4, 0, &[7; 16384])?;
            store.put_tile(a, 4, 3, &[8; 100])?;
            store.finish_frame(a, 3, "out_3.png")?;
            // The newest job is deleted: its id must not come back.
            store.delete_job(b)?;
            (a, b)
        };
        let store = open(&dir);
        let jobs = store.jobs()?;
        assert_eq!(jobs.len(), 1);
        assert_eq!(jobs[0].id, a);
        assert_eq!(jobs[0].state, JobState::Running);
        assert_eq!(jobs[0].frames_done, 1);
        assert_eq!(jobs[0].outputs, vec!["out_3.png".to_string()]);
        assert_eq!(
            store.tiles(a, 4)?.tiles,
            vec![(0, vec![7; 16384]), (3, vec![8; 100])]
        );
        let c = store.insert_job("{}", 0, 7)?;
        assert!(c > b, "{c} after {b}");
        drop(store);
        let store = open(&dir);
        let d = store.insert_job("{}", 0, 8)?;
        assert!(d > c, "{d} after {c}");
        Ok(())
    }

    #[test]
    fn a_newer_store_is_refused() -> Result<(), Box<dyn std::error::Error>> {
        let dir = TempDir::new("newer");
        drop(open(&dir));
        let path = dir.0.join("farm.sqlite");
        {
            let conn = Connection::open(&path)?;
            conn.pragma_update(None, "user_version", 4)?;
        }
        let e = Store::open(&dir.0).map(|_| ()).map_err(|e| e.to_string());
        assert_eq!(
            e,
            Err(format!(
                "{} was written by a newer coordinator (store version 4; this build reads up to 3)",
                path.display()
            ))
        );
        Ok(())
    }

    #[test]
    fn a_garbage_file_is_refused() -> Result<(), Box<dyn std::error::Error>> {
        for (name, bytes) in [
            ("short", b"not a database".to_vec()),
            ("long", (0..8192u32).map(|i| (i * 7 + 3) as u8).collect()),
        ] {
            let dir = TempDir::new(&format!("garbage-{name}"));
            std::fs::create_dir_all(&dir.0)?;
            let path = dir.0.join("farm.sqlite");
            std::fs::write(&path, &bytes)?;
            let e = match Store::open(&dir.0) {
                Ok(_) => panic!("a garbage file ({name}) was opened"),
                Err(e) => e,
            };
            assert!(matches!(e, StoreError::Corrupt { .. }), "{e:?}");
            let expected = format!(
                "{}: the store is damaged or not a coordinator store: ",
                path.display()
            );
            assert!(e.to_string().starts_with(&expected), "{e}");
            // The file is left as it was.
            assert_eq!(std::fs::read(&path)?, bytes);
        }
        Ok(())
    }

    /// A page of the jobs table's b-tree damaged (its cell count made
    /// impossible) is found by `quick_check` at open: the store is refused,
    /// naming the file, what SQLite found and what to do.
    #[test]
    fn a_store_that_fails_quick_check_is_refused() -> Result<(), Box<dyn std::error::Error>> {
        let dir = TempDir::new("quick-check");
        {
            let store = open(&dir);
            for i in 0..100 {
                store.insert_job(&"j".repeat(1000), 0, i)?;
            }
            store.checkpoint()?;
        }
        let path = dir.0.join(DB_FILE);
        let mut bytes = std::fs::read(&path)?;
        let page = usize::from(u16::from_be_bytes([bytes[16], bytes[17]]));
        // The last leaf page of a table (type 0x0d) past the schema's page.
        let leaf = (1..bytes.len() / page)
            .rev()
            .find(|&p| bytes[p * page] == 0x0d)
            .expect("a table leaf page");
        bytes[leaf * page + 3] = 0xff;
        bytes[leaf * page + 4] = 0xff;
        std::fs::write(&path, &bytes)?;
        let e = match Store::open(&dir.0) {
            Ok(_) => panic!("a damaged store was opened"),
            Err(e) => e,
        };
        let text = e.to_string();
        assert!(matches!(e, StoreError::Corrupt { .. }), "{e:?}");
        assert!(text.starts_with(&path.display().to_string()), "{text}");
        assert!(text.contains("SQLite's quick_check"), "{text}");
        assert!(text.contains(RESTORE_HINT), "{text}");
        Ok(())
    }

    #[test]
    fn a_foreign_database_is_refused() -> Result<(), Box<dyn std::error::Error>> {
        let dir = TempDir::new("foreign");
        std::fs::create_dir_all(&dir.0)?;
        let path = dir.0.join("farm.sqlite");
        {
            let conn = Connection::open(&path)?;
            conn.execute_batch("CREATE TABLE jobs (x); PRAGMA user_version = 1;")?;
        }
        let e = Store::open(&dir.0).map(|_| ()).map_err(|e| e.to_string());
        assert_eq!(
            e,
            Err(format!(
                "{}: the store is damaged or not a coordinator store: table jobs has columns (x), \
                 expected (id, spec_json, priority, state, error, frames_done, submitted_unix_ms); \
                 {RESTORE_HINT}",
                path.display()
            ))
        );
        std::fs::remove_file(&path)?;
        {
            let conn = Connection::open(&path)?;
            conn.execute_batch("CREATE TABLE other (x);")?;
        }
        let e = Store::open(&dir.0);
        assert!(matches!(e, Err(StoreError::Corrupt { .. })), "{e:?}");
        Ok(())
    }

    #[test]
    fn the_lock_refuses_a_second_open_until_dropped() -> Result<(), Box<dyn std::error::Error>> {
        let dir = TempDir::new("lock");
        let first = open(&dir);
        let lock_text = std::fs::read_to_string(dir.0.join("lock"))?;
        assert_eq!(lock_text.trim(), std::process::id().to_string());
        let e = Store::open(&dir.0).map(|_| ()).map_err(|e| e.to_string());
        assert_eq!(
            e,
            Err(format!(
                "{} is in use by another coordinator (pid {}): stop it first, or choose another --data",
                dir.0.display(),
                std::process::id()
            ))
        );
        drop(first);
        let again = open(&dir);
        drop(again);
        Ok(())
    }

    #[test]
    fn a_directory_that_cannot_be_created_is_named() -> Result<(), Box<dyn std::error::Error>> {
        let dir = TempDir::new("not-a-dir");
        std::fs::create_dir_all(&dir.0)?;
        let file = dir.0.join("file");
        std::fs::write(&file, b"x")?;
        let data = file.join("data");
        let e = Store::open(&data).map(|_| ()).map_err(|e| e.to_string());
        let Err(message) = e else {
            panic!("a directory under a file was opened")
        };
        assert!(
            message.starts_with(&format!(
                "{}: cannot use as the data directory: ",
                data.display()
            )),
            "{message}"
        );
        Ok(())
    }

    #[test]
    fn a_rotten_tile_is_reported_and_dropped() -> Result<(), Box<dyn std::error::Error>> {
        let dir = TempDir::new("rot");
        let store = open(&dir);
        let a = store.insert_job("{}", 0, 0)?;
        store.put_tile(a, 0, 0, &[1; 64])?;
        store.put_tile(a, 0, 1, &[2; 64])?;
        // A byte flipped under the checksum.
        store.conn.execute(
            "UPDATE tiles SET pixels = ?1 WHERE job = ?2 AND unit = 1",
            params![[2u8; 63].iter().copied().chain([3]).collect::<Vec<u8>>(), a],
        )?;
        let read = store.tiles(a, 0)?;
        assert_eq!(read.tiles, vec![(0, vec![1; 64])]);
        assert_eq!(read.rotten, vec![1]);
        drop(store);
        let report = check(&dir.0)?;
        assert_eq!((report.jobs, report.tiles), (1, 2));
        assert_eq!(report.problems.len(), 1, "{:?}", report.problems);
        assert!(
            report.problems[0].starts_with(&format!("job {a} frame 0 unit 1: ")),
            "{:?}",
            report.problems
        );
        let store = open(&dir);
        store.drop_tiles(a, 0, &[1])?;
        assert_eq!(store.tile_keys(a)?, vec![(0, 0)]);
        drop(store);
        assert!(check(&dir.0)?.problems.is_empty());
        Ok(())
    }

    #[test]
    fn a_version_2_store_gains_checksums_and_its_generation()
    -> Result<(), Box<dyn std::error::Error>> {
        let dir = TempDir::new("upgrade-2");
        std::fs::create_dir_all(&dir.0)?;
        let path = dir.0.join("farm.sqlite");
        {
            let conn = Connection::open(&path)?;
            conn.execute_batch(&schema_1())?;
            conn.execute_batch(SCHEMA_1_TO_2)?;
            conn.pragma_update(None, "user_version", 2)?;
            for _ in 0..3 {
                conn.execute(
                    "INSERT INTO jobs (spec_json, priority, state, submitted_unix_ms) \
                     VALUES ('{}', 0, 'running', 0)",
                    [],
                )?;
            }
            conn.execute(
                "INSERT INTO tiles (job, frame, unit, pixels) VALUES (2, 0, 5, x'0102030405')",
                [],
            )?;
        }
        let store = open(&dir);
        assert_eq!(store.tiles(2, 0)?.tiles, vec![(5, vec![1, 2, 3, 4, 5])]);
        assert_eq!(store.generation()?, 3);
        assert_eq!(std::fs::read_to_string(dir.0.join(GENERATION_FILE))?, "3\n");
        assert_eq!(store.insert_job("{}", 0, 0)?, 4);
        Ok(())
    }

    #[test]
    fn a_store_older_than_its_generation_file_is_refused_unless_accepted()
    -> Result<(), Box<dyn std::error::Error>> {
        let dir = TempDir::new("older");
        let store = open(&dir);
        assert_eq!(store.insert_job("{}", 0, 0)?, 1);
        assert_eq!(store.insert_job("{}", 0, 0)?, 2);
        drop(store);
        let file = dir.0.join(GENERATION_FILE);
        assert_eq!(std::fs::read_to_string(&file)?, "2\n");
        // Jobs 3 to 5 were committed in a WAL that is gone.
        std::fs::write(&file, "5\n")?;
        let e = Store::open(&dir.0).map(|_| ()).map_err(|e| e.to_string());
        let Err(message) = e else {
            panic!("an older store was opened")
        };
        assert!(
            message.contains("older than its generation file")
                && message.contains("ids up to 2, the file says 5")
                && message.contains("--accept-older-store"),
            "{message}"
        );
        let store = Store::open_with(&dir.0, true)?;
        assert_eq!(store.jobs()?.len(), 2);
        // No id given out before is given again.
        assert_eq!(store.insert_job("{}", 0, 0)?, 6);
        drop(store);
        assert_eq!(std::fs::read_to_string(&file)?, "6\n");
        drop(open(&dir));
        std::fs::write(&file, "six")?;
        let e = Store::open(&dir.0).map(|_| ()).map_err(|e| e.to_string());
        assert!(
            e.as_ref()
                .is_err_and(|m| m.contains("generation file") && m.contains("\"six\"")),
            "{e:?}"
        );
        Ok(())
    }

    #[test]
    fn a_backup_is_one_whole_file_of_the_store() -> Result<(), Box<dyn std::error::Error>> {
        let dir = TempDir::new("backup");
        let copy = TempDir::new("backup-copy");
        std::fs::create_dir_all(&copy.0)?;
        let store = open(&dir);
        let a = store.insert_job("{\"a\":1}", 0, 0)?;
        store.put_tile(a, 0, 3, &[9; 1000])?;
        // Taken while the store is open and its WAL holds everything.
        let file = copy.0.join("farm.sqlite");
        assert_eq!(backup(&dir.0, &file)?, a);
        store.insert_job("{}", 0, 0)?;
        drop(store);
        let restored = open(&copy);
        assert_eq!(restored.jobs()?.len(), 1);
        assert_eq!(restored.tiles(a, 0)?.tiles, vec![(3, vec![9; 1000])]);
        Ok(())
    }

    #[test]
    fn a_checkpoint_leaves_everything_in_the_database_file()
    -> Result<(), Box<dyn std::error::Error>> {
        let dir = TempDir::new("checkpoint");
        let store = open(&dir);
        let a = store.insert_job("{}", 0, 0)?;
        store.put_tile(a, 0, 0, &[5; 20_000])?;
        store.checkpoint()?;
        let wal = dir.0.join("farm.sqlite-wal");
        assert_eq!(std::fs::metadata(&wal).map_or(0, |m| m.len()), 0);
        // The database file alone, copied while the store stays open.
        let copy = TempDir::new("checkpoint-copy");
        std::fs::create_dir_all(&copy.0)?;
        std::fs::copy(dir.0.join("farm.sqlite"), copy.0.join("farm.sqlite"))?;
        let alone = open(&copy);
        assert_eq!(alone.tiles(a, 0)?.tiles, vec![(0, vec![5; 20_000])]);
        drop(store);
        Ok(())
    }

    #[test]
    fn the_store_is_send() {
        fn send<T: Send>() {}
        send::<Store>();
        send::<std::sync::Mutex<Store>>();
    }
}
