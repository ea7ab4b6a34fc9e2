//! The deployment files agree with the binaries: every YAML file parses, image
//! names are one, ports and names line up, and every command line (in the
//! manifests, the compose file, the systemd units and the README's examples) is
//! accepted by the real argument parsers of the coordinator and the worker.

use clap::Parser;
use coordinator::cli::{Command, ServeArgs};
use yaml_rust2::{Yaml, YamlLoader};

const IMAGE: &str = "hypertexture:latest";
/// The port of `coordinator serve` everywhere in deploy/.
const PORT: u16 = 47000;
/// The coordinator's gauge of units waiting over every job (what KEDA scales on).
const QUEUE_METRIC: &str = "hypertexture_farm_units_queued";

fn read(path: &str) -> String {
    std::fs::read_to_string(crate::support::root().join(path))
        .unwrap_or_else(|e| panic!("{path}: {e}"))
}

fn load(path: &str) -> Vec<Yaml> {
    YamlLoader::load_from_str(&read(path)).unwrap_or_else(|e| panic!("{path}: {e}"))
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

/// A command line accepted by one of the binaries' own parsers.
#[derive(Debug)]
enum Parsed {
    Coordinator(Box<coordinator::cli::Cli>),
    Worker(Box<worker::cli::Cli>),
}

/// Parses `argv` with the binary's parser (argv[0] names the binary; a path is
/// allowed) and checks that the scene files it names exist in the repository
/// (`/scenes/...` is the image's copy of `scenes/`).
fn parse(argv: &[String]) -> Parsed {
    let binary = argv[0].rsplit('/').next().unwrap();
    let parsed = match binary {
        "coordinator" => Parsed::Coordinator(Box::new(
            coordinator::cli::Cli::try_parse_from(argv).unwrap_or_else(|e| panic!("{argv:?}: {e}")),
        )),
        "worker" => Parsed::Worker(Box::new(
            worker::cli::Cli::try_parse_from(argv).unwrap_or_else(|e| panic!("{argv:?}: {e}")),
        )),
        other => panic!("unknown binary {other}"),
    };
    if let Parsed::Coordinator(cli) = &parsed {
        // A one-shot render names its scene with --scene; `submit` takes it as
        // an argument; `serve` has none (scenes arrive with the jobs).
        let scene = match &cli.command {
            None => cli.scene.clone(),
            Some(Command::Submit(submit)) => Some(submit.scene.clone()),
            Some(Command::Eval(eval)) => eval.scene.clone(),
            Some(_) => None,
        };
        if let Some(scene) = scene {
            let local = match scene.strip_prefix("/scenes") {
                Ok(rest) => std::path::Path::new("scenes").join(rest),
                Err(_) => scene.clone(),
            };
            assert!(
                crate::support::root().join(&local).exists(),
                "{}: not in scenes/ ({argv:?})",
                scene.display()
            );
        }
    }
    parsed
}

/// The arguments of a `coordinator serve` command line.
fn serve(argv: &[String]) -> ServeArgs {
    match parse(argv) {
        Parsed::Coordinator(cli) => match cli.command {
            Some(Command::Serve(args)) => args,
            other => panic!("expected `coordinator serve`, found {other:?}"),
        },
        other => panic!("expected `coordinator serve`, found {other:?}"),
    }
}

/// A long-lived worker's command line: stays between jobs. Returns its --coordinator.
fn plain_worker(argv: &[String]) -> String {
    match parse(argv) {
        Parsed::Worker(cli) => {
            assert!(
                !cli.exit_when_done,
                "a deployed worker stays between jobs: {argv:?}"
            );
            cli.coordinator
        }
        other => panic!("expected a worker, found {other:?}"),
    }
}

/// A service listening beyond loopback on the farm's port.
fn check_listen(args: &ServeArgs) {
    assert!(
        args.listen.listen.ip().is_unspecified(),
        "{}: workers elsewhere must reach it",
        args.listen.listen
    );
    assert_eq!(args.listen.listen.port(), PORT);
}

fn port_of(url: &str) -> u16 {
    url.trim_end_matches('/')
        .rsplit(':')
        .next()
        .unwrap()
        .parse()
        .unwrap()
}

/// Seconds of a compose duration such as "45s".
fn seconds(duration: &Yaml) -> f64 {
    let text = duration.as_str().expect("a duration such as 45s");
    text.strip_suffix('s')
        .and_then(|s| s.parse().ok())
        .unwrap_or_else(|| panic!("{text}: expected seconds, e.g. 45s"))
}

#[test]
fn compose_matches_the_binaries() {
    let docs = load("deploy/compose.yaml");
    let compose = &docs[0];
    let services = &compose["services"];
    let coordinator = &services["coordinator"];
    let worker = &services["worker"];
    assert_eq!(coordinator["image"].as_str(), Some(IMAGE));
    assert_eq!(worker["image"].as_str(), Some(IMAGE));

    let args = serve(&strings(&coordinator["command"]));
    check_listen(&args);
    let url = plain_worker(&strings(&worker["command"]));
    assert_eq!(url, format!("http://coordinator:{PORT}"));
    assert!(worker["deploy"]["replicas"].as_i64().unwrap() >= 1);

    // Published on the host's loopback only (the token is required anyway).
    let published = strings(&coordinator["ports"]);
    assert_eq!(published, [format!("127.0.0.1:{PORT}:{PORT}")]);

    // --data is a named volume, so the queue outlives the container.
    let data = args.data.to_str().unwrap();
    let volumes = strings(&coordinator["volumes"]);
    let named = volumes
        .iter()
        .find_map(|v| v.strip_suffix(&format!(":{data}")))
        .unwrap_or_else(|| panic!("no volume at {data}: {volumes:?}"));
    assert!(
        !compose["volumes"][named].is_badvalue(),
        "{named} is declared as a named volume"
    );

    // Outputs go only to the mounted output directory.
    assert_eq!(args.output_root, [std::path::PathBuf::from("/out")]);
    assert!(volumes.iter().any(|v| v.ends_with(":/out")), "{volumes:?}");

    // Docker's SIGKILL comes after the drain.
    assert!(seconds(&coordinator["stop_grace_period"]) > args.drain_timeout);

    for service in [coordinator, worker] {
        assert!(
            service["environment"]["HYPERTEXTURE_TOKEN"]
                .as_str()
                .is_some_and(|t| t.contains(":?")),
            "the token is required and passed"
        );
    }
}

/// The single document of `docs` of this kind.
fn one<'a>(docs: &'a [Yaml], kind: &str) -> &'a Yaml {
    let mut found = docs.iter().filter(|d| d["kind"].as_str() == Some(kind));
    let doc = found.next().unwrap_or_else(|| panic!("no {kind}"));
    assert!(found.next().is_none(), "more than one {kind}");
    doc
}

/// The pod template's single container, with its image, command line and token checked.
fn container(workload: &Yaml, secret: &str) -> (Yaml, Vec<String>) {
    let pod = &workload["spec"]["template"];
    assert_eq!(
        workload["spec"]["selector"]["matchLabels"]["app"], pod["metadata"]["labels"]["app"],
        "selector matches the pod labels"
    );
    let containers = pod["spec"]["containers"].as_vec().unwrap();
    assert_eq!(containers.len(), 1);
    let c = containers[0].clone();
    assert_eq!(c["image"].as_str(), Some(IMAGE));
    let argv: Vec<String> = strings(&c["command"])
        .into_iter()
        .chain(strings(&c["args"]))
        .collect();
    let env = &c["env"][0];
    assert_eq!(env["name"].as_str(), Some("HYPERTEXTURE_TOKEN"));
    assert_eq!(
        env["valueFrom"]["secretKeyRef"]["name"].as_str(),
        Some(secret)
    );
    (c, argv)
}

#[test]
fn kubernetes_manifests_match_the_binaries() {
    let coordinator_docs = load("deploy/k8s/coordinator.yaml");
    let worker_docs = load("deploy/k8s/workers.yaml");
    let secret = &load("deploy/k8s/secret.yaml")[0];
    let secret_name = secret["metadata"]["name"].as_str().unwrap();
    assert!(secret["stringData"]["token"].as_str().is_some());

    // No Deployment runs the coordinator: the queue's single owner is a StatefulSet.
    for d in coordinator_docs.iter().chain(&worker_docs) {
        let kind = d["kind"].as_str().unwrap();
        assert!(
            ["StatefulSet", "Service", "Deployment"].contains(&kind),
            "{kind}"
        );
    }
    let set = one(&coordinator_docs, "StatefulSet");
    let service = one(&coordinator_docs, "Service");
    let workers = one(&worker_docs, "Deployment");

    // The coordinator: `serve` on the Service's target port, token from the Secret.
    assert_eq!(set["spec"]["replicas"].as_i64(), Some(1));
    let (c, argv) = container(set, secret_name);
    let args = serve(&argv);
    check_listen(&args);
    let port = &c["ports"][0];
    let port_name = port["name"].as_str().unwrap();
    assert_eq!(port["containerPort"].as_i64(), Some(i64::from(PORT)));

    // The queue is on the claim's volume, mounted where --data points.
    let data = args.data.to_str().unwrap();
    let mount = c["volumeMounts"]
        .as_vec()
        .unwrap()
        .iter()
        .find(|m| m["mountPath"].as_str() == Some(data))
        .unwrap_or_else(|| panic!("nothing mounted at --data {data}"));
    assert!(
        set["spec"]["volumeClaimTemplates"]
            .as_vec()
            .unwrap()
            .iter()
            .any(|t| t["metadata"]["name"] == mount["name"]),
        "{data} is a volumeClaimTemplate's volume"
    );
    // Outputs go only to the mounted output volume.
    assert_eq!(args.output_root.len(), 1);
    let out = args.output_root[0].to_str().unwrap();
    assert!(
        c["volumeMounts"]
            .as_vec()
            .unwrap()
            .iter()
            .any(|m| m["mountPath"].as_str() == Some(out)),
        "nothing mounted at --output-root {out}"
    );

    // The kubelet's SIGKILL comes after the drain.
    let grace = set["spec"]["template"]["spec"]["terminationGracePeriodSeconds"]
        .as_i64()
        .expect("terminationGracePeriodSeconds");
    assert!(
        grace as f64 > args.drain_timeout,
        "terminationGracePeriodSeconds {grace} <= --drain-timeout {}",
        args.drain_timeout
    );

    // Probes on the farm's port (TCP: HTTP requests need the bearer token).
    for probe in ["readinessProbe", "livenessProbe"] {
        let target = &c[probe]["tcpSocket"]["port"];
        assert!(
            target.as_str() == Some(port_name) || target.as_i64() == Some(i64::from(PORT)),
            "{probe} checks the farm's port"
        );
    }

    // The Service: ClusterIP in front of the coordinator's pod and port.
    assert_eq!(service["spec"]["type"].as_str(), Some("ClusterIP"));
    let service_name = service["metadata"]["name"].as_str().unwrap();
    assert_eq!(set["spec"]["serviceName"].as_str(), Some(service_name));
    assert_eq!(
        service["spec"]["selector"]["app"],
        set["spec"]["template"]["metadata"]["labels"]["app"]
    );
    let service_port = &service["spec"]["ports"][0];
    let target = &service_port["targetPort"];
    assert!(target.as_str() == Some(port_name) || target.as_i64() == Some(i64::from(PORT)));
    let service_port_number = service_port["port"].as_i64().unwrap();

    // Workers: plain long-lived workers that dial the Service.
    let (_, argv) = container(workers, secret_name);
    let url = plain_worker(&argv);
    assert_eq!(url, format!("http://{service_name}:{service_port_number}"));

    // KEDA scales that Deployment on the coordinator's queue gauge, down to zero.
    let keda = &load("deploy/k8s/keda-scaledobject.yaml")[0];
    assert_eq!(keda["apiVersion"].as_str(), Some("keda.sh/v1alpha1"));
    assert_eq!(keda["kind"].as_str(), Some("ScaledObject"));
    let target = &keda["spec"]["scaleTargetRef"];
    assert_eq!(target["name"], workers["metadata"]["name"]);
    assert!(matches!(target["kind"].as_str(), None | Some("Deployment")));
    assert_eq!(keda["spec"]["minReplicaCount"].as_i64(), Some(0));
    assert!(keda["spec"]["maxReplicaCount"].as_i64().unwrap() >= 1);
    let triggers = keda["spec"]["triggers"].as_vec().unwrap();
    assert_eq!(triggers.len(), 1);
    let trigger = &triggers[0];
    assert_eq!(trigger["type"].as_str(), Some("prometheus"));
    let metadata = &trigger["metadata"];
    assert!(
        metadata["serverAddress"]
            .as_str()
            .unwrap()
            .starts_with("http")
    );
    let query = metadata["query"].as_str().unwrap();
    assert!(query.contains(QUEUE_METRIC), "{query}");
    let number = |key: &str| -> f64 {
        metadata[key]
            .as_str()
            .unwrap_or_else(|| panic!("{key} is a quoted number"))
            .parse()
            .unwrap()
    };
    assert!(number("threshold") > 0.0);
    // Active as soon as one unit waits (the scaler is active above the value).
    assert!(number("activationThreshold") < 1.0);

    // Prometheus scrapes /metrics through the Service with the farm's token.
    let monitor = &load("deploy/k8s/servicemonitor.yaml")[0];
    assert_eq!(monitor["kind"].as_str(), Some("ServiceMonitor"));
    for (label, value) in monitor["spec"]["selector"]["matchLabels"]
        .as_hash()
        .unwrap()
    {
        assert_eq!(
            &service["metadata"]["labels"][label.as_str().unwrap()],
            value,
            "the ServiceMonitor selects the Service"
        );
    }
    let endpoint = &monitor["spec"]["endpoints"][0];
    assert_eq!(endpoint["port"], service_port["name"]);
    assert_eq!(endpoint["path"].as_str(), Some("/metrics"));
    assert_eq!(
        endpoint["authorization"]["credentials"]["name"].as_str(),
        Some(secret_name)
    );
}

/// The `Key=value` settings of a systemd unit (a key may repeat).
fn unit_settings(path: &str) -> Vec<(String, String)> {
    read(path)
        .lines()
        .filter(|l| !l.starts_with('#') && !l.starts_with('['))
        .filter_map(|l| l.split_once('='))
        .map(|(k, v)| (k.trim().to_string(), v.trim().to_string()))
        .collect()
}

fn setting<'a>(unit: &'a [(String, String)], key: &str) -> &'a str {
    unit.iter()
        .find(|(k, _)| k == key)
        .map(|(_, v)| v.as_str())
        .unwrap_or_else(|| panic!("{key}= missing"))
}

fn exec_start(unit: &[(String, String)], binary: &str) -> Vec<String> {
    let argv: Vec<String> = setting(unit, "ExecStart")
        .split_whitespace()
        .map(str::to_string)
        .collect();
    assert_eq!(argv[0], format!("/usr/local/bin/{binary}"));
    argv
}

#[test]
fn systemd_units_match_the_binaries() {
    let coordinator = unit_settings("deploy/systemd/hypertexture-coordinator.service");
    let args = serve(&exec_start(&coordinator, "coordinator"));
    check_listen(&args);
    assert_eq!(
        args.data,
        std::path::Path::new("/var/lib").join(setting(&coordinator, "StateDirectory"))
    );
    assert_eq!(setting(&coordinator, "KillSignal"), "SIGTERM");
    let stop: f64 = setting(&coordinator, "TimeoutStopSec").parse().unwrap();
    assert!(
        stop > args.drain_timeout,
        "TimeoutStopSec outlasts the drain"
    );
    assert_eq!(setting(&coordinator, "Restart"), "on-failure");
    assert!(setting(&coordinator, "EnvironmentFile").starts_with('/'));
    assert!(
        coordinator
            .iter()
            .any(|(k, v)| k == "User" || (k == "DynamicUser" && v == "yes")),
        "not root"
    );
    assert_eq!(setting(&coordinator, "NoNewPrivileges"), "yes");
    assert_eq!(setting(&coordinator, "ProtectSystem"), "strict");
    let writable: Vec<&str> = setting(&coordinator, "ReadWritePaths")
        .split_whitespace()
        .collect();
    assert!(writable.contains(&args.data.to_str().unwrap()));
    // Outputs go only to the writable output directory.
    assert_eq!(args.output_root.len(), 1);
    assert!(writable.contains(&args.output_root[0].to_str().unwrap()));

    let worker = unit_settings("deploy/systemd/hypertexture-worker.service");
    let url = plain_worker(&exec_start(&worker, "worker"));
    assert_eq!(port_of(&url), args.listen.listen.port());
    assert_eq!(setting(&worker, "KillSignal"), "SIGTERM");
    assert!(setting(&worker, "EnvironmentFile").starts_with('/'));
}

#[test]
fn dockerfile_matches_the_binaries() {
    let dockerfile = read("deploy/Dockerfile");
    assert!(dockerfile.contains(&format!("EXPOSE {PORT}")));
    assert!(dockerfile.contains("-p coordinator -p worker"));
    assert!(dockerfile.contains("/release/coordinator /src/target/release/worker /usr/local/bin/"));
    assert!(dockerfile.contains("COPY --from=build /src/scenes /scenes"));
    assert!(dockerfile.contains(&format!("-t {IMAGE}")));
}

/// Splits a shell command line into words: quotes are removed, nothing expands.
fn shell_words(line: &str) -> Vec<String> {
    let mut words = Vec::new();
    let mut word = String::new();
    let mut in_word = false;
    let mut quote = None;
    for ch in line.chars() {
        match (quote, ch) {
            (Some(q), c) if c == q => quote = None,
            (Some(_), c) => word.push(c),
            (None, '\'' | '"') => {
                quote = Some(ch);
                in_word = true;
            }
            (None, c) if c.is_whitespace() => {
                if in_word {
                    words.push(std::mem::take(&mut word));
                    in_word = false;
                }
            }
            (None, c) => {
                word.push(c);
                in_word = true;
            }
        }
    }
    if in_word {
        words.push(word);
    }
    words
}

#[test]
fn readme_commands_match_the_binaries() {
    let readme = read("deploy/README.md");
    let mut checked = 0;
    let mut in_shell = false;
    let mut command = String::new();
    for line in readme.lines() {
        if line.starts_with("```") {
            in_shell = line == "```sh";
            continue;
        }
        if !in_shell || line.trim_start().starts_with('#') {
            continue;
        }
        command.push_str(line.trim_end().trim_end_matches('\\'));
        command.push(' ');
        if line.trim_end().ends_with('\\') {
            continue;
        }
        let mut words = shell_words(&std::mem::take(&mut command));
        // `JOB=$(coordinator submit …)`: the command inside.
        if let Some(inner) = words.first().and_then(|w| w.split_once("=$(")) {
            words[0] = inner.1.to_string();
            if let Some(last) = words.last_mut() {
                *last = last.trim_end_matches(')').to_string();
            }
        }
        // Skip leading VAR=value assignments; $JOB holds a job id.
        let argv: Vec<String> = words
            .into_iter()
            .skip_while(|w| w.contains('=') && !w.starts_with('-'))
            .map(|w| if w == "$JOB" { "1".to_string() } else { w })
            .collect();
        if argv
            .first()
            .is_some_and(|w| w == "coordinator" || w == "worker")
        {
            parse(&argv);
            checked += 1;
        }
    }
    assert!(checked >= 6, "only {checked} commands found in the README");
}

/// `systemd-analyze security --offline=true`'s overall exposure of a unit
/// file (0 is safest, 10 is fully exposed).
fn exposure(path: &str) -> f64 {
    let file = crate::support::root().join(path);
    let out = std::process::Command::new("systemd-analyze")
        .args(["security", "--offline=true"])
        .arg(&file)
        .output()
        .unwrap_or_else(|e| {
            panic!("systemd-analyze: {e} (scripts/test-deps/systemd-analyze.sh installs it)")
        });
    let text = String::from_utf8_lossy(&out.stdout);
    text.lines()
        .find_map(|l| {
            l.split_once("Overall exposure level for ")?
                .1
                .split_once(": ")
        })
        .and_then(|(_, rest)| rest.split_whitespace().next()?.parse().ok())
        .unwrap_or_else(|| {
            panic!(
                "{path}: no exposure level in systemd-analyze's output:\n{text}{}",
                String::from_utf8_lossy(&out.stderr)
            )
        })
}

/// Both units are hardened: systemd scores each at most 2.0 (OK). The
/// worker runs what the network sends on every LAN machine.
#[test]
fn systemd_units_are_hardened() {
    for unit in [
        "deploy/systemd/hypertexture-coordinator.service",
        "deploy/systemd/hypertexture-worker.service",
    ] {
        let score = exposure(unit);
        assert!(score <= 2.0, "{unit}: exposure {score} > 2.0");
        let settings = unit_settings(unit);
        assert_eq!(setting(&settings, "CapabilityBoundingSet"), "", "{unit}");
        assert_eq!(setting(&settings, "NoNewPrivileges"), "yes", "{unit}");
    }
}

/// A compose service's or a Kubernetes container's list, as strings.
fn list(y: &Yaml) -> Vec<String> {
    strings(y)
        .into_iter()
        .map(|s| s.to_ascii_lowercase())
        .collect()
}

/// The image, the compose services and the Kubernetes workloads run as a
/// user other than root, on a read-only root file system, with no
/// capabilities, no privilege gain and the runtime's default seccomp
/// profile.
#[test]
fn containers_run_unprivileged() {
    // The image's last USER is a number other than 0, so runAsNonRoot can
    // check it.
    let dockerfile = read("deploy/Dockerfile");
    let user = dockerfile
        .lines()
        .rev()
        .find_map(|l| l.strip_prefix("USER "))
        .expect("a USER line");
    let uid: u32 = user
        .split(':')
        .next()
        .unwrap()
        .trim()
        .parse()
        .unwrap_or_else(|_| panic!("USER {user}: not a number"));
    assert_ne!(uid, 0, "USER {user}");

    let compose = &load("deploy/compose.yaml")[0];
    for (name, service) in compose["services"].as_hash().unwrap() {
        let name = name.as_str().unwrap();
        let user = service["user"]
            .as_str()
            .unwrap_or_else(|| panic!("{name}: no user"));
        assert!(
            !user.is_empty() && !user.starts_with("0") && !user.starts_with("root"),
            "{name}: user {user}"
        );
        assert_eq!(
            service["read_only"].as_bool(),
            Some(true),
            "{name}: read_only"
        );
        assert_eq!(list(&service["cap_drop"]), ["all"], "{name}: cap_drop");
        assert!(service["cap_add"].is_badvalue(), "{name}: cap_add");
        assert!(service["privileged"].as_bool() != Some(true), "{name}");
        let options = list(&service["security_opt"]);
        assert!(
            options.contains(&"no-new-privileges:true".to_string()),
            "{name}: {options:?}"
        );
        assert!(
            !options.iter().any(|o| o.contains("unconfined")),
            "{name}: {options:?}"
        );
    }

    for (path, kind) in [
        ("deploy/k8s/coordinator.yaml", "StatefulSet"),
        ("deploy/k8s/workers.yaml", "Deployment"),
    ] {
        let docs = load(path);
        let pod = &one(&docs, kind)["spec"]["template"]["spec"];
        let pod_context = &pod["securityContext"];
        assert_eq!(pod_context["runAsNonRoot"].as_bool(), Some(true), "{path}");
        assert!(
            pod_context["runAsUser"].as_i64().is_some_and(|u| u != 0),
            "{path}"
        );
        for c in pod["containers"].as_vec().unwrap() {
            let context = &c["securityContext"];
            let seccomp = if context["seccompProfile"].is_badvalue() {
                &pod_context["seccompProfile"]
            } else {
                &context["seccompProfile"]
            };
            assert_eq!(seccomp["type"].as_str(), Some("RuntimeDefault"), "{path}");
            assert_eq!(context["runAsNonRoot"].as_bool(), Some(true), "{path}");
            assert_eq!(
                context["readOnlyRootFilesystem"].as_bool(),
                Some(true),
                "{path}"
            );
            assert_eq!(
                context["allowPrivilegeEscalation"].as_bool(),
                Some(false),
                "{path}"
            );
            assert!(context["privileged"].as_bool() != Some(true), "{path}");
            assert_eq!(list(&context["capabilities"]["drop"]), ["all"], "{path}");
            assert!(context["capabilities"]["add"].is_badvalue(), "{path}");
        }
    }
}
