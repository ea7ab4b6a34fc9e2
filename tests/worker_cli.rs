//! The worker binary as a user meets it.

use std::process::Command;

fn worker(args: &[&str]) -> std::process::Output {
    Command::new(env!("CARGO_BIN_EXE_worker"))
        .args(args)
        .env_remove("HYPERTEXTURE_TOKEN")
        .output()
        .expect("the worker binary runs")
}

#[test]
fn bad_addresses_fail_cleanly() {
    for (args, expected) in [
        (
            vec!["--coordinator", "not a url"],
            "invalid coordinator address",
        ),
        (
            vec!["--coordinator", "ftp://host:1"],
            "expected http://HOST:PORT",
        ),
        (vec!["--coordinator", "https://localhost:1"], "needs --ca"),
        (
            vec![
                "--coordinator",
                "http://localhost:1",
                "--ca",
                "/no/such/ca.pem",
            ],
            "/no/such/ca.pem",
        ),
        (vec!["--threads", "2"], "--coordinator"),
    ] {
        let out = worker(&args);
        assert!(!out.status.success(), "{args:?}");
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(err.contains(expected), "{args:?}: {err}");
        assert!(!err.contains("panicked"), "{args:?}: {err}");
    }
}
