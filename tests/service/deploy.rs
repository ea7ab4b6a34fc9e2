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
    pod_container(pod, secret)
}

/// A pod template's single container, with its image, command line and token checked.
fn pod_container(pod: &Yaml, secret: &str) -> (Yaml, Vec<String>) {
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

    // Probes on the farm's port, over HTTP (kubernetes_probes_answer_on_a_running_serve).
    coordinator_probes(&c, port_name);

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
    let (worker, argv) = container(workers, secret_name);
    let url = plain_worker(&argv);
    assert_eq!(url, format!("http://{service_name}:{service_port_number}"));
    threads_match_resources(&worker, &argv);

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
        ("deploy/k8s/keda-scaledjob.yaml", "ScaledJob"),
    ] {
        let docs = load(path);
        let pod = &pod_template(one(&docs, kind))["spec"];
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

/// A workload's pod template: a Deployment's or StatefulSet's, or the Job
/// template of a KEDA ScaledJob.
fn pod_template(workload: &Yaml) -> &Yaml {
    match workload["kind"].as_str() {
        Some("ScaledJob") => &workload["spec"]["jobTargetRef"]["template"],
        _ => &workload["spec"]["template"],
    }
}

/// The coordinator's Service as workers dial it: `http://NAME:PORT`.
fn service_url() -> String {
    let docs = load("deploy/k8s/coordinator.yaml");
    let service = one(&docs, "Service");
    format!(
        "http://{}:{}",
        service["metadata"]["name"].as_str().unwrap(),
        service["spec"]["ports"][0]["port"].as_i64().unwrap()
    )
}

/// CPUs of a Kubernetes quantity: "2", 2 or "500m".
fn cpus(quantity: &Yaml) -> f64 {
    match quantity {
        Yaml::Integer(n) => *n as f64,
        Yaml::String(s) => match s.strip_suffix('m') {
            Some(milli) => milli.parse::<f64>().map(|m| m / 1000.0).ok(),
            None => s.parse().ok(),
        }
        .unwrap_or_else(|| panic!("{s}: not a CPU quantity")),
        other => panic!("not a CPU quantity: {other:?}"),
    }
}

/// A worker container's --threads equals its CPU request and limit.
fn threads_match_resources(container: &Yaml, argv: &[String]) {
    let threads = match parse(argv) {
        Parsed::Worker(cli) => cli.threads.expect("--threads given").get(),
        other => panic!("expected a worker, found {other:?}"),
    };
    for side in ["requests", "limits"] {
        let cpu = cpus(&container["resources"][side]["cpu"]);
        assert_eq!(
            cpu, threads as f64,
            "resources.{side}.cpu {cpu} != --threads {threads}"
        );
        assert!(
            !container["resources"][side]["memory"].is_badvalue(),
            "resources.{side}.memory"
        );
    }
}

/// The value after `flag` in `argv`.
fn flag_value<'a>(argv: &'a [String], flag: &str) -> Option<&'a str> {
    argv.iter()
        .position(|a| a == flag)
        .and_then(|i| argv.get(i + 1))
        .map(String::as_str)
}

/// A probe's target: its httpGet path on the farm's port, or its exec command.
enum Probe {
    Http(String),
    Exec(Vec<String>),
}

/// The coordinator's probe `name`, on the farm's port (`port_name` or the number).
fn probe(c: &Yaml, name: &str, port_name: &str) -> Probe {
    let p = &c[name];
    assert!(!p.is_badvalue(), "no {name}");
    if !p["exec"].is_badvalue() {
        return Probe::Exec(strings(&p["exec"]["command"]));
    }
    let get = &p["httpGet"];
    let port = &get["port"];
    assert!(
        port.as_str() == Some(port_name) || port.as_i64() == Some(i64::from(PORT)),
        "{name} checks the farm's port"
    );
    Probe::Http(get["path"].as_str().expect("an httpGet path").to_string())
}

/// The coordinator's probes: startup and liveness GET a path on the farm's
/// port; readiness asks `/readyz` there with the token from the environment
/// (a `bash -c` script). Returns the paths and the readiness script.
fn coordinator_probes(c: &Yaml, port_name: &str) -> (Vec<String>, String) {
    let paths: Vec<String> = ["startupProbe", "livenessProbe"]
        .into_iter()
        .map(|name| match probe(c, name, port_name) {
            Probe::Http(path) => path,
            Probe::Exec(_) => panic!("{name}: expected httpGet"),
        })
        .collect();
    let Probe::Exec(command) = probe(c, "readinessProbe", port_name) else {
        panic!("readinessProbe: expected exec (it needs the token)");
    };
    assert_eq!(command[..2], ["bash", "-c"], "{command:?}");
    let script = command[2].clone();
    for needle in [
        format!("/dev/tcp/127.0.0.1/{PORT}"),
        "GET /readyz ".to_string(),
        "Bearer %s".to_string(),
        "\"$HYPERTEXTURE_TOKEN\"".to_string(),
    ] {
        assert!(script.contains(&needle), "{needle} not in {script}");
    }
    (paths, script)
}

/// The coordinator's probes, run against a real `serve` with a token: its
/// startup and liveness paths answer 200 without the token, and its
/// readiness script (the manifest's own, on the test's port) passes with
/// the token and fails with a wrong one.
#[test]
fn kubernetes_probes_answer_on_a_running_serve() {
    let docs = load("deploy/k8s/coordinator.yaml");
    let set = one(&docs, "StatefulSet");
    let (c, _) = container(set, "hypertexture-token");
    let (paths, script) = coordinator_probes(&c, c["ports"][0]["name"].as_str().unwrap());
    // The script's bash, head and grep: Debian's essential packages.
    let dockerfile = read("deploy/Dockerfile");
    let base = dockerfile.lines().rev().find(|l| l.starts_with("FROM "));
    assert!(
        base.is_some_and(|l| l.starts_with("FROM debian:")),
        "the image's base: {base:?}"
    );

    let dir = crate::support::scratch("k8s-probes");
    let data = dir.join("data");
    let (_serve, url) =
        crate::support::service::serve_without_workers(&data, &dir, &["--token", "sesame"]);
    for path in &paths {
        let answer = crate::support::http::get(&url, path);
        assert_eq!(answer.status, 200, "GET {path}: {}", answer.body);
    }
    let port = port_of(&url);
    let script = script.replace(
        &format!("/dev/tcp/127.0.0.1/{PORT}"),
        &format!("/dev/tcp/127.0.0.1/{port}"),
    );
    let readiness = |token: &str| {
        crate::support::output_within(
            std::process::Command::new("bash")
                .args(["-c", &script])
                .env("HYPERTEXTURE_TOKEN", token),
            10,
        )
    };
    let ready = readiness("sesame");
    assert!(
        ready.status.success(),
        "readiness with the token: {}",
        String::from_utf8_lossy(&ready.stderr)
    );
    assert!(
        !readiness("wrong").status.success(),
        "readiness passes without the right token"
    );
    let _ = std::fs::remove_dir_all(&dir);
}

/// The KEDA ScaledJob: each Job one plain worker dialling the Service, that
/// leaves when idle (--idle-exit), with the Deployment's threads, resources
/// and grace period, scaled on the same trigger as the ScaledObject.
#[test]
fn kubernetes_scaledjob_matches_the_binaries() {
    let scaled = &load("deploy/k8s/keda-scaledjob.yaml")[0];
    assert_eq!(scaled["apiVersion"].as_str(), Some("keda.sh/v1alpha1"));
    assert_eq!(scaled["kind"].as_str(), Some("ScaledJob"));
    let spec = &scaled["spec"];
    assert_eq!(spec["minReplicaCount"].as_i64(), Some(0));
    assert!(spec["maxReplicaCount"].as_i64().unwrap() >= 1);
    let job = &spec["jobTargetRef"];
    assert_eq!(job["parallelism"].as_i64(), Some(1), "one worker a Job");
    assert_eq!(job["completions"].as_i64(), Some(1), "one worker a Job");
    let pod = pod_template(scaled);
    assert!(
        matches!(
            pod["spec"]["restartPolicy"].as_str(),
            Some("Never" | "OnFailure")
        ),
        "a Job's pod restartPolicy"
    );

    let (c, argv) = pod_container(pod, "hypertexture-token");
    assert_eq!(plain_worker(&argv), service_url());
    threads_match_resources(&c, &argv);
    let idle: f64 = flag_value(&argv, "--idle-exit")
        .expect("a Job's worker leaves when idle: --idle-exit SECS")
        .parse()
        .expect("--idle-exit SECS");
    assert!(idle > 0.0);

    // The same worker as the Deployment's, leaving as gracefully.
    let deployment_docs = load("deploy/k8s/workers.yaml");
    let deployment = one(&deployment_docs, "Deployment");
    let (worker, _) = container(deployment, "hypertexture-token");
    assert_eq!(c["resources"], worker["resources"]);
    let grace = |pod: &Yaml| pod["spec"]["terminationGracePeriodSeconds"].as_i64();
    assert!(grace(pod).is_some_and(|g| g > 0));
    assert_eq!(grace(pod), grace(pod_template(deployment)));

    // Scaled on the queue exactly as the ScaledObject scales the Deployment.
    let object = &load("deploy/k8s/keda-scaledobject.yaml")[0];
    assert_eq!(spec["triggers"], object["spec"]["triggers"]);
}

/// Whether `selector`'s matchLabels all hold among `labels`.
fn selects(selector: &Yaml, labels: &Yaml) -> bool {
    selector["matchLabels"]
        .as_hash()
        .unwrap()
        .iter()
        .all(|(k, v)| &labels[k.as_str().unwrap()] == v)
}

/// The disruption budgets: the coordinator is never evicted, the workers of
/// the Deployment a fraction at a time, and the ScaledJob's pods (Jobs,
/// which allow only an integer minAvailable) have none.
#[test]
fn kubernetes_disruption_budgets_cover_the_coordinator_and_workers() {
    let budgets = load("deploy/k8s/pdb.yaml");
    for b in &budgets {
        assert_eq!(b["apiVersion"].as_str(), Some("policy/v1"));
        assert_eq!(b["kind"].as_str(), Some("PodDisruptionBudget"));
    }
    let budget_of = |labels: &Yaml| -> Option<&Yaml> {
        let mut found = budgets
            .iter()
            .filter(|b| selects(&b["spec"]["selector"], labels));
        let budget = found.next();
        assert!(found.next().is_none(), "two budgets select {labels:?}");
        budget
    };
    let labels =
        |path: &str, kind: &str| pod_template(one(&load(path), kind))["metadata"]["labels"].clone();

    let coordinator = budget_of(&labels("deploy/k8s/coordinator.yaml", "StatefulSet"))
        .expect("a budget for the coordinator");
    assert_eq!(coordinator["spec"]["maxUnavailable"].as_i64(), Some(0));

    let workers = budget_of(&labels("deploy/k8s/workers.yaml", "Deployment"))
        .expect("a budget for the workers");
    let most = &workers["spec"]["maxUnavailable"];
    let fraction_or_count = match most {
        Yaml::String(s) => s
            .strip_suffix('%')
            .and_then(|p| p.parse::<u32>().ok())
            .is_some_and(|p| p > 0 && p < 100),
        Yaml::Integer(n) => *n >= 1,
        _ => false,
    };
    assert!(fraction_or_count, "maxUnavailable {most:?}");

    assert!(
        budget_of(&labels("deploy/k8s/keda-scaledjob.yaml", "ScaledJob")).is_none(),
        "a budget selects the ScaledJob's pods"
    );
}

/// The custom resources' kinds, for which kubernetes-validate has no schema.
const CUSTOM_KINDS: [&str; 3] = ["ScaledObject", "ScaledJob", "ServiceMonitor"];

/// The Kubernetes manifests (deploy/k8s/*.yaml), by path from the root.
fn manifests() -> Vec<String> {
    let dir = crate::support::root().join("deploy/k8s");
    let mut paths: Vec<String> = std::fs::read_dir(&dir)
        .unwrap_or_else(|e| panic!("{}: {e}", dir.display()))
        .map(|e| e.unwrap().file_name().into_string().unwrap())
        .filter(|name| name.ends_with(".yaml"))
        .map(|name| format!("deploy/k8s/{name}"))
        .collect();
    paths.sort();
    paths
}

/// `kubernetes-validate --strict FILE`: whether it passed, and its output.
fn validate_strictly(file: &std::path::Path) -> (bool, String) {
    let out = std::process::Command::new("kubernetes-validate")
        .arg("--strict")
        .arg(file)
        .stdin(std::process::Stdio::null())
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .map(|child| crate::support::collect_within(child, 120))
        .unwrap_or_else(|e| {
            panic!(
                "kubernetes-validate: {e} (scripts/test-deps/kubernetes-validate.sh installs it)"
            )
        });
    let text = format!(
        "{}{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
    (out.status.success(), text)
}

/// Every manifest passes `kubernetes-validate --strict` (unknown fields are
/// errors): each built-in resource against its schema, the custom ones
/// reported as without a schema (their fields are checked by
/// kubernetes_custom_resources_use_known_fields). The ScaledJob's
/// jobTargetRef, a batch/v1 JobSpec, is validated as a Job. A misspelt field
/// fails, so the strict schemas are the ones applied.
#[test]
fn kubernetes_manifests_validate_strictly() {
    for path in manifests() {
        let (ok, out) = validate_strictly(&crate::support::root().join(&path));
        assert!(ok && !out.contains("ERROR"), "{path}:\n{out}");
        for doc in load(&path) {
            let kind = doc["kind"].as_str().unwrap();
            let expected = if CUSTOM_KINDS.contains(&kind) {
                format!("Couldn't find schema for kind {kind}")
            } else {
                let name = doc["metadata"]["name"].as_str().unwrap();
                format!("passed for resource {}/{name}", kind.to_lowercase())
            };
            assert!(out.contains(&expected), "{path}: {expected} not in\n{out}");
        }
    }

    let dir = crate::support::scratch("k8s-validate");
    let scaled = &load("deploy/k8s/keda-scaledjob.yaml")[0];
    let mut spec = String::new();
    yaml_rust2::YamlEmitter::new(&mut spec)
        .dump(&scaled["spec"]["jobTargetRef"])
        .unwrap();
    let spec: String = spec
        .lines()
        .filter(|l| *l != "---")
        .map(|l| format!("  {l}\n"))
        .collect();
    let job = dir.join("job.yaml");
    std::fs::write(
        &job,
        format!("apiVersion: batch/v1\nkind: Job\nmetadata:\n  name: worker\nspec:\n{spec}"),
    )
    .unwrap();
    let (ok, out) = validate_strictly(&job);
    assert!(
        ok && out.contains("passed for resource job/worker"),
        "the ScaledJob's jobTargetRef as a Job:\n{out}"
    );

    let misspelt = dir.join("misspelt.yaml");
    let text = read("deploy/k8s/workers.yaml");
    assert!(text.contains("terminationGracePeriodSeconds:"));
    std::fs::write(
        &misspelt,
        text.replace("terminationGracePeriodSeconds:", "terminationGracePeriod:"),
    )
    .unwrap();
    let (ok, out) = validate_strictly(&misspelt);
    assert!(
        !ok && out.contains("'terminationGracePeriod' was unexpected"),
        "--strict lets an unknown field through:\n{out}"
    );
    let _ = std::fs::remove_dir_all(&dir);
}

/// Whether every key of the mapping `y` is one of `known`.
fn only_known(y: &Yaml, known: &[&str], what: &str) {
    let map = y
        .as_hash()
        .unwrap_or_else(|| panic!("{what}: not a mapping"));
    for key in map.keys() {
        let key = key.as_str().unwrap();
        assert!(known.contains(&key), "{what}: unknown field {key}");
    }
}

/// The fields of KEDA's triggers (keda.sh/v1alpha1).
const TRIGGER_FIELDS: &[&str] = &[
    "type",
    "name",
    "metadata",
    "authenticationRef",
    "metricType",
    "useCachedMetrics",
];
/// The metadata of KEDA's prometheus scaler.
const PROMETHEUS_FIELDS: &[&str] = &[
    "serverAddress",
    "query",
    "queryParameters",
    "threshold",
    "activationThreshold",
    "namespace",
    "customHeaders",
    "ignoreNullValues",
    "unsafeSsl",
];
/// The spec of KEDA's ScaledObject.
const SCALED_OBJECT_FIELDS: &[&str] = &[
    "scaleTargetRef",
    "pollingInterval",
    "cooldownPeriod",
    "initialCooldownPeriod",
    "idleReplicaCount",
    "minReplicaCount",
    "maxReplicaCount",
    "fallback",
    "advanced",
    "triggers",
];
/// The spec of KEDA's ScaledJob.
const SCALED_JOB_FIELDS: &[&str] = &[
    "jobTargetRef",
    "pollingInterval",
    "successfulJobsHistoryLimit",
    "failedJobsHistoryLimit",
    "envSourceContainerName",
    "minReplicaCount",
    "maxReplicaCount",
    "rollout",
    "scalingStrategy",
    "triggers",
];
/// A ScaledJob's scalingStrategy.
const SCALING_STRATEGY_FIELDS: &[&str] = &[
    "strategy",
    "customScalingQueueLengthDeduction",
    "customScalingRunningJobPercentage",
    "pendingPodConditions",
    "multipleScalersCalculation",
];
/// The spec of the Prometheus Operator's ServiceMonitor (monitoring.coreos.com/v1).
const SERVICE_MONITOR_FIELDS: &[&str] = &[
    "jobLabel",
    "targetLabels",
    "podTargetLabels",
    "endpoints",
    "selector",
    "namespaceSelector",
    "sampleLimit",
];
/// A ServiceMonitor's endpoint.
const ENDPOINT_FIELDS: &[&str] = &[
    "port",
    "targetPort",
    "path",
    "scheme",
    "params",
    "interval",
    "scrapeTimeout",
    "tlsConfig",
    "authorization",
    "honorLabels",
    "honorTimestamps",
    "metricRelabelings",
    "relabelings",
];

/// A KEDA spec's prometheus triggers use only the scaler's fields.
fn known_triggers(spec: &Yaml, kind: &str) {
    for t in spec["triggers"].as_vec().unwrap() {
        only_known(t, TRIGGER_FIELDS, &format!("{kind} trigger"));
        assert_eq!(t["type"].as_str(), Some("prometheus"));
        only_known(
            &t["metadata"],
            PROMETHEUS_FIELDS,
            &format!("{kind} prometheus"),
        );
    }
}

/// A ServiceMonitor's spec uses only the operator's fields.
fn known_service_monitor(spec: &Yaml) {
    only_known(spec, SERVICE_MONITOR_FIELDS, "ServiceMonitor");
    for endpoint in spec["endpoints"].as_vec().unwrap() {
        only_known(endpoint, ENDPOINT_FIELDS, "endpoint");
        let authorization = &endpoint["authorization"];
        only_known(authorization, &["type", "credentials"], "authorization");
        only_known(
            &authorization["credentials"],
            &["name", "key", "optional"],
            "credentials",
        );
    }
}

/// The custom resources, for which kubernetes-validate has no schema, use
/// only the fields of their published definitions: KEDA's ScaledObject and
/// ScaledJob (keda.sh/v1alpha1) with the prometheus scaler, and the
/// Prometheus Operator's ServiceMonitor (monitoring.coreos.com/v1).
#[test]
fn kubernetes_custom_resources_use_known_fields() {
    let mut seen = Vec::new();
    for doc in manifests().iter().flat_map(|p| load(p)) {
        let kind = doc["kind"].as_str().unwrap().to_string();
        if !CUSTOM_KINDS.contains(&kind.as_str()) {
            continue;
        }
        only_known(&doc, &["apiVersion", "kind", "metadata", "spec"], &kind);
        let spec = &doc["spec"];
        match kind.as_str() {
            "ScaledObject" => {
                only_known(spec, SCALED_OBJECT_FIELDS, &kind);
                only_known(
                    &spec["scaleTargetRef"],
                    &["apiVersion", "kind", "name", "envSourceContainerName"],
                    "scaleTargetRef",
                );
                known_triggers(spec, &kind);
            }
            "ScaledJob" => {
                only_known(spec, SCALED_JOB_FIELDS, &kind);
                let strategy = &spec["scalingStrategy"];
                only_known(strategy, SCALING_STRATEGY_FIELDS, "scalingStrategy");
                assert!(matches!(
                    strategy["strategy"].as_str(),
                    Some("default" | "custom" | "accurate" | "eager")
                ));
                known_triggers(spec, &kind);
            }
            _ => known_service_monitor(spec),
        }
        seen.push(kind);
    }
    seen.sort();
    assert_eq!(seen, ["ScaledJob", "ScaledObject", "ServiceMonitor"]);
}
