//! The farm's progress bar: units done, and each worker's throughput.

use std::time::Instant;

use crate::farm::scheduler::Scheduler;

/// A progress bar on stderr when it is a terminal (hidden otherwise).
pub struct FarmProgress(indicatif::ProgressBar);

impl FarmProgress {
    /// A bar over `units` units, shown when `enabled` and stderr is a terminal.
    pub fn new(enabled: bool, units: u64) -> FarmProgress {
        use std::io::IsTerminal;
        if !enabled || !std::io::stderr().is_terminal() {
            return FarmProgress(indicatif::ProgressBar::hidden());
        }
        let bar = indicatif::ProgressBar::new(units);
        bar.set_style(
            indicatif::ProgressStyle::with_template(
                "{spinner} [{elapsed_precise}] {bar:30} {pos}/{len} units {msg}",
            )
            .unwrap_or_else(|_| indicatif::ProgressStyle::default_bar()),
        );
        FarmProgress(bar)
    }

    /// Shows the scheduler's state: units done, and kilopixels per second per worker.
    pub fn update(&self, s: &Scheduler, now: Instant) {
        if self.0.is_hidden() {
            return;
        }
        self.0.set_position(s.progress().0 as u64);
        let rates: Vec<String> = s
            .workers()
            .filter(|w| w.alive)
            .map(|w| {
                let secs = now.duration_since(w.joined).as_secs_f64().max(1e-3);
                format!("{} {:.0} kpx/s", w.name, w.pixels as f64 / secs / 1000.0)
            })
            .collect();
        self.0.set_message(rates.join(", "));
    }

    /// Clears the bar.
    pub fn finish(&self) {
        self.0.finish_and_clear();
    }
}
