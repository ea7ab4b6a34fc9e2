//! What keeps the service's memory, store and answers bounded: the queue
//! limit (`--max-queued`), how long ended jobs are kept (`--keep-ended`), and
//! the page size of `GET /api/v1/jobs`.

use std::time::Duration;

/// Jobs not ended (queued or running) a service holds by default; one more
/// submission is refused with 429.
pub const DEFAULT_MAX_QUEUED: usize = 10_000;

/// What a refused submission's `Retry-After` says, in seconds.
pub const RETRY_AFTER_SECS: u64 = 30;

/// Jobs a page of `GET /api/v1/jobs` holds unless `limit` says otherwise.
pub const DEFAULT_PAGE: usize = 100;

/// The largest `limit` of `GET /api/v1/jobs`.
pub const MAX_PAGE: usize = 1000;

/// How often the supervisor prunes ended jobs.
pub const PRUNE_EVERY: Duration = Duration::from_secs(1);

/// How long ended jobs are kept (`--keep-ended`): for at most `age` after they
/// ended, and only the `count` that ended last. Their files are never touched.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct KeepEnded {
    /// The longest an ended job is kept.
    pub age: Option<Duration>,
    /// The most ended jobs kept.
    pub count: Option<usize>,
}

impl Default for KeepEnded {
    /// Seven days, and 1,000 jobs.
    fn default() -> KeepEnded {
        KeepEnded {
            age: Some(Duration::from_secs(7 * 24 * 3600)),
            count: Some(1000),
        }
    }
}

/// `--keep-ended`'s default, as written on the command line.
pub const DEFAULT_KEEP_ENDED: &str = "7d,1000";

impl std::str::FromStr for KeepEnded {
    type Err = String;

    /// A comma-separated list of an age (`7d`, `12h`, `30m`, `90s`) and a
    /// count of jobs (`1000`), either or both.
    fn from_str(s: &str) -> Result<KeepEnded, String> {
        let mut keep = KeepEnded {
            age: None,
            count: None,
        };
        for part in s.split(',').map(str::trim) {
            let bad = || {
                format!(
                    "{part:?}: expected an age (7d, 12h, 30m, 90s) or a number of jobs (1000), comma-separated"
                )
            };
            if let Ok(n) = part.parse::<usize>() {
                if keep.count.replace(n).is_some() {
                    return Err(format!("{s:?}: two counts of jobs"));
                }
                continue;
            }
            let digits = part.trim_end_matches(|c: char| c.is_ascii_alphabetic());
            let unit = match &part[digits.len()..] {
                "s" => 1,
                "m" => 60,
                "h" => 3600,
                "d" => 86_400,
                _ => return Err(bad()),
            };
            let n: u64 = digits.parse().map_err(|_| bad())?;
            let secs = n.checked_mul(unit).ok_or_else(bad)?;
            if keep.age.replace(Duration::from_secs(secs)).is_some() {
                return Err(format!("{s:?}: two ages"));
            }
        }
        Ok(keep)
    }
}

impl KeepEnded {
    /// Of the ended jobs `(id, age)`, the ones to prune: older than the age,
    /// or beyond the count of the newest (by id, the order they were submitted).
    pub fn to_prune(&self, mut ended: Vec<(u64, Duration)>) -> Vec<u64> {
        ended.sort_unstable_by_key(|&(id, _)| std::cmp::Reverse(id));
        ended
            .iter()
            .enumerate()
            .filter(|(i, (_, age))| {
                self.count.is_some_and(|n| *i >= n) || self.age.is_some_and(|max| *age > max)
            })
            .map(|(_, (id, _))| *id)
            .collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn keep_ended_reads_ages_and_counts() {
        assert_eq!(
            DEFAULT_KEEP_ENDED.parse::<KeepEnded>(),
            Ok(KeepEnded::default())
        );
        let k: KeepEnded = "90s".parse().unwrap();
        assert_eq!(k.age, Some(Duration::from_secs(90)));
        assert_eq!(k.count, None);
        let k: KeepEnded = "5".parse().unwrap();
        assert_eq!((k.age, k.count), (None, Some(5)));
        for bad in ["7w", "", "1d,2d", "d", "3,4"] {
            assert!(bad.parse::<KeepEnded>().is_err(), "{bad}");
        }
        let k = KeepEnded {
            age: Some(Duration::from_secs(10)),
            count: Some(2),
        };
        let s = Duration::from_secs;
        let pruned = k.to_prune(vec![(1, s(1)), (2, s(11)), (3, s(1)), (4, s(1))]);
        assert_eq!(pruned, vec![2, 1]);
    }
}
