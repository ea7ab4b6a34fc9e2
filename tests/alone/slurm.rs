//! Slurm for real: a one-node cluster of Debian's `slurm-wlm` (installed by
//! `scripts/test-deps/slurm.sh`) started in a scratch directory, with its
//! own munged (key, socket, pid file), `slurm.conf`, state and spool
//! directories and loopback ports; `ProctrackType=proctrack/linuxproc`,
//! `TaskPlugin=task/none`, no cgroup.conf. The committed
//! `deploy/slurm/workers-array.sbatch` is submitted as an array of workers
//! against a one-shot coordinator: the image is the in-process one byte for
//! byte, every task ends on its own within its deadline (tasks that start
//! after the frame is done, against a coordinator they never reach,
//! included), and `scancel` of half the tasks mid-frame still gives the exact
//! image. Every daemon is stopped by its pid. Slurm runs jobs as root here,
//! so the test needs root, as the package install does.
//!
//! It holds [`alone`]: its workers render on the machine's cores beside
//! nothing else of this binary.

use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant, SystemTime};

use crate::support::*;

/// Seconds without work after which an array task's worker leaves
/// (`HYPERTEXTURE_IDLE_EXIT`).
const IDLE_EXIT: f64 = 3.0;

/// How long past the end of its work (the frame written, or its own start
/// when that came later) a task may take to end: its idle time and the
/// time Slurm and a loaded machine take to start and reap it.
const TASK_DEADLINE_SECS: f64 = IDLE_EXIT + 12.0;

/// How long a task cancelled mid-frame may take to leave Slurm's queue.
const CANCEL_DEADLINE_SECS: u64 = 15;

#[test]
fn an_array_of_slurm_workers_renders_the_exact_image_and_every_task_ends() {
    let _alone = alone();
    let dir = scratch("slurm");
    let started = Instant::now();
    let cluster = Cluster::start(&dir);
    eprintln!(
        "slurm: the cluster was up in {:.1} s",
        started.elapsed().as_secs_f64()
    );

    // Six tasks on four CPUs: two start only once the frame is done and its
    // coordinator gone, never reach it, and still leave.
    let reference = dir.join("reference.png");
    let flags = ["--spp", "2"];
    in_process(
        "fur",
        &reference,
        &[&["--width", "64", "--height", "64"][..], &flags].concat(),
    );
    let out = dir.join("array.png");
    let (coord, url) = remote_only("fur", 64, &out, &flags);
    let submitted = now();
    let job = cluster.submit_workers(&url, "0-5");
    let (status, log) = coord.finish(180);
    let frame_done = now();
    eprintln!(
        "slurm: the frame was done {:.1} s after sbatch",
        frame_done - submitted
    );
    assert!(status.success(), "coordinator:\n{}", log.join("\n"));
    same_bytes(&reference, &out);
    assert!(
        log.iter()
            .any(|l| l.contains(&format!("worker slurm-{job}_")) && l.contains(" joined from ")),
        "the workers are named after their array task:\n{}",
        log.join("\n")
    );
    cluster.wait_gone(&job, 60);
    let tasks = cluster.task_logs(&job, 6);
    for task in &tasks {
        task.ended_on_its_own(frame_done);
    }
    assert!(
        tasks.iter().any(|t| t.text.contains("cannot reach")),
        "no task started after the frame was done:\n{}",
        tasks.iter().map(|t| t.text.as_str()).collect::<String>()
    );
    std::fs::remove_file(&out).unwrap();

    half_the_array_cancelled_mid_frame(&cluster, &dir);
    drop(cluster);
    std::fs::remove_dir_all(&dir).unwrap();
}

/// Four tasks render a frame; two are cancelled once all have joined and
/// before it is done: the image is still exact, and the cancelled tasks
/// leave the queue within [`CANCEL_DEADLINE_SECS`].
fn half_the_array_cancelled_mid_frame(cluster: &Cluster, dir: &Path) {
    // About 2 s of the farm's work on two cores: long enough for the cancel
    // to land mid-frame.
    let flags = ["--spp", "64"];
    let reference = dir.join("reference-96.png");
    in_process(
        "fur",
        &reference,
        &[&["--width", "96", "--height", "96"][..], &flags].concat(),
    );
    let out = dir.join("cancelled.png");
    let (mut coord, url) = remote_only("fur", 96, &out, &flags);
    let job = cluster.submit_workers(&url, "0-3");
    let joined = |log: &[String]| {
        (0..4).all(|t| {
            let line = format!("worker slurm-{job}_{t} joined");
            log.iter().any(|l| l.contains(&line))
        })
    };
    let deadline = Instant::now() + Duration::from_secs(60);
    while !joined(&coord.log) {
        let left = deadline.saturating_duration_since(Instant::now());
        match coord.lines.recv_timeout(left) {
            Ok(line) => coord.log.push(line),
            Err(_) => panic!(
                "the four tasks did not join within 60 s:\n{}",
                coord.log.join("\n")
            ),
        }
    }
    assert!(
        !out.exists() && !coord.log.iter().any(|l| l.contains("rendered ")),
        "the frame was done before the cancel: make it larger"
    );
    let cancelled = Instant::now();
    let o = output_within(
        cluster
            .command("scancel")
            .args([format!("{job}_0"), format!("{job}_1")]),
        30,
    );
    assert!(
        o.status.success(),
        "scancel: {}",
        String::from_utf8_lossy(&o.stderr)
    );
    let (status, log) = coord.finish(180);
    let frame_done = now();
    assert!(status.success(), "coordinator:\n{}", log.join("\n"));
    same_bytes(&reference, &out);
    until(
        CANCEL_DEADLINE_SECS,
        "the cancelled tasks leave the queue",
        || {
            let left = cluster.queued(&job);
            !left.contains(&format!("{job}_0")) && !left.contains(&format!("{job}_1"))
        },
    );
    eprintln!(
        "slurm: the cancelled tasks left the queue {:.1} s after scancel",
        cancelled.elapsed().as_secs_f64()
    );
    cluster.wait_gone(&job, 60);
    let tasks = cluster.task_logs(&job, 4);
    for task in &tasks[..2] {
        // SIGTERM from scancel: the unit rendering delivered, the goodbye said.
        assert!(
            task.text.contains("shutting down") && task.text.contains("leaving after"),
            "{} left without its goodbye:\n{}",
            task.name,
            task.text
        );
    }
    for task in &tasks[2..] {
        task.ended_on_its_own(frame_done);
    }
}

/// Seconds since the epoch, the clock `date +%s.%N` reads in the task logs.
fn now() -> f64 {
    SystemTime::now()
        .duration_since(SystemTime::UNIX_EPOCH)
        .unwrap()
        .as_secs_f64()
}

/// An array task's log, as `workers-array.sbatch` writes it.
struct TaskLog {
    name: String,
    text: String,
}

impl TaskLog {
    /// The number after `marker` on the line holding it.
    fn time(&self, marker: &str) -> f64 {
        self.text
            .lines()
            .find(|l| l.contains(marker))
            .and_then(|l| l.split(marker).nth(1))
            .and_then(|rest| rest.split_whitespace().next())
            .and_then(|t| t.parse().ok())
            .unwrap_or_else(|| panic!("{}: no {marker:?} line:\n{}", self.name, self.text))
    }

    /// The task ended with status 0 within [`TASK_DEADLINE_SECS`] of the
    /// end of its work, and its log holds no escape code.
    fn ended_on_its_own(&self, frame_done: f64) {
        let started = self.time(" started at ");
        let ended = self.time(" ended at ");
        assert!(
            self.text.contains("with status 0"),
            "{}:\n{}",
            self.name,
            self.text
        );
        let late = ended - started.max(frame_done);
        eprintln!(
            "slurm: {} ran {:.1} s, ended {late:.1} s after its work",
            self.name,
            ended - started
        );
        assert!(
            late <= TASK_DEADLINE_SECS,
            "{} ended {late:.1} s after its work (at most {TASK_DEADLINE_SECS} s):\n{}",
            self.name,
            self.text
        );
        assert!(
            !self.text.contains('\u{1b}'),
            "{}: colour codes in a log file:\n{}",
            self.name,
            self.text
        );
    }
}

/// A one-node Slurm cluster of this test's own: munged, slurmctld and
/// slurmd, each a child of this process, stopped by its pid on drop.
struct Cluster {
    dir: PathBuf,
    conf: PathBuf,
    /// The daemons in the order they started: munged, slurmctld, slurmd.
    daemons: Vec<(&'static str, Child)>,
}

impl Cluster {
    /// Writes the configuration and starts the daemons; returns once the
    /// node is idle (at most 60 s).
    fn start(dir: &Path) -> Cluster {
        let dir = dir.join("cluster");
        for sub in ["state", "spool"] {
            std::fs::create_dir_all(dir.join(sub)).unwrap();
        }
        let mut cluster = Cluster {
            conf: dir.join("slurm.conf"),
            dir,
            daemons: Vec::new(),
        };
        cluster.start_munge();
        std::fs::write(&cluster.conf, cluster.slurm_conf()).unwrap();
        let conf = cluster.conf.to_str().unwrap().to_string();
        cluster.daemon("slurmctld", &["-D", "-i", "-f", &conf]);
        cluster.daemon("slurmd", &["-D", "-N", "ht1", "-f", &conf]);
        until(60, "the Slurm node is idle", || {
            cluster.daemons_alive();
            let o = output_within(cluster.command("sinfo").args(["-h", "-o", "%T"]), 30);
            String::from_utf8_lossy(&o.stdout).trim() == "idle"
        });
        cluster
    }

    /// munged with a key, socket, pid and seed file of its own.
    fn start_munge(&mut self) {
        let key = self.dir.join("munge.key");
        let mut bytes = vec![0u8; 1024];
        std::fs::File::open("/dev/urandom")
            .and_then(|mut r| std::io::Read::read_exact(&mut r, &mut bytes))
            .unwrap();
        std::fs::write(&key, bytes).unwrap();
        use std::os::unix::fs::PermissionsExt;
        std::fs::set_permissions(&key, std::fs::Permissions::from_mode(0o400)).unwrap();
        let at = |name: &str| format!("{}", self.dir.join(name).display());
        let args = [
            "--foreground".to_string(),
            "--force".into(),
            format!("--socket={}", at("munge.socket")),
            format!("--key-file={}", at("munge.key")),
            format!("--pid-file={}", at("munged.pid")),
            format!("--log-file={}", at("munged.log")),
            format!("--seed-file={}", at("munged.seed")),
        ];
        let args: Vec<&str> = args.iter().map(String::as_str).collect();
        self.daemon("munged", &args);
        let socket = self.dir.join("munge.socket");
        until(30, "munged's socket", || {
            self.daemons_alive();
            socket.exists()
        });
    }

    /// `slurm.conf`: one node of four CPUs on loopback, ports from the kernel.
    fn slurm_conf(&self) -> String {
        let d = self.dir.display();
        let (ctld, slurmd) = (free_port(), free_port());
        format!(
            "ClusterName=hypertexture\n\
             SlurmctldHost=localhost(127.0.0.1)\n\
             SlurmctldPort={ctld}\n\
             SlurmdPort={slurmd}\n\
             SlurmUser=root\n\
             SlurmdUser=root\n\
             AuthType=auth/munge\n\
             CredType=cred/munge\n\
             AuthInfo=socket={d}/munge.socket\n\
             CommunicationParameters=NoInAddrAny,NoCtldInAddrAny\n\
             ProctrackType=proctrack/linuxproc\n\
             TaskPlugin=task/none\n\
             MpiDefault=none\n\
             StateSaveLocation={d}/state\n\
             SlurmdSpoolDir={d}/spool\n\
             SlurmctldPidFile={d}/slurmctld.pid\n\
             SlurmdPidFile={d}/slurmd.pid\n\
             SlurmctldLogFile={d}/slurmctld.log\n\
             SlurmdLogFile={d}/slurmd.log\n\
             SchedulerType=sched/backfill\n\
             SchedulerParameters=sched_interval=1\n\
             SelectType=select/cons_tres\n\
             SelectTypeParameters=CR_CPU\n\
             SlurmdParameters=config_overrides\n\
             ReturnToService=2\n\
             KillWait=10\n\
             AccountingStorageType=accounting_storage/none\n\
             JobAcctGatherType=jobacct_gather/none\n\
             JobCompType=jobcomp/none\n\
             NodeName=ht1 NodeAddr=127.0.0.1 CPUs=4 State=UNKNOWN\n\
             PartitionName=ht Nodes=ht1 Default=YES MaxTime=10 State=UP\n"
        )
    }

    /// Starts a daemon in the foreground, a child of this process, its
    /// output in `NAME.out`.
    fn daemon(&mut self, name: &'static str, args: &[&str]) {
        let out = std::fs::File::create(self.dir.join(format!("{name}.out"))).unwrap();
        let child = Command::new(sbin(name))
            .args(args)
            .env("SLURM_CONF", &self.conf)
            .stdin(Stdio::null())
            .stdout(out.try_clone().unwrap())
            .stderr(out)
            .spawn()
            .unwrap_or_else(|e| panic!("{name} does not start: {e}"));
        self.daemons.push((name, child));
    }

    /// Fails the test, with its output, when a daemon has died.
    fn daemons_alive(&mut self) {
        for (name, child) in &mut self.daemons {
            if let Some(status) = child.try_wait().unwrap() {
                let out = std::fs::read_to_string(self.dir.join(format!("{name}.out")))
                    .unwrap_or_default();
                panic!("{name} exited ({status}):\n{out}");
            }
        }
    }

    /// A Slurm client command for this cluster.
    fn command(&self, program: &str) -> Command {
        let mut cmd = Command::new(program);
        cmd.env("SLURM_CONF", &self.conf).env_remove("SLURM_JOB_ID");
        cmd
    }

    /// Submits `deploy/slurm/workers-array.sbatch` as the array `tasks`
    /// against `url`, each task one CPU; returns the job's id.
    fn submit_workers(&self, url: &str, tasks: &str) -> String {
        let script = root().join("deploy/slurm/workers-array.sbatch");
        let log = self.dir.join("worker-%A_%a.log");
        let o = output_within(
            self.command("sbatch")
                .arg("--parsable")
                .arg(format!("--array={tasks}"))
                .arg(format!("--output={}", log.display()))
                .arg("--time=5")
                .arg(&script)
                .arg(url)
                .env("HYPERTEXTURE_WORKER", worker_bin())
                .env("HYPERTEXTURE_IDLE_EXIT", IDLE_EXIT.to_string())
                .env_remove("HYPERTEXTURE_TOKEN")
                .env_remove("NO_COLOR")
                .env_remove("RUST_LOG"),
            30,
        );
        assert!(
            o.status.success(),
            "sbatch: {}",
            String::from_utf8_lossy(&o.stderr)
        );
        let id = String::from_utf8_lossy(&o.stdout).trim().to_string();
        id.split(';').next().unwrap().to_string()
    }

    /// The job's tasks still in the queue (pending, running, completing).
    fn queued(&self, job: &str) -> String {
        let o = output_within(
            self.command("squeue")
                .args(["-h", "-r", "-j", job, "-o", "%i %T"]),
            30,
        );
        String::from_utf8_lossy(&o.stdout).into_owned()
    }

    /// Waits (at most `secs`) until none of the job's tasks is queued.
    fn wait_gone(&self, job: &str, secs: u64) {
        let deadline = Instant::now() + Duration::from_secs(secs);
        loop {
            let left = self.queued(job);
            if left.trim().is_empty() {
                return;
            }
            assert!(
                Instant::now() < deadline,
                "tasks of job {job} still queued after {secs} s:\n{left}"
            );
            std::thread::sleep(Duration::from_millis(200));
        }
    }

    /// The logs of the job's `n` array tasks.
    fn task_logs(&self, job: &str, n: usize) -> Vec<TaskLog> {
        (0..n)
            .map(|task| {
                let name = format!("worker-{job}_{task}.log");
                let text = std::fs::read_to_string(self.dir.join(&name))
                    .unwrap_or_else(|e| panic!("{name}: {e}"));
                TaskLog { name, text }
            })
            .collect()
    }
}

impl Drop for Cluster {
    /// Cancels the jobs left (a test that failed midway) and waits for them
    /// (at most 20 s), then stops every daemon by its pid, the last started
    /// first: SIGTERM, then SIGKILL after 15 s.
    fn drop(&mut self) {
        let _ = self
            .command("scancel")
            .args(["--partition", "ht"])
            .stdin(Stdio::null())
            .output();
        let deadline = Instant::now() + Duration::from_secs(20);
        while Instant::now() < deadline {
            let left = self
                .command("squeue")
                .arg("-h")
                .stdin(Stdio::null())
                .output();
            match left {
                Ok(o) if !o.stdout.is_empty() => std::thread::sleep(Duration::from_millis(200)),
                _ => break,
            }
        }
        for (name, child) in self.daemons.iter_mut().rev() {
            let pid = libc::pid_t::try_from(child.id()).expect("a pid");
            // SAFETY: a signal to our own child, which has not been reaped.
            unsafe { libc::kill(pid, libc::SIGTERM) };
            let deadline = Instant::now() + Duration::from_secs(15);
            while child.try_wait().ok().flatten().is_none() {
                if Instant::now() > deadline {
                    eprintln!("{name} (pid {pid}) ignored SIGTERM: killed");
                    let _ = child.kill();
                    let _ = child.wait();
                    break;
                }
                std::thread::sleep(Duration::from_millis(50));
            }
        }
    }
}

/// A daemon's binary: on PATH, or in /usr/sbin where Debian puts it.
fn sbin(name: &str) -> PathBuf {
    std::env::var_os("PATH")
        .into_iter()
        .flat_map(|p| std::env::split_paths(&p).collect::<Vec<_>>())
        .chain([PathBuf::from("/usr/sbin"), PathBuf::from("/sbin")])
        .map(|d| d.join(name))
        .find(|p| p.exists())
        .unwrap_or_else(|| panic!("{name} is missing: run scripts/test-deps/slurm.sh"))
}
