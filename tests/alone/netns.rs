//! The farm across a real network: the coordinator and two workers each in a
//! network namespace of their own, joined by veth pairs to a bridge in a
//! fourth namespace, with private 10.x addresses that exist only inside those
//! namespaces. The host's own network is never touched, and the namespaces
//! (and with them the links) are deleted when the test ends, passed or failed.
//!
//! They need root (`ip netns add`). CI and this machine run as root; elsewhere
//! each test prints why it skips.

use std::path::Path;
use std::process::Command;
use std::time::{Duration, Instant};

use crate::support::*;

/// Runs `ip` with `args`; panics with its stderr when it fails.
fn ip(args: &[&str]) {
    let out = Command::new("ip").args(args).output().expect("ip runs");
    assert!(
        out.status.success(),
        "ip {}: {}",
        args.join(" "),
        String::from_utf8_lossy(&out.stderr)
    );
}

/// Why this machine cannot run the tests, if it cannot.
fn cannot_run() -> Option<String> {
    // SAFETY: geteuid has no preconditions.
    if unsafe { libc::geteuid() } != 0 {
        return Some("not root: `ip netns add` needs CAP_SYS_ADMIN".into());
    }
    let probe = format!("htprobe{}", std::process::id());
    match Command::new("ip").args(["netns", "add", &probe]).output() {
        Ok(o) if o.status.success() => {
            let _ = Command::new("ip").args(["netns", "del", &probe]).status();
            None
        }
        Ok(o) => Some(format!(
            "`ip netns add` fails here: {}",
            String::from_utf8_lossy(&o.stderr).trim()
        )),
        Err(e) => Some(format!("no `ip` command: {e}")),
    }
}

/// The namespaces of one test: a bridge and three hosts. Dropping it deletes
/// them all (their veth ends go with them).
struct Net {
    bridge: String,
    /// Per host: namespace, the bridge-side link's name, its address.
    hosts: Vec<(String, String, String)>,
}

impl Net {
    /// `hosts` namespaces on a bridge; names unique to this process and test.
    fn new(test: &str, hosts: usize) -> Net {
        use std::hash::{BuildHasher, Hasher};
        let mut h = std::collections::hash_map::RandomState::new().build_hasher();
        h.write(test.as_bytes());
        h.write_u32(std::process::id());
        let tag = h.finish();
        // Interface names are at most 15 bytes: "ht" + 6 hex + role + index.
        let id = format!("{:06x}", tag & 0xff_ffff);
        let subnet = 16 + (tag >> 24) % 200;
        let mut net = Net {
            bridge: format!("ht{id}br"),
            hosts: Vec::new(),
        };
        ip(&["netns", "add", &net.bridge]);
        ip(&["-n", &net.bridge, "link", "add", "br0", "type", "bridge"]);
        ip(&["-n", &net.bridge, "link", "set", "br0", "up"]);
        for i in 0..hosts {
            let ns = format!("ht{id}h{i}");
            let (inner, outer) = (format!("ht{id}i{i}"), format!("ht{id}o{i}"));
            let addr = format!("10.{}.{}.{}", (tag >> 40) % 200 + 20, subnet, i + 1);
            ip(&["netns", "add", &ns]);
            net.hosts.push((ns.clone(), outer.clone(), addr.clone()));
            ip(&[
                "-n",
                &ns,
                "link",
                "add",
                &inner,
                "type",
                "veth",
                "peer",
                "name",
                &outer,
                "netns",
                &net.bridge,
            ]);
            ip(&["-n", &net.bridge, "link", "set", &outer, "master", "br0"]);
            ip(&["-n", &net.bridge, "link", "set", &outer, "up"]);
            ip(&[
                "-n",
                &ns,
                "addr",
                "add",
                &format!("{addr}/24"),
                "dev",
                &inner,
            ]);
            ip(&["-n", &ns, "link", "set", &inner, "up"]);
            ip(&["-n", &ns, "link", "set", "lo", "up"]);
        }
        net
    }

    /// Host `i`'s namespace and address.
    fn host(&self, i: usize) -> (&str, &str) {
        (&self.hosts[i].0, &self.hosts[i].2)
    }

    /// Takes host `i`'s link to the bridge down or up.
    fn link(&self, i: usize, up: bool) {
        ip(&[
            "-n",
            &self.bridge,
            "link",
            "set",
            &self.hosts[i].1,
            if up { "up" } else { "down" },
        ]);
    }
}

impl Drop for Net {
    fn drop(&mut self) {
        for (ns, _, _) in &self.hosts {
            let _ = Command::new("ip").args(["netns", "del", ns]).status();
        }
        let _ = Command::new("ip")
            .args(["netns", "del", &self.bridge])
            .status();
    }
}

/// `program args` inside namespace `ns`.
fn in_ns(ns: &str, program: &Path, args: &[&str]) -> Command {
    let mut cmd = Command::new("ip");
    cmd.args(["netns", "exec", ns]).arg(program).args(args);
    cmd
}

/// A TLS farm with a token across namespaces: a worker with a wrong token
/// is refused, one worker's link is cut mid-frame and restored, the other
/// is stopped (SIGSTOP) past its lease and continued, and the image is
/// byte-identical to the in-process one.
#[test]
fn a_tls_farm_across_namespaces_survives_a_cut_link_and_a_stopped_worker() {
    let _alone = alone();
    if let Some(why) = cannot_run() {
        eprintln!("skipped: {why}");
        return;
    }
    let started = Instant::now();
    let dir = scratch("netns-farm");
    // Long enough (4 samples a pixel) that the cut falls mid-frame.
    let size = "256";
    let (out, expected) = (dir.join("farm.png"), dir.join("in-process.png"));
    in_process(
        "noisy_sphere",
        &expected,
        &["--width", size, "--height", size, "--spp", "4"],
    );
    let net = Net::new("farm", 3);
    let (coord_ns, coord_addr) = net.host(0);

    let key = rcgen::KeyPair::generate().unwrap();
    let cert = rcgen::CertificateParams::new(vec![coord_addr.to_string()])
        .unwrap()
        .self_signed(&key)
        .unwrap();
    let (cert_path, key_path) = (dir.join("cert.pem"), dir.join("key.pem"));
    std::fs::write(&cert_path, cert.pem()).unwrap();
    std::fs::write(&key_path, key.serialize_pem()).unwrap();
    let token = "netns-s3cret";
    let listen = format!("{coord_addr}:47000");
    let url = format!("https://{coord_addr}:47000");

    worker_bin();
    let mut coord = Running::spawn(&mut in_ns(
        coord_ns,
        Path::new(env!("CARGO_BIN_EXE_coordinator")),
        &[
            "--scene",
            scene("noisy_sphere").to_str().unwrap(),
            "--out",
            out.to_str().unwrap(),
            "--width",
            size,
            "--height",
            size,
            "--spp",
            "4",
            "--listen",
            &listen,
            "--token",
            token,
            "--tls-cert",
            cert_path.to_str().unwrap(),
            "--tls-key",
            key_path.to_str().unwrap(),
            "--local-workers",
            "0",
            "--lease-timeout",
            "2",
            "--worker-timeout",
            "60",
        ],
    ));
    coord.wait_for("farm listening on", 30);
    let worker = |ns: &str, name: &str, token: &str| {
        Running::spawn(&mut in_ns(
            ns,
            &worker_bin(),
            &[
                "--coordinator",
                &url,
                "--ca",
                cert_path.to_str().unwrap(),
                "--token",
                token,
                "--name",
                name,
                "--threads",
                "1",
                "--exit-when-done",
            ],
        ))
    };
    let (w1_ns, _) = net.host(1);
    let (w2_ns, _) = net.host(2);
    let mut intruder = worker(w2_ns, "intruder", "wrong-token");
    let line = intruder.wait_for("refused", 30);
    assert!(line.contains("token"), "{line}");
    drop(intruder);

    let mut w1 = worker(w1_ns, "cut", token);
    let mut w2 = worker(w2_ns, "stopped", token);
    w1.wait_for("registered with", 30);
    w2.wait_for("registered with", 30);

    // Mid-frame: cut the first worker's link for 3 s (past its lease), and
    // stop the second worker for 3 s (past its lease) meanwhile.
    net.link(1, false);
    w2.signal(libc::SIGSTOP);
    std::thread::sleep(Duration::from_secs(3));
    net.link(1, true);
    w2.signal(libc::SIGCONT);

    let (status, log) = coord.finish(120);
    let text = log.join("\n");
    assert!(status.success(), "{text}");
    assert!(text.contains("stopped answering"), "{text}");
    assert!(
        !text.contains("worker intruder joined"),
        "a wrong token joined:\n{text}"
    );
    assert_eq!(
        std::fs::read(&out).unwrap(),
        std::fs::read(&expected).unwrap(),
        "the farm's image across namespaces differs from the in-process one:\n{text}"
    );
    let _ = w1.finish(30);
    let _ = w2.finish(30);
    assert!(started.elapsed() < Duration::from_secs(300));
    drop(net);
    std::fs::remove_dir_all(&dir).unwrap();
}
