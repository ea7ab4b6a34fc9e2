//! TLS as a user sets it up: `coordinator cert` makes the files, `serve`
//! uses them and a worker trusting the CA renders; a CA certificate given as
//! the server's is refused at start with how to make a server certificate;
//! the local workers' CA file lives in a private directory that goes with
//! the coordinator, on success and on failure.

use std::os::unix::fs::PermissionsExt as _;
use std::path::{Path, PathBuf};
use std::process::Command;

use crate::support::*;

/// The local workers' CA directories in the temporary directory `tmp`.
fn ca_dirs(tmp: &Path) -> Vec<PathBuf> {
    std::fs::read_dir(tmp)
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| {
            p.file_name()
                .and_then(|n| n.to_str())
                .is_some_and(|n| n.starts_with("hypertexture-ca"))
        })
        .collect()
}

/// A scratch directory for `test`, and an empty temporary directory in it
/// for the coordinator (its TMPDIR).
fn scratch_with_tmp(test: &str) -> (PathBuf, PathBuf) {
    let dir = scratch(test);
    let tmp = dir.join("tmp");
    std::fs::create_dir(&tmp).unwrap();
    (dir, tmp)
}

/// A self-signed certificate for `name` (a CA's when `ca`) and its key,
/// written into `dir`: (certificate, key).
fn self_signed(dir: &Path, name: &str, ca: bool) -> (PathBuf, PathBuf) {
    let key = rcgen::KeyPair::generate().unwrap();
    let mut params = rcgen::CertificateParams::new(vec![name.to_string()]).unwrap();
    if ca {
        params.is_ca = rcgen::IsCa::Ca(rcgen::BasicConstraints::Unconstrained);
    }
    let cert = params.self_signed(&key).unwrap();
    let (cert_path, key_path) = (dir.join("cert.pem"), dir.join("key.pem"));
    std::fs::write(&cert_path, cert.pem()).unwrap();
    std::fs::write(&key_path, key.serialize_pem()).unwrap();
    (cert_path, key_path)
}

/// `coordinator cert --out DIR --name …`: the files it wrote.
fn make_cert(dir: &Path) -> PathBuf {
    let tls = dir.join("tls");
    let o = coordinator(&[
        "cert",
        "--out",
        tls.to_str().unwrap(),
        "--name",
        "render.lan",
    ]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let listed = String::from_utf8_lossy(&o.stdout);
    for file in ["ca.pem", "ca.key", "server.pem", "server.key"] {
        assert!(listed.contains(file), "{listed}");
    }
    tls
}

/// The coordinator binary in `dir` (its working directory, where outputs
/// go), with `tmp` as its temporary directory.
fn coordinator_in(dir: &Path, tmp: &Path, args: &[&str]) -> Running {
    worker_bin();
    Running::spawn(
        Command::new(env!("CARGO_BIN_EXE_coordinator"))
            .args(args)
            .env("TMPDIR", tmp)
            .current_dir(dir),
    )
}

/// A service on the certificates `coordinator cert` makes: its local worker
/// and a worker trusting ca.pem join, a client trusting ca.pem submits, the
/// image is exact. The local worker's CA is in a private directory while
/// the service runs, and gone after it stops.
#[test]
fn a_farm_on_certificates_from_coordinator_cert_renders() {
    let (dir, tmp) = scratch_with_tmp("tls-cert");
    let tls = make_cert(&dir);
    let (server_pem, server_key, ca) = (
        tls.join("server.pem"),
        tls.join("server.key"),
        tls.join("ca.pem"),
    );
    let expected = dir.join("expected.png");
    let scene = scene("noisy_sphere");
    let o = coordinator(&[
        "--scene",
        scene.to_str().unwrap(),
        "--out",
        expected.to_str().unwrap(),
        "--width",
        "32",
        "--height",
        "32",
        "--in-process",
        "--quiet",
    ]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));

    let mut s = coordinator_in(
        &dir,
        &tmp,
        &[
            "serve",
            "--data",
            dir.join("data").to_str().unwrap(),
            "--listen",
            "127.0.0.1:0",
            "--local-workers",
            "1",
            "--threads",
            "1",
            "--tls-cert",
            server_pem.to_str().unwrap(),
            "--tls-key",
            server_key.to_str().unwrap(),
        ],
    );
    let port = s.port();
    s.wait_for("serving on https://", 30);
    if !s.log.iter().any(|l| l.contains("joined")) {
        s.wait_for("joined", 30);
    }
    let cas = ca_dirs(&tmp);
    assert_eq!(cas.len(), 1, "{cas:?}");
    let mode = std::fs::metadata(&cas[0]).unwrap().permissions().mode();
    assert_eq!(mode & 0o777, 0o700, "{}", cas[0].display());
    let files: Vec<_> = std::fs::read_dir(&cas[0]).unwrap().collect();
    assert_eq!(files.len(), 1);
    let file = files[0].as_ref().unwrap().path();
    assert_eq!(
        std::fs::read(&file).unwrap(),
        std::fs::read(&server_pem).unwrap()
    );

    let url = format!("https://localhost:{port}");
    let mut worker = Running::worker(&[
        "--coordinator",
        &url,
        "--ca",
        ca.to_str().unwrap(),
        "--threads",
        "1",
        "--name",
        "lan",
    ]);
    worker.wait_for("registered with", 30);
    let out = dir.join("farm.png");
    let o = coordinator(&[
        "submit",
        "--server",
        &url,
        "--ca",
        ca.to_str().unwrap(),
        scene.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
        "--width",
        "32",
        "--height",
        "32",
    ]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let id = String::from_utf8_lossy(&o.stdout).trim().to_string();
    let o = coordinator(&["wait", "--server", &url, "--ca", ca.to_str().unwrap(), &id]);
    assert!(
        o.status.success(),
        "{}{}",
        String::from_utf8_lossy(&o.stdout),
        String::from_utf8_lossy(&o.stderr)
    );
    assert!(
        std::fs::read(&out).unwrap() == std::fs::read(&expected).unwrap(),
        "the farm's image differs from the in-process one"
    );
    drop(worker);
    s.signal(15);
    let (status, log) = s.finish(60);
    assert!(status.success(), "{}", log.join("\n"));
    assert_eq!(ca_dirs(&tmp), Vec::<PathBuf>::new(), "left behind");
    std::fs::remove_dir_all(&dir).unwrap();
}

/// A CA certificate (CA:TRUE, as `openssl req -x509` makes) given as the
/// server's stops `serve` and a one-shot render at once, saying how to make
/// a server certificate; nothing waits for workers that could never join.
#[test]
fn a_ca_certificate_as_the_servers_is_refused_with_how_to_make_one() {
    let (dir, tmp) = scratch_with_tmp("tls-ca-as-server");
    let (cert_path, key_path) = self_signed(&dir, "localhost", true);
    let data = dir.join("data");
    let out = dir.join("x.png");
    let scene = scene("noisy_sphere");
    for from_cert in [false, true] {
        // The openssl-like one, then the CA `coordinator cert` makes.
        let (cert, key) = if from_cert {
            let tls = make_cert(&dir);
            (tls.join("ca.pem"), tls.join("ca.key"))
        } else {
            (cert_path.clone(), key_path.clone())
        };
        let (cert, key) = (cert.to_str().unwrap(), key.to_str().unwrap());
        for args in [
            vec![
                "serve",
                "--data",
                data.to_str().unwrap(),
                "--listen",
                "127.0.0.1:0",
                "--local-workers",
                "1",
                "--tls-cert",
                cert,
                "--tls-key",
                key,
            ],
            vec![
                "--scene",
                scene.to_str().unwrap(),
                "--out",
                out.to_str().unwrap(),
                "--width",
                "16",
                "--height",
                "16",
                "--local-workers",
                "1",
                "--tls-cert",
                cert,
                "--tls-key",
                key,
            ],
        ] {
            let (status, log) = coordinator_in(&dir, &tmp, &args).finish(20);
            let text = log.join("\n");
            assert!(!status.success(), "{args:?}: {text}");
            for needed in [
                cert,
                "CA certificate",
                "CA:TRUE",
                "coordinator cert --out DIR",
                "--ca DIR/ca.pem",
            ] {
                assert!(text.contains(needed), "{args:?}: no {needed:?} in\n{text}");
            }
            assert!(!text.contains("farm listening"), "{args:?}: {text}");
        }
    }
    assert!(ca_dirs(&tmp).is_empty());
    std::fs::remove_dir_all(&dir).unwrap();
}

/// A render that fails after its local workers started (they cannot verify
/// a certificate for another name, so none joins) still removes their CA
/// directory.
#[test]
fn the_local_workers_ca_goes_when_the_render_fails() {
    let (dir, tmp) = scratch_with_tmp("tls-ca-cleanup");
    let (cert_path, key_path) = self_signed(&dir, "elsewhere.invalid", false);
    let scene = scene("noisy_sphere");
    let mut c = coordinator_in(
        &dir,
        &tmp,
        &[
            "--scene",
            scene.to_str().unwrap(),
            "--out",
            dir.join("x.png").to_str().unwrap(),
            "--width",
            "16",
            "--height",
            "16",
            "--local-workers",
            "1",
            "--worker-timeout",
            "3",
            "--tls-cert",
            cert_path.to_str().unwrap(),
            "--tls-key",
            key_path.to_str().unwrap(),
        ],
    );
    c.wait_for("started 1 local worker", 30);
    assert_eq!(ca_dirs(&tmp).len(), 1, "the CA is written");
    let (status, log) = c.finish(60);
    assert!(!status.success(), "{}", log.join("\n"));
    assert_eq!(ca_dirs(&tmp), Vec::<PathBuf>::new(), "left behind");
    std::fs::remove_dir_all(&dir).unwrap();
}
