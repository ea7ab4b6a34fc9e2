//! CPU time: of one thread (the async thread's, a render thread's) and of
//! the process, for the statistics each tile carries.

/// The CPU-time clock of one thread, readable from any thread (Linux's
/// `pthread_getcpuclockid`); reads 0 where the OS offers none.
#[derive(Clone, Copy, Debug)]
pub(crate) struct CpuClock(Option<ClockId>);

#[cfg(target_os = "linux")]
type ClockId = libc::clockid_t;
#[cfg(not(target_os = "linux"))]
type ClockId = ();

impl CpuClock {
    /// The clock of the calling thread.
    pub(crate) fn of_this_thread() -> CpuClock {
        #[cfg(target_os = "linux")]
        {
            let mut id: libc::clockid_t = 0;
            // SAFETY: pthread_self is the calling thread, alive; the call only
            // writes the clock id into `id`.
            let ok = unsafe { libc::pthread_getcpuclockid(libc::pthread_self(), &mut id) } == 0;
            CpuClock(ok.then_some(id))
        }
        #[cfg(not(target_os = "linux"))]
        {
            CpuClock(None)
        }
    }

    /// The thread's CPU time so far, in microseconds.
    pub(crate) fn micros(self) -> u64 {
        #[cfg(target_os = "linux")]
        {
            let Some(id) = self.0 else { return 0 };
            let mut t = libc::timespec {
                tv_sec: 0,
                tv_nsec: 0,
            };
            // SAFETY: clock_gettime only writes into `t`; a clock of a thread
            // that has exited gives an error, read as 0.
            if unsafe { libc::clock_gettime(id, &mut t) } != 0 {
                return 0;
            }
            t.tv_sec as u64 * 1_000_000 + t.tv_nsec as u64 / 1000
        }
        #[cfg(not(target_os = "linux"))]
        {
            0
        }
    }
}

/// The async thread's CPU time between one tile and the next.
pub(crate) struct CallsCpu {
    clock: CpuClock,
    last: u64,
}

impl CallsCpu {
    pub(crate) fn new(clock: CpuClock) -> CallsCpu {
        CallsCpu {
            clock,
            last: clock.micros(),
        }
    }

    /// Microseconds since the last call (or since `new`).
    pub(crate) fn since_last(&mut self) -> u64 {
        let now = self.clock.micros();
        let d = now.saturating_sub(self.last);
        self.last = now;
        d
    }
}

/// The process's CPU time (user + system) in microseconds, from the OS.
pub fn process_cpu_micros() -> u64 {
    #[cfg(unix)]
    {
        // SAFETY: getrusage only writes into the zeroed struct we pass.
        let mut usage: libc::rusage = unsafe { std::mem::zeroed() };
        if unsafe { libc::getrusage(libc::RUSAGE_SELF, &mut usage) } != 0 {
            return 0;
        }
        let micros = |t: libc::timeval| t.tv_sec as u64 * 1_000_000 + t.tv_usec as u64;
        micros(usage.ru_utime) + micros(usage.ru_stime)
    }
    #[cfg(not(unix))]
    {
        0
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Spins until this thread has used some CPU.
    fn burn(clock: CpuClock) {
        let start = clock.micros();
        let mut x = 1u64;
        let deadline = std::time::Instant::now() + std::time::Duration::from_secs(5);
        while clock.micros() <= start && std::time::Instant::now() < deadline {
            for i in 0..100_000u64 {
                x = std::hint::black_box(x.wrapping_mul(6364136223846793005).wrapping_add(i));
            }
        }
    }

    #[cfg(target_os = "linux")]
    #[test]
    fn a_threads_clock_counts_its_own_cpu() {
        let clock = CpuClock::of_this_thread();
        let mut calls = CallsCpu::new(clock);
        let before = clock.micros();
        burn(clock);
        assert!(clock.micros() > before);
        assert!(calls.since_last() > 0);
        assert!(process_cpu_micros() >= clock.micros());
    }
}
