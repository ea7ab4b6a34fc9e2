//! The store's faults: a full disk under `--data` (a small tmpfs this test
//! mounts as root and unmounts), a frame's record the store refuses, a byte
//! flipped in a stored tile, a lost or truncated WAL, a backup put back, and
//! a drain whose local workers are SIGSTOPped. Every acknowledged job ends
//! done and byte-identical to the in-process render. Loopback only; every
//! wait is bounded.

use std::io::Write;
use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::{Duration, Instant};

use crate::support::service::{
    children, client, job, metric, poll_job, reference, serve, submit, wait,
};
use crate::support::{Running, coordinator, http, same_bytes, scene, scratch, until};

/// A tmpfs of `size` mounted on `dir`; unmounted on drop, also when the test
/// fails.
struct Tmpfs(PathBuf);

impl Tmpfs {
    fn mount(dir: &Path, size: &str) -> Tmpfs {
        std::fs::create_dir_all(dir).unwrap();
        let status = Command::new("mount")
            .args(["-t", "tmpfs", "-o", &format!("size={size}"), "tmpfs"])
            .arg(dir)
            .status()
            .expect("mount runs");
        assert!(status.success(), "mount -t tmpfs (the test runs as root)");
        Tmpfs(dir.to_path_buf())
    }
}

impl Drop for Tmpfs {
    fn drop(&mut self) {
        for _ in 0..50 {
            let ok = Command::new("umount")
                .arg(&self.0)
                .status()
                .is_ok_and(|s| s.success());
            if ok {
                return;
            }
            std::thread::sleep(Duration::from_millis(100));
        }
        let _ = Command::new("umount").arg("-l").arg(&self.0).status();
    }
}

/// Fills the file system of `dir` with `dir/filler` until it has no room.
fn fill(dir: &Path) -> PathBuf {
    let path = dir.join("filler");
    let mut file = std::fs::File::create(&path).unwrap();
    let chunk = vec![0x55u8; 64 << 10];
    for _ in 0..100_000 {
        match file.write(&chunk) {
            Ok(0) => break,
            Ok(_) => {}
            Err(e) if e.raw_os_error() == Some(libc::ENOSPC) => break,
            Err(e) => panic!("{}: {e}", path.display()),
        }
    }
    // The last partial block.
    for _ in 0..100_000 {
        match file.write(&[0x55]) {
            Ok(1) => {}
            _ => break,
        }
    }
    let _ = file.sync_all();
    path
}

/// POSTs a job as JSON; returns the status and the body.
fn post_job(url: &str, scene_name: &str, out: &Path) -> (u16, serde_json::Value) {
    let text = std::fs::read_to_string(scene(scene_name)).unwrap();
    let body = serde_json::json!({
        "scene": text,
        "scene_name": format!("{scene_name}.ron"),
        "out": out.to_str().unwrap(),
        "width": 32,
        "height": 32,
    });
    let answer = http::post_job(url, &body);
    (answer.status, answer.json())
}

/// GET `/readyz`: the status.
fn readyz(url: &str) -> u16 {
    http::get(url, "/readyz").status
}

const SMALL: [&str; 4] = ["--width", "32", "--height", "32"];

/// The in-process renders of the tribble's first `frames` frames at 32².
fn references(dir: &Path, frames: u32) -> Vec<PathBuf> {
    (0..frames)
        .map(|f| {
            let frame = f.to_string();
            let args = ["--width", "32", "--height", "32", "--frame", &frame];
            reference("tribble", dir, &format!("ref_{f}.png"), &args)
        })
        .collect()
}

/// Disk full under `--data` while a job renders and while others are
/// submitted: submissions get 507 (or 503) and no id, tiles are refused and
/// handed out again, the service says so (readiness, metrics, status, one
/// WARN line), and once space returns it goes on by itself: every
/// acknowledged job ends done, byte-identical, with every frame recorded, and
/// ids are never given twice, across a restart too.
#[test]
fn a_full_disk_under_data_loses_no_acknowledged_job() {
    let dir = scratch("store-full");
    let mnt = dir.join("mnt");
    let tmpfs = Tmpfs::mount(&mnt, "8m");
    let data = mnt.join("data");
    let expected = references(&dir, 3);
    // The outputs go beside the tmpfs, not on it.
    let root = dir.to_str().unwrap();
    let (s, url) = serve(
        &data,
        &[
            "--local-workers",
            "1",
            "--verify",
            "0",
            "--lease-timeout",
            "3",
            "--output-root",
            root,
        ],
    );
    let a = submit(
        &url,
        "tribble",
        &dir.join("a_#.png"),
        &["--width", "32", "--height", "32", "--frames", "0..3"],
    );
    let filler = fill(&mnt);
    // Submissions while the disk is full: refused, without an id.
    let mut refused = 0;
    until(30, "a refused submission", || {
        let (status, body) = post_job(&url, "tribble", &dir.join("x.png"));
        if status == 201 {
            return false;
        }
        assert!(status == 507 || status == 503, "{status} {body}");
        assert!(body.get("id").is_none(), "{body}");
        assert!(
            body["error"].as_str().unwrap().contains("not queued"),
            "{body}"
        );
        refused += 1;
        true
    });
    assert!(refused > 0);
    until(10, "readiness failing", || readyz(&url) == 503);
    assert_eq!(metric(&url, "hypertexture_store_writable"), 0.0);
    let (_, table, _) = client(&["status", "--server", &url]);
    assert!(table.starts_with("NOT READY: "), "{table}");
    // Tiles keep arriving and are refused: still one WARN line.
    std::thread::sleep(Duration::from_millis(2500));
    std::fs::remove_file(&filler).unwrap();
    until(20, "readiness back", || readyz(&url) == 200);
    assert_eq!(metric(&url, "hypertexture_store_writable"), 1.0);
    let c = submit(&url, "tribble", &dir.join("c.png"), &SMALL);
    assert!(c > a, "{c} after {a}");
    assert!(wait(&url, a).0, "{}", job(&url, a));
    assert!(wait(&url, c).0, "{}", job(&url, c));
    s.signal(15);
    let (status, log) = s.finish(30);
    assert!(status.success(), "{}", log.join("\n"));
    let warnings = log
        .iter()
        .filter(|l| l.contains("WARN") && !l.contains("local worker") && l.contains("the store"))
        .count();
    // Once the store fails, no unit goes out: few tiles are refused.
    let refused = log.iter().filter(|l| l.contains("tile refused")).count();
    assert!(refused <= 8, "{refused} tiles refused:\n{}", log.join("\n"));
    assert!(
        (1..=2).contains(&warnings),
        "{warnings} WARN lines:\n{}",
        log.join("\n")
    );
    assert!(
        !log.iter()
            .any(|l| l.contains("lying") || l.contains("blocklist")),
        "{}",
        log.join("\n")
    );
    for (f, want) in expected.iter().enumerate() {
        same_bytes(&dir.join(format!("a_{f}.png")), want);
    }
    same_bytes(&dir.join("c.png"), &expected[0]);
    // After a restart: both done, every frame listed, and new ids go on.
    let (_s, url) = serve(&data, &["--local-workers", "0", "--output-root", root]);
    let ja = job(&url, a);
    assert_eq!(ja["state"], "done", "{ja}");
    assert_eq!(ja["outputs"].as_array().unwrap().len(), 3, "{ja}");
    assert!(ja["blocklisted"].as_array().unwrap().is_empty(), "{ja}");
    assert_eq!(job(&url, c)["state"], "done");
    let d = submit(&url, "tribble", &dir.join("d.png"), &SMALL);
    assert!(d > c, "{d} after {c}");
    drop(_s);
    drop(tmpfs);
}

/// A frame's record refused by the store (a trigger makes SQLite refuse the
/// output row, as a full disk refuses the whole transaction): the frame's
/// file is written, but the frame counts only once recorded, so the job is
/// not done and the service is not ready while the record waits; once the
/// store takes it, it is recorded by itself, the job ends done with every
/// frame listed and byte-identical, and a restart finds the same.
#[test]
fn a_frames_record_the_store_refuses_waits_and_is_kept_once_it_writes() {
    let dir = scratch("store-record");
    let data = dir.join("data");
    let expected = references(&dir, 2);
    let (s, url) = serve(&data, &["--local-workers", "1", "--verify", "0"]);
    let conn = rusqlite::Connection::open(data.join("farm.sqlite")).unwrap();
    conn.busy_timeout(Duration::from_secs(5)).unwrap();
    conn.execute_batch(
        "CREATE TRIGGER refuse_outputs BEFORE INSERT ON outputs \
         BEGIN SELECT RAISE(ABORT, 'refused by the test'); END;",
    )
    .unwrap();
    let id = submit(
        &url,
        "tribble",
        &dir.join("r_#.png"),
        &["--width", "32", "--height", "32", "--frames", "0..2"],
    );
    let first = dir.join("r_0.png");
    until(60, "frame 0's file", || first.exists());
    until(10, "/readyz failing", || readyz(&url) == 503);
    // Other writes (frame 1's tiles, the probes) succeed meanwhile: the
    // store still counts as failing while a record waits.
    for _ in 0..12 {
        let j = job(&url, id);
        assert_ne!(j["state"], "done", "{j}");
        assert_eq!(j["frames_done"], 0, "a frame counts once recorded: {j}");
        assert!(j["outputs"].as_array().unwrap().is_empty(), "{j}");
        assert_eq!(readyz(&url), 503, "not ready while a record waits");
        assert_eq!(metric(&url, "hypertexture_store_writable"), 0.0);
        std::thread::sleep(Duration::from_millis(250));
    }
    // The store takes writes again: nothing to restart.
    conn.execute_batch("DROP TRIGGER refuse_outputs;").unwrap();
    drop(conn);
    let j = poll_job(&url, id, 60, |j| j["state"] == "done");
    assert_eq!(j["outputs"].as_array().unwrap().len(), 2, "{j}");
    assert_eq!(readyz(&url), 200);
    for (f, want) in expected.iter().enumerate() {
        same_bytes(&dir.join(format!("r_{f}.png")), want);
    }
    s.signal(15);
    let (status, log) = s.finish(60);
    assert!(status.success(), "{}", log.join("\n"));
    let (_s, url) = serve(&data, &["--local-workers", "0"]);
    let j = job(&url, id);
    assert_eq!(j["state"], "done", "{j}");
    assert_eq!(j["outputs"].as_array().unwrap().len(), 2, "{j}");
}

/// Finds `needle` in `haystack`; returns its offset if it occurs once.
fn find_once(haystack: &[u8], needle: &[u8]) -> Option<usize> {
    let mut found = haystack
        .windows(needle.len())
        .enumerate()
        .filter(|(_, w)| *w == needle);
    let first = found.next()?.0;
    found.next().is_none().then_some(first)
}

/// The file offset of a 32-byte stretch of `pixels` that occurs once in
/// `file`, tried from the tile's middle outwards.
fn unique_stretch(file: &[u8], pixels: &[u8]) -> Option<usize> {
    const STRETCH: usize = 32;
    let starts = pixels.len().checked_sub(STRETCH)? / STRETCH;
    (0..=starts)
        .map(|i| {
            let half = starts / 2;
            let k = if i % 2 == 0 {
                half + i / 2
            } else {
                half.wrapping_sub(i / 2 + 1)
            };
            k.min(starts) * STRETCH
        })
        .find_map(|off| find_once(file, &pixels[off..off + STRETCH]).map(|at| at + STRETCH / 2))
}

/// A stored tile (JSON of the tiles table's row): its job, frame, unit and bytes.
fn stored_tiles(db: &Path) -> Vec<(u64, u32, u32, Vec<u8>)> {
    let conn = rusqlite::Connection::open(db).unwrap();
    conn.prepare("SELECT job, frame, unit, pixels FROM tiles ORDER BY job, frame, unit")
        .unwrap()
        .query_map([], |r| Ok((r.get(0)?, r.get(1)?, r.get(2)?, r.get(3)?)))
        .unwrap()
        .collect::<Result<_, _>>()
        .unwrap()
}

/// A clean stop leaves one file (the WAL checkpointed); 4 bytes flipped
/// inside one stored tile of it are found by `store check` and at the next
/// start: the tile is dropped, counted, logged, rendered again, and the image
/// is still exact.
#[test]
fn a_flipped_byte_in_a_stored_tile_is_dropped_and_rendered_again() {
    let dir = scratch("store-rot");
    let data = dir.join("data");
    // A frame of 64 units that takes a one-thread worker seconds, so the
    // kill lands while most of its units are still to come: a frame once
    // written keeps no tiles.
    let slow = ["--width", "64", "--height", "64", "--spp", "256"];
    let expected = reference("tribble", &dir, "ref.png", &slow);
    let (s, url) = serve(&data, &["--local-workers", "0", "--verify", "0"]);
    let id = submit(&url, "tribble", &dir.join("t.png"), &slow);
    // A worker delivers a few units, then stops for good (SIGKILL).
    let mut w = Running::worker(&["--coordinator", &url, "--threads", "1", "--name", "w"]);
    poll_job(&url, id, 60, |j| j["units_done"].as_u64().unwrap() >= 4);
    w.signal(9);
    let _ = w.child.wait();
    s.signal(15);
    let (status, log) = s.finish(60);
    assert!(status.success(), "{}", log.join("\n"));
    let db = data.join("farm.sqlite");
    let wal = data.join("farm.sqlite-wal");
    assert_eq!(
        std::fs::metadata(&wal).map_or(0, |m| m.len()),
        0,
        "a clean stop leaves the WAL empty"
    );
    let tiles = stored_tiles(&db);
    assert!(tiles.len() >= 4, "{} tiles stored", tiles.len());
    let mut bytes = std::fs::read(&db).unwrap();
    // Tiles of background repeat one another, and a tile larger than a page
    // is split across overflow pages: flip inside a stretch of one tile's
    // bytes that occurs exactly once in the file.
    let (job_id, frame, unit, mid) = tiles
        .iter()
        .cycle()
        .skip(tiles.len() / 2)
        .take(tiles.len())
        .find_map(|(job, frame, unit, pixels)| {
            unique_stretch(&bytes, pixels).map(|at| (*job, *frame, *unit, at))
        })
        .expect("a stretch of some tile's bytes once in the file");
    assert_eq!(job_id, id);
    for b in &mut bytes[mid..mid + 4] {
        *b ^= 0xa5;
    }
    std::fs::write(&db, &bytes).unwrap();
    let _ = std::fs::remove_file(&wal);
    let checked = coordinator(&["store", "check", "--data", data.to_str().unwrap()]);
    let stderr = String::from_utf8_lossy(&checked.stderr);
    assert!(
        !checked.status.success(),
        "store check passed a flipped tile"
    );
    assert!(
        stderr.contains(&format!("job {id} frame {frame} unit {unit}: ")),
        "{stderr}"
    );
    let (s, url) = serve(&data, &["--local-workers", "1", "--verify", "0"]);
    assert!(wait(&url, id).0, "{}", job(&url, id));
    assert_eq!(metric(&url, "hypertexture_store_tiles_dropped_total"), 1.0);
    s.signal(15);
    let (_, log) = s.finish(30);
    assert!(
        log.iter().any(|l| l.contains(&format!(
            "job {id} frame {frame} unit {unit}: the stored tile's bytes do not match"
        ))),
        "{}",
        log.join("\n")
    );
    same_bytes(&dir.join("t.png"), &expected);
}

/// Jobs committed in the WAL only (SIGKILL), then the WAL deleted or cut
/// short: the next start refuses, naming the problem, never a silent empty
/// queue; with --accept-older-store it goes on, and gives no id twice.
#[test]
fn a_lost_or_truncated_wal_is_refused_not_an_empty_queue() {
    for case in ["deleted", "truncated"] {
        let dir = scratch(&format!("store-wal-{case}"));
        let data = dir.join("data");
        let (s, url) = serve(&data, &["--local-workers", "0"]);
        let ids: Vec<u64> = (0..3)
            .map(|i| submit(&url, "tribble", &dir.join(format!("j{i}.png")), &SMALL))
            .collect();
        s.signal(9);
        let _ = s.finish(30);
        let wal = data.join("farm.sqlite-wal");
        let len = std::fs::metadata(&wal).unwrap().len();
        assert!(len > 0, "the jobs are in the WAL");
        if case == "deleted" {
            std::fs::remove_file(&wal).unwrap();
        } else {
            std::fs::OpenOptions::new()
                .write(true)
                .open(&wal)
                .unwrap()
                .set_len(len / 2)
                .unwrap();
        }
        let args = [
            "serve",
            "--data",
            data.to_str().unwrap(),
            "--listen",
            "127.0.0.1:0",
            "--local-workers",
            "0",
        ];
        let (ok, _, stderr) = client(&args);
        assert!(!ok, "{case}: started");
        assert!(
            stderr.contains("older than its generation file")
                && stderr.contains("farm.sqlite")
                && stderr.contains("--accept-older-store"),
            "{case}: {stderr}"
        );
        let (_s, url) = serve(&data, &["--local-workers", "0", "--accept-older-store"]);
        let next = submit(&url, "tribble", &dir.join("n.png"), &SMALL);
        assert!(
            next > *ids.last().unwrap(),
            "{case}: id {next} after {ids:?}"
        );
    }
}

/// A backup taken while a job renders, put back after the service is killed:
/// the job resumes from the copy and its frames come out exact.
#[test]
fn a_backup_taken_mid_job_and_restored_resumes_exactly() {
    let dir = scratch("store-backup");
    let data = dir.join("data");
    let expected = references(&dir, 2);
    let (s, url) = serve(&data, &["--local-workers", "1", "--verify", "0"]);
    let id = submit(
        &url,
        "tribble",
        &dir.join("b_#.png"),
        &["--width", "32", "--height", "32", "--frames", "0..2"],
    );
    poll_job(&url, id, 60, |j| j["units_done"].as_u64().unwrap() > 0);
    let copy = dir.join("copy.sqlite");
    let out = coordinator(&[
        "store",
        "backup",
        "--data",
        data.to_str().unwrap(),
        copy.to_str().unwrap(),
    ]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    s.signal(9);
    let _ = s.finish(30);
    for f in ["farm.sqlite", "farm.sqlite-wal", "farm.sqlite-shm"] {
        let _ = std::fs::remove_file(data.join(f));
    }
    std::fs::copy(&copy, data.join("farm.sqlite")).unwrap();
    let (_s, url) = serve(&data, &["--local-workers", "1", "--verify", "0"]);
    assert!(wait(&url, id).0, "{}", job(&url, id));
    for (f, want) in expected.iter().enumerate() {
        same_bytes(&dir.join(format!("b_{f}.png")), want);
    }
}

/// Sends `signal` to `pids`.
fn kill(pids: &[u32], signal: i32) {
    for &pid in pids {
        // SAFETY: kill(2) on processes this test started (through the coordinator).
        unsafe {
            libc::kill(pid as libc::pid_t, signal);
        }
    }
}

/// Local workers SIGCONTed and killed on drop, also when the test fails.
struct Stopped(Vec<u32>);

impl Drop for Stopped {
    fn drop(&mut self) {
        kill(&self.0, libc::SIGCONT);
        kill(&self.0, libc::SIGKILL);
    }
}

/// Both local workers SIGSTOPped mid-job: SIGTERM with --drain-timeout 2
/// exits within the drain time and 1 s, and the next start finishes the job
/// exactly.
#[test]
fn a_drain_with_stuck_workers_ends_on_time() {
    let dir = scratch("store-drain");
    let data = dir.join("data");
    let expected = reference(
        "tribble",
        &dir,
        "ref.png",
        &["--width", "64", "--height", "64"],
    );
    let (s, url) = serve(
        &data,
        &[
            "--local-workers",
            "2",
            "--drain-timeout",
            "2",
            "--verify",
            "0",
        ],
    );
    let id = submit(
        &url,
        "tribble",
        &dir.join("t.png"),
        &["--width", "64", "--height", "64"],
    );
    poll_job(&url, id, 60, |j| j["units_done"].as_u64().unwrap() > 0);
    let workers = children(s.child.id());
    assert_eq!(workers.len(), 2, "{workers:?}");
    let stopped = Stopped(workers.clone());
    kill(&workers, libc::SIGSTOP);
    let started = Instant::now();
    s.signal(15);
    let (status, log) = s.finish(30);
    let took = started.elapsed();
    assert!(status.success(), "{}", log.join("\n"));
    assert!(
        took <= Duration::from_secs(3),
        "exit took {took:?} with --drain-timeout 2:\n{}",
        log.join("\n")
    );
    drop(stopped);
    let (_s, url) = serve(&data, &["--local-workers", "1"]);
    assert!(wait(&url, id).0);
    same_bytes(&dir.join("t.png"), &expected);
}
