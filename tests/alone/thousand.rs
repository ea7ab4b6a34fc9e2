//! A coordinator under a thousand workers: 1,024 clients, each on a
//! connection of its own, register with one coordinator on loopback and
//! render a sequence of small frames. Each client is the worker library
//! itself (`worker::run`, as the binary runs it), a task in this process:
//! a worker process takes about 8 MiB, 8 GiB for a thousand, which a CI
//! machine does not have, while a task takes a few hundred KiB and speaks
//! the same protocol with the same bytes.
//!
//! The coordinator starts with a soft open-file limit of 512 and raises it
//! to the hard one. It runs pinned to one core, the clients on the other,
//! and the test prints its CPU per tile, its peak RSS and open descriptors,
//! and the tile rate: the figures BENCHMARKS.md quotes. The frames are
//! byte-identical to in-process, and the verified fraction of units is
//! rendered twice as with two workers.

use std::collections::BTreeSet;
use std::os::unix::process::CommandExt as _;
use std::process::Command;
use std::time::{Duration, Instant};

use crate::children_cpu;
use crate::support::*;

/// Clients.
const WORKERS: usize = 1024;
/// Frames of 64 units each: one unit per client.
const FRAMES: u32 = 16;
/// The fraction of units rendered twice.
const VERIFY: f64 = 0.1;

/// Pins the calling thread (and the threads it starts) to `cpu`.
fn pin(cpu: usize) -> std::io::Result<()> {
    // SAFETY: the set is zeroed, then set through the libc macros, and
    // sched_setaffinity only reads it.
    unsafe {
        let mut set: libc::cpu_set_t = std::mem::zeroed();
        libc::CPU_SET(cpu, &mut set);
        if libc::sched_setaffinity(0, std::mem::size_of_val(&set), &set) != 0 {
            return Err(std::io::Error::last_os_error());
        }
    }
    Ok(())
}

/// The open-file limit of this process: (soft, hard).
fn open_files() -> (u64, u64) {
    // SAFETY: getrlimit writes only into the zeroed struct we pass.
    let mut lim: libc::rlimit = unsafe { std::mem::zeroed() };
    assert_eq!(unsafe { libc::getrlimit(libc::RLIMIT_NOFILE, &mut lim) }, 0);
    (lim.rlim_cur as u64, lim.rlim_max as u64)
}

/// What /proc says of a running process: resident KiB (the high-water
/// mark), open descriptors and CPU seconds. `None` once it has gone.
fn sample(pid: u32) -> Option<(u64, usize, f64)> {
    let stat = std::fs::read_to_string(format!("/proc/{pid}/stat")).ok()?;
    // The fields after the command's closing parenthesis: utime and stime
    // are the 12th and 13th.
    let fields: Vec<&str> = stat.rsplit_once(')')?.1.split_whitespace().collect();
    let ticks: f64 = fields.get(11)?.parse::<f64>().ok()? + fields.get(12)?.parse::<f64>().ok()?;
    // SAFETY: sysconf only reads a constant.
    let cpu = ticks / unsafe { libc::sysconf(libc::_SC_CLK_TCK) } as f64;
    let status = std::fs::read_to_string(format!("/proc/{pid}/status")).ok()?;
    let hwm = status
        .lines()
        .find_map(|l| l.strip_prefix("VmHWM:"))?
        .trim()
        .trim_end_matches("kB")
        .trim()
        .parse()
        .ok()?;
    let fds = std::fs::read_dir(format!("/proc/{pid}/fd")).ok()?.count();
    Some((hwm, fds, cpu))
}

#[test]
fn a_thousand_workers_on_one_coordinator() {
    let _alone = alone();
    let (soft, hard) = open_files();
    assert!(
        hard >= 2 * WORKERS as u64 + 256,
        "this test needs an open-file hard limit of at least {}, has {hard}",
        2 * WORKERS + 256
    );
    if soft < hard {
        let raised = libc::rlimit {
            rlim_cur: hard,
            rlim_max: hard,
        };
        // SAFETY: setrlimit only reads the struct.
        assert_eq!(unsafe { libc::setrlimit(libc::RLIMIT_NOFILE, &raised) }, 0);
    }
    let two_cores = std::thread::available_parallelism().map_or(1, |n| n.get()) >= 2;
    let dir = scratch("thousand");
    let size = ["--width", "32", "--height", "32"];
    let frames = format!("0..{FRAMES}");
    let mut common: Vec<&str> = size.to_vec();
    common.extend(["--frames", &frames]);
    in_process("fur", &dir.join("ref.png"), &common);
    let before = children_cpu();
    let scene = scene("fur");
    let out = dir.join("farm.png");
    let verify = VERIFY.to_string();
    let mut cmd = Command::new(env!("CARGO_BIN_EXE_coordinator"));
    cmd.args([
        "--scene",
        scene.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
    ])
    .args(&common)
    .args(["--local-workers", "0", "--verify", &verify])
    .args(["--lease-timeout", "30"]);
    // SAFETY: the closure calls only async-signal-safe functions
    // (setrlimit, sched_setaffinity) between fork and exec.
    unsafe {
        cmd.pre_exec(move || {
            let low = libc::rlimit {
                rlim_cur: 512,
                rlim_max: hard,
            };
            if libc::setrlimit(libc::RLIMIT_NOFILE, &low) != 0 {
                return Err(std::io::Error::last_os_error());
            }
            if two_cores {
                pin(0)?;
            }
            Ok(())
        });
    }
    let mut coordinator = Running::spawn(&mut cmd);
    let pid = coordinator.child.id();
    let port = coordinator.port();
    let url = format!("http://127.0.0.1:{port}");

    // The clients, on a runtime of two threads pinned to the other core.
    let clients = std::thread::spawn(move || {
        if two_cores {
            pin(1).expect("pinning the clients");
        }
        let runtime = tokio::runtime::Builder::new_multi_thread()
            .worker_threads(2)
            .enable_all()
            .build()
            .unwrap();
        let (_stop, stopped) = tokio::sync::watch::channel(false);
        let tasks: Vec<_> = (0..WORKERS)
            .map(|i| {
                let config = worker::WorkerConfig {
                    exit_when_done: true,
                    lease: Duration::from_secs(30),
                    asset_cache_bytes: 1 << 20,
                    ..worker_config(&url, &format!("t{i:04}"))
                };
                runtime.spawn(worker::run(config, stopped.clone()))
            })
            .collect();
        runtime.block_on(async {
            let mut reports = Vec::new();
            for t in tasks {
                reports.push(t.await.expect("a client panicked"));
            }
            reports
        })
    });

    // Peaks while it runs.
    let started = Instant::now();
    let deadline = started + Duration::from_secs(600);
    let (mut rss_kib, mut fds) = (0, 0);
    // The coordinator's CPU and the tiles in once every client has joined:
    // from there on its work is tiles.
    let mut all_joined: Option<(f64, usize)> = None;
    while let Some((r, f, cpu)) = sample(pid) {
        rss_kib = rss_kib.max(r);
        fds = fds.max(f);
        while let Ok(line) = coordinator.lines.try_recv() {
            coordinator.log.push(line);
        }
        if all_joined.is_none()
            && coordinator
                .log
                .iter()
                .filter(|l| l.contains(" joined from "))
                .count()
                == WORKERS
        {
            let frames = coordinator
                .log
                .iter()
                .filter(|l| l.contains("with the farm in"))
                .count();
            all_joined = Some((cpu, frames));
        }
        assert!(Instant::now() < deadline, "not done in 600 s");
        if coordinator.child.try_wait().unwrap().is_some() {
            break;
        }
        std::thread::sleep(Duration::from_millis(50));
    }
    let (status, log) = coordinator.finish(60);
    let wall = started.elapsed();
    let cpu = children_cpu() - before;
    assert!(status.success(), "{}", log.join("\n"));
    let reports = clients.join().expect("the clients' thread");
    let failed: Vec<_> = reports.iter().filter_map(|r| r.as_ref().err()).collect();
    assert!(failed.is_empty(), "clients failed: {failed:?}");

    // Every client joined, each on a connection of its own.
    let joined: BTreeSet<&str> = log
        .iter()
        .filter_map(|l| Some(l.split("worker ").nth(1)?.split_once(" joined from")?.0))
        .collect();
    assert_eq!(joined.len(), WORKERS, "clients that joined");
    assert!(fds >= WORKERS, "at most {fds} descriptors open at once");
    assert!(
        log.iter()
            .any(|l| l.contains("open-file limit raised from 512 to")),
        "{}",
        log.join("\n")
    );

    // The frames are exact.
    for f in 0..FRAMES {
        let name = format!("_{f:04}.png");
        same_bytes(
            &dir.join(format!("farm{name}")),
            &dir.join(format!("ref{name}")),
        );
    }

    // Each unit once, from the coordinator's account of each worker, and
    // the verified fraction twice: sampled by a keyed hash, a binomial
    // count (mean 102.4, standard deviation 9.6 here).
    let units: u64 = log
        .iter()
        .filter_map(|l| {
            let rest = l.split("worker t").nth(1)?;
            rest.split(": ")
                .nth(1)?
                .split(" units")
                .next()?
                .parse::<u64>()
                .ok()
        })
        .sum();
    let total = u64::from(FRAMES) * 64;
    assert_eq!(units, total, "tiles accepted");
    let twice: u64 = log
        .iter()
        .find_map(|l| {
            l.split("; ")
                .nth(1)?
                .strip_suffix(" units verified by a second rendering")?
                .parse()
                .ok()
        })
        .unwrap_or_else(|| panic!("no count of units rendered twice in\n{}", log.join("\n")));
    let expected = VERIFY * total as f64;
    eprintln!(
        "{WORKERS} workers, {total} units: {twice} rendered twice ({expected:.0} expected at --verify {VERIFY})"
    );
    assert!(
        (expected * 0.6..=expected * 1.4).contains(&(twice as f64)),
        "{twice} units rendered twice of {total} at --verify {VERIFY}"
    );
    let (joined_cpu, joined_frames) = all_joined.expect("every client joined");
    let later = (FRAMES as usize - joined_frames) * 64;
    eprintln!(
        "after the last client joined: {:.1} µs of coordinator CPU a tile ({:.3} s for the {later} units of {} frames)",
        (cpu - joined_cpu) * 1e6 / later.max(1) as f64,
        cpu - joined_cpu,
        FRAMES as usize - joined_frames
    );
    eprintln!(
        "coordinator: {:.1} µs of CPU a tile ({cpu:.3} s for {total} tiles, registrations included), peak RSS {:.1} MiB, {fds} descriptors at most, {:.0} tiles/s over {:.2} s",
        cpu * 1e6 / total as f64,
        rss_kib as f64 / 1024.0,
        total as f64 / wall.as_secs_f64(),
        wall.as_secs_f64()
    );
}
