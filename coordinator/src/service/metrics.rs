//! The service's metrics in the Prometheus text exposition format (0.0.4),
//! written from a snapshot of the farm at each scrape: nothing is counted
//! twice, and nothing can drift from what `/api/v1` shows.
//!
//! Series labelled by job exist only for running jobs (a unit handed out,
//! not ended): the number of series is bounded by the jobs being rendered,
//! never by the queue's length or its history. `promtool check metrics`
//! passes on the text (`tests/service/limits.rs`).

use std::fmt::Write;

use crate::farm::scheduler::JobId;
use crate::farm::{FarmStats, LATENCY_BUCKETS};
use crate::service::jobs::{JobState, JobView, WorkerView};

/// What a scrape shows.
pub struct Snapshot<'a> {
    /// The running jobs.
    pub jobs: &'a [JobView],
    /// How many jobs are in each state, in the order of [`JobState::ALL`].
    pub job_states: &'a [usize; JobState::ALL.len()],
    /// Every connected worker.
    pub workers: &'a [WorkerView],
    /// The farm's counters.
    pub stats: &'a FarmStats,
    /// Units waiting to be handed out, over every job.
    pub queued_all: u64,
    /// Units waiting to be handed out, by running job.
    pub queued: &'a [(JobId, u64)],
    /// Units held by workers, by running job.
    pub in_flight: &'a [(JobId, u64)],
    /// The store: whether it writes, and the tiles dropped because their
    /// stored bytes no longer matched their checksum.
    pub store: StoreHealth,
}

/// The store's side of a scrape.
#[derive(Clone, Copy, Debug, Default)]
pub struct StoreHealth {
    /// Whether the store's last write succeeded.
    pub writable: bool,
    /// Tiles read back that failed their checksum (dropped, rendered again).
    pub tiles_dropped: u64,
}

/// A label value with `\`, `"` and newlines escaped.
fn label(value: &str) -> String {
    let mut out = String::with_capacity(value.len());
    for c in value.chars() {
        match c {
            '\\' => out.push_str("\\\\"),
            '"' => out.push_str("\\\""),
            '\n' => out.push_str("\\n"),
            c if c.is_control() => {}
            c => out.push(c),
        }
    }
    out
}

fn header(out: &mut String, name: &str, kind: &str, help: &str) {
    let _ = writeln!(out, "# HELP {name} {help}");
    let _ = writeln!(out, "# TYPE {name} {kind}");
}

/// The exposition text.
pub fn render(s: &Snapshot<'_>) -> String {
    let mut out = String::new();
    health(&mut out, s);
    units(&mut out, s);
    jobs_and_workers(&mut out, s);
    latency(&mut out, s.stats);
    counters(&mut out, s.stats);
    out
}

/// Whether the store writes, the tiles it dropped, the workers connected.
fn health(out: &mut String, s: &Snapshot<'_>) {
    header(
        out,
        "hypertexture_store_writable",
        "gauge",
        "1 while the store writes; 0 while its writes fail (disk full, I/O error): tiles are refused and handed out again, submissions refused.",
    );
    let _ = writeln!(
        out,
        "hypertexture_store_writable {}",
        u8::from(s.store.writable)
    );
    header(
        out,
        "hypertexture_store_tiles_dropped_total",
        "counter",
        "Stored tiles read back whose bytes did not match their checksum: dropped and rendered again.",
    );
    let _ = writeln!(
        out,
        "hypertexture_store_tiles_dropped_total {}",
        s.store.tiles_dropped
    );
    header(
        out,
        "hypertexture_workers_connected",
        "gauge",
        "Workers connected to the farm.",
    );
    let _ = writeln!(out, "hypertexture_workers_connected {}", s.workers.len());
}

/// Units queued (over every job and by running job), in flight and done.
fn units(out: &mut String, s: &Snapshot<'_>) {
    header(
        out,
        "hypertexture_farm_units_queued",
        "gauge",
        "Units waiting to be handed out, over every job (what an autoscaler watches).",
    );
    let _ = writeln!(out, "hypertexture_farm_units_queued {}", s.queued_all);

    header(
        out,
        "hypertexture_units_queued",
        "gauge",
        "Units of the frame rendering waiting to be handed out, by running job.",
    );
    for (job, n) in s.queued {
        let _ = writeln!(out, "hypertexture_units_queued{{job=\"{job}\"}} {n}");
    }
    header(
        out,
        "hypertexture_units_in_flight",
        "gauge",
        "Units held by workers, by running job.",
    );
    for (job, n) in s.in_flight {
        let _ = writeln!(out, "hypertexture_units_in_flight{{job=\"{job}\"}} {n}");
    }
    header(
        out,
        "hypertexture_units_done",
        "gauge",
        "Units complete, over every frame, by running job.",
    );
    for j in s.jobs {
        let _ = writeln!(
            out,
            "hypertexture_units_done{{job=\"{}\"}} {}",
            j.id, j.units_done
        );
    }
}

/// Jobs by state, and each worker's pixels per second.
fn jobs_and_workers(out: &mut String, s: &Snapshot<'_>) {
    header(out, "hypertexture_jobs", "gauge", "Jobs by state.");
    for (state, n) in JobState::ALL.iter().zip(s.job_states) {
        let _ = writeln!(out, "hypertexture_jobs{{state=\"{}\"}} {n}", state.as_str());
    }
    header(
        out,
        "hypertexture_worker_pixels_per_second",
        "gauge",
        "Pixels per second over the last minute, by worker.",
    );
    for w in s.workers {
        let _ = writeln!(
            out,
            "hypertexture_worker_pixels_per_second{{worker=\"{}\",name=\"{}\"}} {}",
            label(&w.id),
            label(&w.name),
            w.pixels_per_second
        );
    }
}

/// The histogram of unit latencies, from assignment to accepted tile.
fn latency(out: &mut String, stats: &FarmStats) {
    header(
        out,
        "hypertexture_unit_latency_seconds",
        "histogram",
        "From a unit's assignment to its accepted tile.",
    );
    let mut cumulative = 0;
    for (i, bound) in LATENCY_BUCKETS.iter().enumerate() {
        cumulative += stats.latency_buckets[i];
        let _ = writeln!(
            out,
            "hypertexture_unit_latency_seconds_bucket{{le=\"{bound}\"}} {cumulative}"
        );
    }
    cumulative += stats.latency_buckets[LATENCY_BUCKETS.len()];
    let _ = writeln!(
        out,
        "hypertexture_unit_latency_seconds_bucket{{le=\"+Inf\"}} {cumulative}"
    );
    let _ = writeln!(
        out,
        "hypertexture_unit_latency_seconds_sum {}",
        stats.latency_sum
    );
    let _ = writeln!(
        out,
        "hypertexture_unit_latency_seconds_count {}",
        stats.latency_count
    );
}

/// The farm's counters.
fn counters(out: &mut String, stats: &FarmStats) {
    for (name, help, value) in [
        (
            "hypertexture_unit_retries_total",
            "Units given back by a worker (ReportFailure) and queued again.",
            stats.retries,
        ),
        (
            "hypertexture_workers_blocklisted_total",
            "Workers blocklisted for a job after failing 3 of its units.",
            stats.blocklisted,
        ),
        (
            "hypertexture_workers_refused_total",
            "Registrations refused (protocol or arithmetic mismatch).",
            stats.refused_workers,
        ),
        (
            "hypertexture_calls_unauthenticated_total",
            "Worker calls refused for a missing or wrong token.",
            stats.unauthenticated,
        ),
        (
            "hypertexture_handler_panics_total",
            "Requests whose handler panicked: each answered 500 (gRPC: INTERNAL), the service going on.",
            stats.handler_panics,
        ),
    ] {
        header(out, name, "counter", help);
        let _ = writeln!(out, "{name} {value}");
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_exposition_is_well_formed_and_escapes_labels() {
        let mut stats = FarmStats::default();
        stats.latency_buckets[0] = 2;
        stats.latency_buckets[LATENCY_BUCKETS.len()] = 1;
        stats.latency_count = 3;
        let workers = [WorkerView {
            id: "w1".into(),
            name: "evil\"\nname".into(),
            tags: vec![],
            threads: 1,
            pixels_per_second: 10.0,
            current_job: None,
            units: 1,
            blocklisted_for: vec![],
        }];
        let text = render(&Snapshot {
            jobs: &[],
            job_states: &[0, 1, 0, 0, 0],
            workers: &workers,
            stats: &stats,
            queued_all: 7,
            queued: &[(4, 7)],
            in_flight: &[(4, 1)],
            store: StoreHealth {
                writable: false,
                tiles_dropped: 3,
            },
        });
        assert!(text.contains("hypertexture_store_writable 0\n"), "{text}");
        assert!(
            text.contains("hypertexture_store_tiles_dropped_total 3\n"),
            "{text}"
        );
        assert!(
            text.contains("hypertexture_farm_units_queued 7\n"),
            "{text}"
        );
        assert!(text.contains("hypertexture_jobs{state=\"running\"} 1\n"));
        assert!(text.contains("hypertexture_units_queued{job=\"4\"} 7\n"));
        assert!(text.contains("name=\"evil\\\"\\nname\""), "{text}");
        assert!(text.contains("hypertexture_unit_latency_seconds_bucket{le=\"+Inf\"} 3\n"));
        assert!(text.contains("hypertexture_unit_latency_seconds_bucket{le=\"0.005\"} 2\n"));
        assert!(text.contains("hypertexture_jobs{state=\"queued\"} 0\n"));
        for line in text.lines().filter(|l| !l.starts_with('#')) {
            let value = line.rsplit(' ').next().unwrap();
            assert!(value.parse::<f64>().is_ok(), "{line}");
        }
    }
}
