//! The deployment files agree with the binaries: every YAML file parses, image
//! names are one, ports line up, and every command line is accepted by the real
//! argument parsers of the coordinator and the worker.

mod support;

use clap::Parser;
use yaml_rust2::{Yaml, YamlLoader};

const IMAGE: &str = "hypertexture:latest";

fn load(path: &str) -> Vec<Yaml> {
    let text = std::fs::read_to_string(support::root().join(path))
        .unwrap_or_else(|e| panic!("{path}: {e}"));
    YamlLoader::load_from_str(&text).unwrap_or_else(|e| panic!("{path}: {e}"))
}

fn strings(y: &Yaml) -> Vec<String> {
    y.as_vec()
        .map(|v| {
            v.iter()
                .map(|s| match s {
                    Yaml::String(s) => s.clone(),
                    Yaml::Integer(i) => i.to_string(),
                    other => panic!("not a string: {other:?}"),
                })
                .collect()
        })
        .unwrap_or_default()
}

/// Checks a command line with the binary's own parser; returns the value of `flag`.
fn check_command(argv: &[String], flag: &str) -> String {
    match argv[0].as_str() {
        "coordinator" => {
            coordinator::cli::Cli::try_parse_from(argv).unwrap_or_else(|e| panic!("{argv:?}: {e}"));
        }
        "worker" => {
            worker::cli::Cli::try_parse_from(argv).unwrap_or_else(|e| panic!("{argv:?}: {e}"));
        }
        other => panic!("unknown binary {other}"),
    }
    if argv.iter().any(|a| a == "--scene") {
        let scene = value(argv, "--scene");
        let local = scene
            .strip_prefix("/scenes/")
            .expect("scenes live in /scenes in the image");
        assert!(
            support::root().join("scenes").join(local).exists(),
            "{scene} is not in scenes/"
        );
    }
    value(argv, flag)
}

fn value(argv: &[String], flag: &str) -> String {
    let i = argv
        .iter()
        .position(|a| a == flag)
        .unwrap_or_else(|| panic!("{flag} missing in {argv:?}"));
    argv[i + 1].clone()
}

fn port_of(addr: &str) -> i64 {
    addr.rsplit(':')
        .next()
        .unwrap()
        .trim_end_matches('/')
        .parse()
        .unwrap()
}

#[test]
fn compose_matches_the_binaries() {
    let docs = load("deploy/compose.yaml");
    let services = &docs[0]["services"];
    let coordinator = &services["coordinator"];
    let worker = &services["worker"];
    assert_eq!(coordinator["image"].as_str(), Some(IMAGE));
    assert_eq!(worker["image"].as_str(), Some(IMAGE));
    let listen = check_command(&strings(&coordinator["command"]), "--listen");
    let url = check_command(&strings(&worker["command"]), "--coordinator");
    assert_eq!(url, format!("http://coordinator:{}", port_of(&listen)));
    let published = strings(&coordinator["ports"]);
    assert!(
        published
            .iter()
            .any(|p| p.ends_with(&format!(":{}", port_of(&listen)))),
        "{published:?}"
    );
    for service in [coordinator, worker] {
        assert!(
            service["environment"]["HYPERTEXTURE_TOKEN"]
                .as_str()
                .is_some(),
            "the token is passed"
        );
    }
}

#[test]
fn kubernetes_manifests_match_the_binaries() {
    let mut docs = load("deploy/k8s/coordinator.yaml");
    docs.extend(load("deploy/k8s/workers.yaml"));
    let secret = &load("deploy/k8s/secret.yaml")[0];
    let secret_name = secret["metadata"]["name"].as_str().unwrap();
    assert!(secret["stringData"]["token"].as_str().is_some());

    let service = docs
        .iter()
        .find(|d| d["kind"].as_str() == Some("Service"))
        .expect("a Service");
    let service_name = service["metadata"]["name"].as_str().unwrap();
    let service_port = service["spec"]["ports"][0]["port"].as_i64().unwrap();
    let target_port = service["spec"]["ports"][0]["targetPort"].as_i64().unwrap();

    let mut seen = Vec::new();
    for d in docs
        .iter()
        .filter(|d| d["kind"].as_str() == Some("Deployment"))
    {
        let pod = &d["spec"]["template"];
        assert_eq!(
            d["spec"]["selector"]["matchLabels"]["app"], pod["metadata"]["labels"]["app"],
            "selector matches the pod labels"
        );
        for c in pod["spec"]["containers"].as_vec().unwrap() {
            assert_eq!(c["image"].as_str(), Some(IMAGE));
            let argv: Vec<String> = strings(&c["command"])
                .into_iter()
                .chain(strings(&c["args"]))
                .collect();
            let env = &c["env"][0];
            assert_eq!(env["name"].as_str(), Some("HYPERTEXTURE_TOKEN"));
            assert_eq!(
                env["valueFrom"]["secretKeyRef"]["name"].as_str(),
                Some(secret_name)
            );
            match argv[0].as_str() {
                "coordinator" => {
                    let listen = port_of(&check_command(&argv, "--listen"));
                    assert_eq!(c["ports"][0]["containerPort"].as_i64(), Some(listen));
                    assert_eq!(target_port, listen);
                    assert_eq!(
                        service["spec"]["selector"]["app"],
                        pod["metadata"]["labels"]["app"]
                    );
                }
                "worker" => {
                    let url = check_command(&argv, "--coordinator");
                    assert_eq!(url, format!("http://{service_name}:{service_port}"));
                }
                other => panic!("unexpected container command {other}"),
            }
            seen.push(argv[0].clone());
        }
    }
    seen.sort();
    assert_eq!(seen, ["coordinator", "worker"]);
}

#[test]
fn systemd_unit_and_dockerfile_match_the_binaries() {
    let unit =
        std::fs::read_to_string(support::root().join("deploy/systemd/hypertexture-worker.service"))
            .unwrap();
    let exec = unit
        .lines()
        .find_map(|l| l.strip_prefix("ExecStart="))
        .expect("ExecStart");
    let mut argv: Vec<String> = exec.split_whitespace().map(str::to_string).collect();
    assert_eq!(argv[0], "/usr/local/bin/worker");
    argv[0] = "worker".into();
    assert_eq!(port_of(&check_command(&argv, "--coordinator")), 50051);
    assert!(unit.contains("KillSignal=SIGTERM"));

    let dockerfile = std::fs::read_to_string(support::root().join("deploy/Dockerfile")).unwrap();
    assert!(dockerfile.contains("EXPOSE 50051"));
    assert!(dockerfile.contains("-p coordinator -p worker"));
    assert!(dockerfile.contains(&format!("-t {IMAGE}")));
}
