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
//! - `tiles(job, frame, unit, pixels)`: the units received of unfinished frames.
//! - `redo(job, frame)`: finished frames to render again, because a worker
//!   caught lying had delivered some of their tiles (version 2; a version 1
//!   store gains the table when opened).

use std::fs::{File, OpenOptions};
use std::io::{Read, Write};
use std::os::fd::AsRawFd;
use std::path::{Path, PathBuf};
use std::time::Duration;

use rusqlite::{Connection, ErrorCode, OptionalExtension, params};

use crate::jobs::JobState;

/// The store version this build writes and the newest it reads.
pub const STORE_VERSION: i64 = 2;

/// The database file's name inside the data directory.
pub const DB_FILE: &str = "farm.sqlite";

/// The lock file's name inside the data directory.
pub const LOCK_FILE: &str = "lock";

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
    PRIMARY KEY (job, frame, unit)
);
CREATE TABLE redo (
    job INTEGER NOT NULL REFERENCES jobs(id) ON DELETE CASCADE,
    frame INTEGER NOT NULL,
    PRIMARY KEY (job, frame)
) WITHOUT ROWID;
";

/// What version 2 added to version 1's schema.
const SCHEMA_1_TO_2: &str = "
CREATE TABLE redo (
    job INTEGER NOT NULL REFERENCES jobs(id) ON DELETE CASCADE,
    frame INTEGER NOT NULL,
    PRIMARY KEY (job, frame)
) WITHOUT ROWID;
";

/// The tables of [`SCHEMA`] and their columns, in order: what [`Store::open`]
/// checks an existing database against.
const TABLES: [(&str, &[&str]); 4] = [
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
    ("tiles", &["job", "frame", "unit", "pixels"]),
    ("redo", &["job", "frame"]),
];

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
    #[error("{file}: the store is corrupt or not a coordinator store: {message}")]
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
    /// The [`JobSpec`](crate::jobs::JobSpec) as submitted, as JSON.
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

impl Store {
    /// Opens the store in `dir` (created if missing): locks `dir/lock`, then
    /// opens `dir/farm.sqlite`, creating the schema if the database is new and
    /// checking the store version and the schema (not every page: opening stays
    /// quick however many tiles are stored) if not.
    pub fn open(dir: &Path) -> Result<Store, StoreError> {
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
        Ok(store)
    }

    /// The database file.
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// Adds a queued job; returns its id, greater than every id given before.
    pub fn insert_job(
        &self,
        spec_json: &str,
        priority: i32,
        submitted_unix_ms: u64,
    ) -> Result<u64, StoreError> {
        let id: i64 = self
            .conn
            .prepare_cached(
                "INSERT INTO jobs (spec_json, priority, state, submitted_unix_ms) \
                 VALUES (?1, ?2, ?3, ?4) RETURNING id",
            )
            .and_then(|mut s| {
                s.query_row(
                    params![
                        spec_json,
                        priority,
                        JobState::Queued.as_str(),
                        submitted_unix_ms
                    ],
                    |r| r.get(0),
                )
            })
            .map_err(|e| self.sqlite(e))?;
        u64::try_from(id).map_err(|_| self.corrupt(format!("negative job id {id}")))
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
        self.conn
            .prepare_cached(
                "INSERT OR REPLACE INTO tiles (job, frame, unit, pixels) \
                 SELECT ?1, ?2, ?3, ?4 FROM jobs \
                 WHERE id = ?1 AND state IN ('queued', 'running')",
            )
            .and_then(|mut s| s.execute(params![job, frame, unit, pixels]))
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
        let (rows, outputs, redo) = self.transaction(|conn| {
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

    /// The stored tiles of frame `frame` of job `job`: `(unit, pixels)` by unit.
    pub fn tiles(&self, job: u64, frame: u32) -> Result<Vec<(u32, Vec<u8>)>, StoreError> {
        self.conn
            .prepare_cached(
                "SELECT unit, pixels FROM tiles WHERE job = ?1 AND frame = ?2 ORDER BY unit",
            )
            .and_then(|mut s| {
                s.query_map(params![job, frame], |r| Ok((r.get(0)?, r.get(1)?)))?
                    .collect()
            })
            .map_err(|e| self.sqlite(e))
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
                self.check_tables(&TABLES[..3])?;
                self.transaction(|conn| {
                    conn.execute_batch(SCHEMA_1_TO_2)?;
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
            _ => self.sqlite(e),
        }
    }
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
            store.tiles(a, 0)?,
            vec![(0, vec![0; 50]), (2, vec![3; 100])]
        );
        assert_eq!(store.tiles(a, 5)?, vec![]);
        assert_eq!(store.tile_keys(a)?, vec![(0, 0), (0, 2), (1, 0)]);
        store.finish_frame(a, 0, "a0.png")?;
        assert_eq!(store.tiles(a, 0)?, vec![]);
        assert_eq!(store.tiles(a, 1)?, vec![(0, vec![10; 10])]);
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
            // Version 1's schema: the current one without `redo`.
            let v1 = SCHEMA.split("CREATE TABLE redo").next().unwrap_or_default();
            conn.execute_batch(v1)?;
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
            store.tiles(a, 4)?,
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
            conn.pragma_update(None, "user_version", 3)?;
        }
        let e = Store::open(&dir.0).map(|_| ()).map_err(|e| e.to_string());
        assert_eq!(
            e,
            Err(format!(
                "{} was written by a newer coordinator (store version 3; this build reads up to 2)",
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
                "{}: the store is corrupt or not a coordinator store: ",
                path.display()
            );
            assert!(e.to_string().starts_with(&expected), "{e}");
            // The file is left as it was.
            assert_eq!(std::fs::read(&path)?, bytes);
        }
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
                "{}: the store is corrupt or not a coordinator store: table jobs has columns (x), \
                 expected (id, spec_json, priority, state, error, frames_done, submitted_unix_ms)",
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
    fn the_store_is_send() {
        fn send<T: Send>() {}
        send::<Store>();
        send::<std::sync::Mutex<Store>>();
    }
}
