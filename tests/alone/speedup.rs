//! Speedup without wall time: the workers must not burn more CPU than the serial
//! render (their total process CPU, from the OS via getrusage and reported with
//! their goodbye, ≤ 1.10 × the CPU of `--in-process --threads 1`, measured as
//! two such renders side by side, see [`serial`]), and every worker must render
//! a share. Coordinator included, the farm stays within 1.25×.
//!
//! One run can cost 25% more CPU than the next on a shared machine (a busy
//! neighbour, a cold cache, a slower clock), which one pair of runs cannot tell
//! apart from a farm that wastes work. So the test runs the serial renders and
//! the farm in turn, eleven farms between twelve serial pairs, and bounds the
//! median of the eleven ratios: each farm is compared with the serial runs made
//! just before and just after it, and the median ignores the rounds a neighbour
//! spoilt, in either direction. (On a 2-core VM one round's ratio ranges over
//! 0.93–1.27 around a median near 1.06: about three rounds in ten land over
//! 1.10, so the median needs more than a handful of them.)
//!
//! It holds [`alone`] in a binary of its own: `RUSAGE_CHILDREN` counts every
//! child this process has waited for, so no other test may run children
//! beside it.

use crate::children_cpu;
use crate::support::*;

/// Rounds of a serial and a farm render.
const ROUNDS: usize = 11;

/// The CPU seconds of `--in-process --threads 1`, rendered twice at once and
/// averaged: the farm's two workers share the machine's cores, caches and
/// memory bandwidth (on a VM, perhaps a core's two hyperthreads), and a thread
/// running beside another takes more CPU time for the same work than one
/// running alone, up to 1.4× here. Two serial renders side by side see what
/// the two workers see, so the ratio measures only what the farm adds.
fn serial(common: &[&str], dir: &std::path::Path) -> f64 {
    let before = children_cpu();
    let renders: Vec<std::process::Child> = (0..2)
        .map(|i| {
            let out = dir.join(format!("serial-{i}.png"));
            std::process::Command::new(env!("CARGO_BIN_EXE_coordinator"))
                .args(common)
                .args([
                    "--out",
                    out.to_str().unwrap(),
                    "--in-process",
                    "--threads",
                    "1",
                    "--quiet",
                ])
                .env_remove("RUST_LOG")
                .stderr(std::process::Stdio::piped())
                .spawn()
                .expect("the coordinator binary runs")
        })
        .collect();
    for render in renders {
        let o = collect_within(render, RUN_SECS);
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    }
    (children_cpu() - before) / 2.0
}

/// The farm of two local worker processes: (the workers' own process CPU as they
/// report it, the CPU of the coordinator and its workers together).
fn farm(common: &[&str], out: &std::path::Path) -> (f64, f64) {
    let before = children_cpu();
    let o = output_within(
        std::process::Command::new(env!("CARGO_BIN_EXE_coordinator"))
            .args(
                [
                    common,
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
            .env("NO_COLOR", "1"),
        RUN_SECS,
    );
    let total = children_cpu() - before;
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
    (workers, total)
}

#[test]
fn the_farm_costs_no_more_cpu_than_the_serial_render() {
    let _alone = alone();
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

    // Serial, farm, serial, farm, …, serial: each farm is compared with the
    // mean of the serial renders just before and just after it, so that a
    // machine whose speed drifts during the test moves both sides alike.
    let (mut workers, mut farms) = (Vec::new(), Vec::new());
    let mut before = serial(&common, &dir);
    for round in 0..ROUNDS {
        let (w, f) = farm(&common, &dir.join("farm.png"));
        let after = serial(&common, &dir);
        let s = (before + after) / 2.0;
        println!(
            "round {round}: serial CPU {before:.3} s then {after:.3} s; workers {w:.3} s ({:.3}); farm {f:.3} s ({:.3})",
            w / s,
            f / s
        );
        workers.push(w / s);
        farms.push(f / s);
        before = after;
    }
    let (workers, farm) = (median(workers), median(farms));
    println!("median ratios: workers {workers:.3}; with the coordinator {farm:.3}");
    assert!(
        workers <= 1.10,
        "the workers' CPU is {workers:.3} × the serial CPU (median of {ROUNDS}), over 1.10"
    );
    assert!(
        farm <= 1.25,
        "the farm's CPU is {farm:.3} × the serial CPU (median of {ROUNDS}), over 1.25"
    );
    std::fs::remove_dir_all(&dir).unwrap();
}
