//! Speedup without wall time: the workers must not burn more CPU than the serial
//! render (their total process CPU, from the OS via getrusage and reported with
//! their goodbye, ≤ 1.10 × the CPU of `--in-process --threads 1`), and every
//! worker must render a share. Coordinator included, the farm stays within 1.25×.
//!
//! Its own test binary: `RUSAGE_CHILDREN` counts every child this process has
//! waited for, so no other test may run children beside it.

mod support;

use support::*;

/// CPU seconds (user + system) of all waited-for children so far.
fn children_cpu() -> f64 {
    // SAFETY: getrusage writes only into the zeroed struct we pass.
    let mut usage: libc::rusage = unsafe { std::mem::zeroed() };
    assert_eq!(
        unsafe { libc::getrusage(libc::RUSAGE_CHILDREN, &mut usage) },
        0
    );
    let secs = |t: libc::timeval| t.tv_sec as f64 + t.tv_usec as f64 / 1e6;
    secs(usage.ru_utime) + secs(usage.ru_stime)
}

#[test]
fn the_farm_costs_no_more_cpu_than_the_serial_render() {
    let dir = scratch("speedup");
    let fur = scene("fur");
    let common = [
        "--scene",
        fur.to_str().unwrap(),
        // Large enough that the workers' fixed costs (process start, connection,
        // scene build) stay small beside the render, as they are at full size.
        "--width",
        "512",
        "--height",
        "512",
    ];
    let _ = worker_bin();

    let before = children_cpu();
    let out = dir.join("serial.png");
    let o = coordinator(
        &[
            &common[..],
            &[
                "--out",
                out.to_str().unwrap(),
                "--in-process",
                "--threads",
                "1",
                "--quiet",
            ],
        ]
        .concat(),
    );
    assert!(o.status.success());
    let serial = children_cpu() - before;

    let before = children_cpu();
    let out = dir.join("farm.png");
    let o = std::process::Command::new(env!("CARGO_BIN_EXE_coordinator"))
        .args(
            [
                &common[..],
                &[
                    "--out",
                    out.to_str().unwrap(),
                    "--local-workers",
                    "2",
                    "--threads",
                    "1",
                ],
            ]
            .concat(),
        )
        .env("RUST_LOG", "info")
        .env("NO_COLOR", "1")
        .output()
        .unwrap();
    let farm = children_cpu() - before;
    let log = String::from_utf8_lossy(&o.stderr);
    assert!(o.status.success(), "{log}");

    let shares: Vec<&str> = log
        .lines()
        .filter(|l| l.contains("worker local-") && l.contains(" units,"))
        .collect();
    assert_eq!(shares.len(), 2, "{log}");
    let mut workers = 0.0;
    for line in shares {
        assert!(
            !line.contains(": 0 units"),
            "a worker rendered nothing: {line}"
        );
        let cpu = line
            .split("process cpu ")
            .nth(1)
            .and_then(|r| r.trim_end_matches(" s").parse::<f64>().ok())
            .unwrap_or_else(|| panic!("no process cpu in {line:?}"));
        workers += cpu;
    }
    println!(
        "serial CPU {serial:.3} s; workers {workers:.3} s (ratio {:.3}); with the coordinator {farm:.3} s (ratio {:.3})",
        workers / serial,
        farm / serial
    );
    assert!(
        workers <= 1.10 * serial,
        "workers' CPU {workers:.3} s > 1.10 × serial {serial:.3} s\n{log}"
    );
    assert!(
        farm <= 1.25 * serial,
        "farm CPU {farm:.3} s > 1.25 × serial {serial:.3} s\n{log}"
    );
    std::fs::remove_dir_all(&dir).unwrap();
}
