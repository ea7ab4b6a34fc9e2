//! Command-line arguments, converted into a library [`WorkerConfig`].

use std::num::NonZeroUsize;
use std::path::PathBuf;

use clap::Parser;

use crate::{WorkerConfig, WorkerError};

/// Join a hypertexture render farm: dial the coordinator, render the pixel sets it
/// hands out, send the tiles back. Stateless: the scene arrives with the work.
#[derive(Debug, Parser)]
#[command(version, about, long_about = None, after_help = SLURM_HELP)]
pub struct Cli {
    /// The coordinator's address, e.g. http://10.0.0.5:50051 (https:// with --ca).
    #[arg(long, value_name = "URL")]
    pub coordinator: String,
    /// Render threads (default: SLURM_CPUS_PER_TASK under Slurm, else every
    /// core; at most 4 × the cores, and 1024).
    #[arg(long, value_name = "N", value_parser = threads)]
    pub threads: Option<NonZeroUsize>,
    /// Shared secret the coordinator requires.
    #[command(flatten)]
    pub token: TokenArg,
    /// Name shown in the coordinator's logs (default: the Slurm job, e.g.
    /// slurm-1234_3, under Slurm; else host name and process id).
    #[arg(long, value_name = "NAME")]
    pub name: Option<String>,
    /// The coordinator's CA.
    #[command(flatten)]
    pub ca: CaArg,
    /// Exit when the coordinator says the frame is finished (instead of waiting
    /// for the next render). Used for the coordinator's own local workers.
    #[arg(long)]
    pub exit_when_done: bool,
    /// With --exit-when-done: seconds the coordinator may be unreachable before
    /// the worker leaves (exit status 1), as its units' leases run out there.
    #[arg(long, value_name = "SECS", default_value_t = 10.0, value_parser = positive_seconds)]
    pub lease_timeout: f64,
    /// Leave (exit status 0, after a goodbye) once there has been nothing to
    /// render for this long: the coordinator had no unit for this worker, or
    /// could not be reached, including one never reached (default: stay).
    #[arg(long, value_name = "SECS", value_parser = positive_seconds)]
    pub idle_exit: Option<f64>,
    /// A tag for jobs that require it (repeatable), e.g. --tag gpu --tag big-memory:
    /// jobs submitted with --require-tag go only to workers carrying all their tags.
    #[arg(long = "tag", value_name = "NAME", value_parser = tag)]
    pub tag: Vec<String>,
    /// Megabytes of meshes kept between assignments, the least recently used
    /// dropped first (a scene in use keeps its own, whatever their size).
    #[arg(long, value_name = "MB", default_value_t = crate::cache::DEFAULT_ASSET_CACHE_MB,
          value_parser = clap::value_parser!(u64).range(0..=1 << 20))]
    pub asset_cache_mb: u64,
    /// Exit as soon as the process with this id is no longer this worker's
    /// parent (set by the coordinator for its own local workers).
    #[arg(long, value_name = "PID", hide = true)]
    pub parent_pid: Option<u32>,
    /// Only warnings and errors.
    #[arg(long, short)]
    pub quiet: bool,
}

/// `worker --help`'s last paragraph: where the defaults come from under Slurm.
const SLURM_HELP: &str = "Under Slurm (SLURM_JOB_ID set), --name defaults to slurm-JOB \
(slurm-ARRAYJOB_TASK for an array task, with -PROCID added when the step has several tasks) \
and --threads to SLURM_CPUS_PER_TASK. A flag given always wins over the environment.";

impl Cli {
    /// The library configuration these arguments ask for, with the defaults
    /// of this process's environment ([`Cli::into_config_with`]).
    pub fn into_config(self) -> Result<WorkerConfig, WorkerError> {
        self.into_config_with(|name| std::env::var(name).ok())
    }

    /// The library configuration these arguments ask for; a flag left out
    /// takes its default from the environment `env` looks up (Slurm's
    /// variables, [`slurm_name`] and [`slurm_threads`]), then from the machine.
    pub fn into_config_with(
        self,
        env: impl Fn(&str) -> Option<String>,
    ) -> Result<WorkerConfig, WorkerError> {
        let threads = match self.threads {
            Some(n) => n.get(),
            None => match slurm_threads(&env)? {
                Some(n) => n,
                None => std::thread::available_parallelism().map_or(1, NonZeroUsize::get),
            },
        };
        let name = self
            .name
            .clone()
            .or_else(|| slurm_name(&env))
            .unwrap_or_else(default_name);
        let idle_exit = self.idle_exit.map(std::time::Duration::from_secs_f64);
        self.into_config_of(threads, name, idle_exit)
    }

    /// The configuration with the defaults already settled.
    fn into_config_of(
        self,
        threads: usize,
        name: String,
        idle_exit: Option<std::time::Duration>,
    ) -> Result<WorkerConfig, WorkerError> {
        let ca = match &self.ca.ca {
            Some(path) => Some(read_ca(path).map_err(|source| WorkerError::Ca {
                path: path.clone(),
                source,
            })?),
            None => None,
        };
        Ok(WorkerConfig {
            coordinator: self.coordinator,
            threads,
            token: self.token.secret(),
            name,
            ca,
            exit_when_done: self.exit_when_done,
            lease: std::time::Duration::from_secs_f64(self.lease_timeout),
            fault: None,
            shares_process: false,
            tags: self.tag,
            asset_cache_bytes: self.asset_cache_mb << 20,
            idle_exit,
        })
    }
}

/// `--token`: the farm's shared secret (also from `HYPERTEXTURE_TOKEN`),
/// flattened into the worker's and the coordinator's commands; each command
/// words its help with `mut_arg("token", …)`.
#[derive(Clone, Debug, Default, clap::Args)]
pub struct TokenArg {
    /// Shared secret the coordinator requires.
    #[arg(
        long,
        env = "HYPERTEXTURE_TOKEN",
        hide_env_values = true,
        value_name = "TOKEN"
    )]
    pub token: Option<String>,
}

impl TokenArg {
    /// The secret; an empty one is none.
    pub fn secret(self) -> Option<String> {
        self.token.filter(|t| !t.is_empty())
    }
}

/// `--ca`: the CA certificate (PEM) a client trusts the server's TLS
/// certificate by (the worker's coordinator, the coordinator's clients'
/// service).
#[derive(Clone, Debug, Default, clap::Args)]
pub struct CaArg {
    /// CA certificate (PEM) to verify the coordinator's TLS certificate.
    #[arg(long, value_name = "FILE")]
    pub ca: Option<PathBuf>,
}

/// The name of a worker started by Slurm: `slurm-` and the job
/// (`SLURM_JOB_ID`), or for an array task Slurm's own `ARRAYJOB_TASK`
/// (`SLURM_ARRAY_JOB_ID`, `SLURM_ARRAY_TASK_ID`); `-PROCID` added when the
/// step runs several tasks (`SLURM_NTASKS` above 1, `SLURM_PROCID`). `None`
/// outside Slurm.
pub fn slurm_name(env: impl Fn(&str) -> Option<String>) -> Option<String> {
    let var = |name: &str| env(name).filter(|v| !v.trim().is_empty());
    let job = var("SLURM_JOB_ID")?;
    let mut name = match (var("SLURM_ARRAY_JOB_ID"), var("SLURM_ARRAY_TASK_ID")) {
        (Some(array), Some(task)) => format!("slurm-{}_{}", array.trim(), task.trim()),
        _ => format!("slurm-{}", job.trim()),
    };
    let several = var("SLURM_NTASKS").is_some_and(|n| n.trim().parse::<u64>().is_ok_and(|n| n > 1));
    if let (true, Some(proc_id)) = (several, var("SLURM_PROCID")) {
        name.push('-');
        name.push_str(proc_id.trim());
    }
    Some(name)
}

/// The render threads Slurm gave this task: `SLURM_CPUS_PER_TASK`, checked
/// like `--threads`; `None` when it is not set (Slurm leaves it out unless
/// the job asked for `--cpus-per-task`).
pub fn slurm_threads(env: impl Fn(&str) -> Option<String>) -> Result<Option<usize>, WorkerError> {
    match env("SLURM_CPUS_PER_TASK").filter(|v| !v.trim().is_empty()) {
        None => Ok(None),
        Some(v) => {
            threads(v.trim())
                .map(|n| Some(n.get()))
                .map_err(|message| WorkerError::Environment {
                    name: "SLURM_CPUS_PER_TASK",
                    message,
                })
        }
    }
}

/// Host name and process id.
fn default_name() -> String {
    let host = std::fs::read_to_string("/proc/sys/kernel/hostname")
        .map(|h| h.trim().to_string())
        .ok()
        .filter(|h| !h.is_empty())
        .or_else(|| std::env::var("HOSTNAME").ok())
        .unwrap_or_else(|| "worker".into());
    format!("{host}-{}", std::process::id())
}

/// A tag: 1 to 64 of `A-Z a-z 0-9 . _ -`.
fn tag(s: &str) -> Result<String, String> {
    if !s.is_empty()
        && s.len() <= 64
        && s.chars()
            .all(|c| c.is_ascii_alphanumeric() || matches!(c, '.' | '_' | '-'))
    {
        Ok(s.to_string())
    } else {
        Err(format!(
            "expected 1 to 64 of A-Z a-z 0-9 . _ -, found {s:?}"
        ))
    }
}

/// The largest CA certificate file read.
const MAX_CA_BYTES: u64 = 1 << 20;

/// A CA certificate file's bytes: at most [`MAX_CA_BYTES`] are read.
fn read_ca(path: &std::path::Path) -> std::io::Result<Vec<u8>> {
    use std::io::Read as _;
    let mut bytes = Vec::new();
    std::fs::File::open(path)?
        .take(MAX_CA_BYTES + 1)
        .read_to_end(&mut bytes)?;
    if bytes.len() as u64 > MAX_CA_BYTES {
        return Err(std::io::Error::other(format!(
            "larger than {MAX_CA_BYTES} bytes, the most read"
        )));
    }
    Ok(bytes)
}

/// The most render threads one process starts: 4 × the cores, and at most
/// 1024 (more only cost memory and switches).
pub fn max_threads() -> usize {
    let cores = std::thread::available_parallelism().map_or(1, NonZeroUsize::get);
    (4 * cores).min(1024)
}

/// `--threads`: 1 to [`max_threads`].
pub fn threads(s: &str) -> Result<NonZeroUsize, String> {
    let n: NonZeroUsize = s
        .parse()
        .map_err(|_| format!("expected a number of threads from 1, found {s:?}"))?;
    let max = max_threads();
    if n.get() > max {
        let cores = std::thread::available_parallelism().map_or(1, NonZeroUsize::get);
        return Err(format!(
            "{n} threads is too many: at most {max} (4 × the {cores} cores, and no more than 1024)"
        ));
    }
    Ok(n)
}

/// Seconds: a finite number above 0 and at most a day (the time-outs of the
/// worker's and the coordinator's commands).
pub fn positive_seconds(s: &str) -> Result<f64, String> {
    let v: f64 = s
        .parse()
        .map_err(|_| format!("expected a number of seconds, found {s:?}"))?;
    if v.is_finite() && v > 0.0 && v <= 86_400.0 {
        Ok(v)
    } else {
        Err(format!("expected seconds between 0 and 86400, found {s}"))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn parse(args: &[&str]) -> Result<Cli, String> {
        Cli::try_parse_from(std::iter::once("worker").chain(args.iter().copied()))
            .map_err(|e| e.to_string())
    }

    #[test]
    fn connection_flags_become_the_config() {
        let cli = parse(&[
            "--coordinator",
            "http://10.0.0.5:50051",
            "--token",
            "s3cret",
            "--threads",
            "1",
            "--name",
            "w1",
            "--tag",
            "gpu",
            "--lease-timeout",
            "2.5",
            "--exit-when-done",
        ])
        .unwrap();
        let config = cli.into_config().unwrap();
        assert_eq!(config.coordinator, "http://10.0.0.5:50051");
        assert_eq!(config.token.as_deref(), Some("s3cret"));
        assert_eq!((config.threads, config.name.as_str()), (1, "w1"));
        assert_eq!(config.tags, ["gpu"]);
        assert_eq!(config.lease, std::time::Duration::from_millis(2500));
        assert!(config.exit_when_done && config.ca.is_none());
    }

    /// The environment of a Slurm task: `vars` as (name, value) pairs.
    fn slurm(vars: &[(&'static str, &'static str)]) -> impl Fn(&str) -> Option<String> + use<> {
        let vars = vars.to_vec();
        move |name: &str| {
            vars.iter()
                .find(|(n, _)| *n == name)
                .map(|(_, v)| v.to_string())
        }
    }

    #[test]
    fn under_slurm_the_name_and_threads_come_from_the_job() {
        let array = slurm(&[
            ("SLURM_JOB_ID", "1237"),
            ("SLURM_ARRAY_JOB_ID", "1234"),
            ("SLURM_ARRAY_TASK_ID", "3"),
            ("SLURM_CPUS_PER_TASK", "2"),
            ("SLURM_NTASKS", "1"),
            ("SLURM_PROCID", "0"),
        ]);
        let config = parse(&["--coordinator", "http://c"])
            .unwrap()
            .into_config_with(&array)
            .unwrap();
        assert_eq!((config.name.as_str(), config.threads), ("slurm-1234_3", 2));
        let step = slurm(&[
            ("SLURM_JOB_ID", "77"),
            ("SLURM_NTASKS", "4"),
            ("SLURM_PROCID", "2"),
        ]);
        assert_eq!(slurm_name(&step).as_deref(), Some("slurm-77-2"));
        assert_eq!(
            slurm_name(slurm(&[("SLURM_JOB_ID", "77")])).as_deref(),
            Some("slurm-77")
        );
        assert_eq!(slurm_name(slurm(&[])), None, "outside Slurm");
        assert_eq!(slurm_threads(slurm(&[])).unwrap(), None);
    }

    #[test]
    fn a_flag_given_wins_over_slurm() {
        let env = slurm(&[("SLURM_JOB_ID", "9"), ("SLURM_CPUS_PER_TASK", "2")]);
        let config = parse(&[
            "--coordinator",
            "http://c",
            "--name",
            "mine",
            "--threads",
            "1",
        ])
        .unwrap()
        .into_config_with(&env)
        .unwrap();
        assert_eq!((config.name.as_str(), config.threads), ("mine", 1));
        let outside = parse(&["--coordinator", "http://c"])
            .unwrap()
            .into_config_with(slurm(&[]))
            .unwrap();
        assert!(!outside.name.starts_with("slurm-"), "{}", outside.name);
        assert_eq!(
            outside.threads,
            std::thread::available_parallelism().map_or(1, NonZeroUsize::get)
        );
    }

    #[test]
    fn a_bad_slurm_cpus_per_task_is_named() {
        for bad in ["0", "many", "999999"] {
            let env = slurm(&[("SLURM_JOB_ID", "9"), ("SLURM_CPUS_PER_TASK", bad)]);
            let e = parse(&["--coordinator", "http://c"])
                .unwrap()
                .into_config_with(&env)
                .unwrap_err();
            let text = e.to_string();
            assert!(
                matches!(
                    e,
                    WorkerError::Environment {
                        name: "SLURM_CPUS_PER_TASK",
                        ..
                    }
                ),
                "{bad}: {text}"
            );
            assert!(text.contains("SLURM_CPUS_PER_TASK"), "{text}");
        }
        // The flag given, the variable is not read.
        let env = slurm(&[("SLURM_CPUS_PER_TASK", "0")]);
        let config = parse(&["--coordinator", "http://c", "--threads", "1"])
            .unwrap()
            .into_config_with(&env)
            .unwrap();
        assert_eq!(config.threads, 1);
    }

    #[test]
    fn idle_exit_is_seconds_or_none() {
        let config = parse(&["--coordinator", "http://c", "--idle-exit", "1.5"])
            .unwrap()
            .into_config()
            .unwrap();
        assert_eq!(
            config.idle_exit,
            Some(std::time::Duration::from_millis(1500))
        );
        let config = parse(&["--coordinator", "http://c"])
            .unwrap()
            .into_config()
            .unwrap();
        assert_eq!(config.idle_exit, None);
        let e = parse(&["--coordinator", "http://c", "--idle-exit", "0"]).unwrap_err();
        assert!(e.contains("--idle-exit"), "{e}");
    }

    #[test]
    fn an_empty_token_is_none() {
        let cli = parse(&["--coordinator", "http://c", "--token", ""]).unwrap();
        assert_eq!(cli.token.clone().secret(), None);
        assert_eq!(cli.into_config().unwrap().token, None);
    }

    #[test]
    fn a_missing_ca_file_is_named() {
        let cli = parse(&["--coordinator", "https://c", "--ca", "/nonexistent/ca.pem"]).unwrap();
        match cli.into_config() {
            Err(WorkerError::Ca { path, .. }) => {
                assert_eq!(path, PathBuf::from("/nonexistent/ca.pem"));
            }
            other => panic!("expected a CA error, found {other:?}"),
        }
    }

    #[test]
    fn refusals_name_the_flag() {
        for (args, flag) in [
            (
                &["--coordinator", "http://c", "--threads", "0"][..],
                "--threads",
            ),
            (&["--coordinator", "http://c", "--tag", "a b"], "--tag"),
            (
                &["--coordinator", "http://c", "--lease-timeout", "0"],
                "--lease-timeout",
            ),
            (&["--token", "t"], "--coordinator"),
        ] {
            let e = parse(args)
                .err()
                .unwrap_or_else(|| panic!("{args:?} was accepted"));
            assert!(e.contains(flag), "{args:?}: {e}");
        }
    }

    #[test]
    fn help_words_the_shared_flags_for_the_worker() {
        use clap::CommandFactory;
        let help = Cli::command().render_help().to_string();
        for words in [
            "--token <TOKEN>",
            "Shared secret the coordinator requires",
            "--ca <FILE>",
            "CA certificate (PEM) to verify the coordinator's TLS certificate",
            "--idle-exit <SECS>",
            "SLURM_CPUS_PER_TASK",
            "A flag given always wins over the environment",
        ] {
            assert!(help.contains(words), "{words:?}:\n{help}");
        }
    }
}
