//! deploy/: the Kubernetes kustomization checked by parsing every manifest
//! and the references between them (no cluster is reachable here), the
//! compose file's commands checked against the real CLI, and the compose
//! end-to-end script run on this machine's Docker engine when there is one.

use std::collections::{BTreeMap, BTreeSet};
use std::path::Path;

use serde_yaml::Value;

use super::common::{lcrl, load_docs, repo, seq, stderr, stdout, str_of};

/// `lcrl launch ARGS --dry-run` with the manifest's placeholders filled in:
/// the command line it would run.
fn dry_run(args: &[String], run_dir: &Path, tls: &Path) -> String {
    let out = launch_here(args, run_dir, tls).arg("--dry-run").output().unwrap();
    assert!(out.status.success(), "`lcrl {}` fails: {}", args.join(" "), stderr(&out));
    stdout(&out)
}

/// `lcrl ARGS` with the container's paths mapped to this machine's.
fn launch_here(args: &[String], run_dir: &Path, tls: &Path) -> std::process::Command {
    let configs = repo().join("configs");
    let args: Vec<String> = args.iter().map(|a| local_path(a, run_dir, tls).replace("/configs", &configs.display().to_string())).collect();
    let mut cmd = lcrl();
    cmd.args(&args);
    cmd
}

/// A container path on this machine: /runs and /tls (the TLS secret) mapped.
fn local_path(arg: &str, run_dir: &Path, tls: &Path) -> String {
    let arg = arg.replace("/runs", &run_dir.display().to_string());
    match arg.strip_prefix("/tls") {
        Some(rest) if rest.is_empty() || rest.starts_with('/') => format!("{}{rest}", tls.display()),
        _ => arg,
    }
}

/// A folder as `lcrl certs` writes it: what the Secret lcrl-tls holds.
fn certs() -> tempfile::TempDir {
    let dir = tempfile::tempdir().unwrap();
    let out = lcrl().args(["certs", "--out"]).arg(dir.path()).output().unwrap();
    assert!(out.status.success(), "{}", stderr(&out));
    dir
}

/// The files of a Secret volume as a pod sees them: its `items`, or every
/// file `lcrl certs` writes when it lists none.
fn secret_files(volume: &Value) -> Vec<String> {
    match volume["secret"]["items"].as_sequence() {
        Some(items) => items
            .iter()
            .map(|item| {
                assert_eq!(item["key"], item["path"], "a Secret item keeps its file name: {item:?}");
                str_of(item, &["key"]).to_string()
            })
            .collect(),
        None => ["ca.pem", "server.pem", "server.key", "client.pem", "client.key", "token"].map(String::from).to_vec(),
    }
}

/// A folder with only `files` of `certs`: /tls as one pod sees it.
fn tls_with(certs: &Path, files: &[String]) -> tempfile::TempDir {
    let dir = tempfile::tempdir().unwrap();
    for file in files {
        std::fs::copy(certs.join(file), dir.path().join(file)).unwrap_or_else(|e| panic!("{file}: not a file `lcrl certs` writes ({e})"));
    }
    dir
}

/// `s` with every `${VAR:-default}` replaced by its default, as compose
/// reads it with VAR unset.
fn with_defaults(s: &str) -> String {
    let mut out = String::new();
    let mut rest = s;
    while let Some(start) = rest.find("${") {
        out.push_str(&rest[..start]);
        let end = start + rest[start..].find('}').unwrap_or_else(|| panic!("unclosed ${{ in {s}"));
        out.push_str(rest[start + 2..end].split_once(":-").map_or("", |(_, default)| default));
        rest = &rest[end + 1..];
    }
    out.push_str(rest);
    out
}

/// The unprivileged user deploy/Dockerfile runs as (`USER UID:GID`).
fn image_user() -> (i64, i64) {
    let dockerfile = std::fs::read_to_string(repo().join("deploy/Dockerfile")).unwrap();
    let users: Vec<&str> = dockerfile.lines().filter_map(|l| l.trim().strip_prefix("USER ")).collect();
    assert_eq!(users.len(), 1, "deploy/Dockerfile names one USER: {users:?}");
    let (uid, gid) = users[0].trim().split_once(':').expect("USER UID:GID, numeric (no /etc/passwd in the image)");
    let (uid, gid): (i64, i64) = (uid.parse().unwrap(), gid.parse().unwrap());
    assert!(uid > 0 && gid > 0, "the image runs as root: USER {}", users[0]);
    (uid, gid)
}

/// An exec health probe: `lcrl health https://127.0.0.1:PORT` with TLS
/// files that `lcrl certs` writes; returns the port.
fn check_health_command(words: &[&str], tls: &Path, what: &str) -> u16 {
    assert_eq!(&words[..2], ["/bin/lcrl", "health"], "{what}: {words:?}");
    let port = words[2].strip_prefix("https://127.0.0.1:").unwrap_or_else(|| panic!("{what}: probes {} without TLS", words[2]));
    for file in words.iter().filter_map(|w| w.strip_prefix("/tls/")) {
        assert!(tls.join(file).is_file(), "{what}: /tls/{file} is not a file `lcrl certs` writes");
    }
    for flag in ["--tls-ca", "--tls-client-cert", "--tls-client-key"] {
        assert!(words.contains(&flag), "{what}: health probe without {flag} (servers ask for client certificates)");
    }
    port.parse().unwrap()
}

#[test]
fn kubernetes_manifests_reference_each_other_consistently() {
    let tls = certs();
    let k8s = repo().join("deploy/k8s");
    let kustomization = &load_docs(&k8s.join("kustomization.yaml"))[0];
    assert_eq!(str_of(kustomization, &["kind"]), "Kustomization");

    // Generated ConfigMaps: name -> keys; the presets mirror configs/.
    let mut config_maps: BTreeMap<String, BTreeSet<String>> = BTreeMap::new();
    for generator in seq(kustomization, "configMapGenerator") {
        let keys = config_maps.entry(str_of(generator, &["name"]).to_string()).or_default();
        for file in seq(generator, "files") {
            let path = k8s.join(file.as_str().unwrap());
            let name = path.file_name().unwrap().to_string_lossy().into_owned();
            let original = repo().join("configs").join(&name);
            let same = std::fs::read(&path).ok() == std::fs::read(&original).ok();
            assert!(same, "{} differs from {} (copy configs/ into deploy/k8s/presets/)", path.display(), original.display());
            keys.insert(name);
        }
        for literal in seq(generator, "literals") {
            keys.insert(literal.as_str().unwrap().split_once('=').unwrap().0.to_string());
        }
    }
    let presets = &config_maps["lcrl-presets"];
    // Every preset (a config with a [job] section) is in the ConfigMap, but
    // those that serve a Gymnasium environment: the image has no Python
    // (`lcrl launch` refuses them, see launch_refuses_presets_that_serve_python).
    for entry in std::fs::read_dir(repo().join("configs")).unwrap() {
        let path = entry.unwrap().path();
        let name = path.file_name().unwrap().to_string_lossy().into_owned();
        let text = std::fs::read_to_string(&path).unwrap();
        if text.contains("[job]") && !text.contains("[env_server]") {
            assert!(presets.contains(&name), "configs/{name} is not in the lcrl-presets ConfigMap");
        }
    }
    let literals: BTreeMap<&str, &str> = seq(&seq(kustomization, "configMapGenerator")[1], "literals").iter().filter_map(|l| l.as_str()?.split_once('=')).collect();
    assert!(presets.contains(literals["preset"]), "lcrl-run's preset {} is not a preset", literals["preset"]);

    // The image the manifests name is the one build-image.sh builds.
    let image = &seq(kustomization, "images")[0];
    let image_name = str_of(image, &["name"]);
    let built = format!("{}:{}", str_of(image, &["newName"]), str_of(image, &["newTag"]));
    let build_script = std::fs::read_to_string(repo().join("deploy/build-image.sh")).unwrap();
    assert!(build_script.contains(&format!("tag=\"${{1:-{built}}}\"")), "build-image.sh does not build {built}");

    let docs: Vec<Value> = seq(kustomization, "resources").iter().flat_map(|r| load_docs(&k8s.join(r.as_str().unwrap()))).collect();
    let of_kind = |kind: &'static str| docs.iter().filter(move |d| d["kind"].as_str() == Some(kind));
    let claims: BTreeSet<&str> = of_kind("PersistentVolumeClaim").map(|d| str_of(d, &["metadata", "name"])).collect();
    let services: BTreeMap<&str, &Value> = of_kind("Service").map(|d| (str_of(d, &["metadata", "name"]), d)).collect();
    let deployments: Vec<&Value> = of_kind("Deployment").collect();
    assert_eq!(deployments.len(), 3, "graph builder, learner, actors");
    let run_dir = tempfile::tempdir().unwrap();
    let mut roles = BTreeSet::new();
    let (image_uid, image_gid) = image_user();

    for deployment in &deployments {
        let name = str_of(deployment, &["metadata", "name"]);
        let labels = &deployment["spec"]["template"]["metadata"]["labels"];
        for (key, value) in deployment["spec"]["selector"]["matchLabels"].as_mapping().unwrap() {
            assert_eq!(&labels[key.as_str().unwrap()], value, "{name}: selector does not match its pods");
        }
        let pod = &deployment["spec"]["template"]["spec"];
        let volumes: BTreeMap<&str, &Value> = seq(pod, "volumes").into_iter().map(|v| (str_of(v, &["name"]), v)).collect();
        for volume in volumes.values() {
            if let Some(cm) = volume["configMap"]["name"].as_str() {
                assert!(config_maps.contains_key(cm), "{name}: ConfigMap {cm} is not generated");
            }
            if let Some(claim) = volume["persistentVolumeClaim"]["claimName"].as_str() {
                assert!(claims.contains(claim), "{name}: claim {claim} does not exist");
            }
            if let Some(secret) = volume["secret"]["secretName"].as_str() {
                assert_eq!(secret, "lcrl-tls", "{name}: the TLS secret README tells users to create");
            }
        }
        assert!(volumes.values().any(|v| v["secret"]["secretName"].as_str() == Some("lcrl-tls")), "{name}: no TLS secret");
        // Never root: the image's user, and fsGroup so it reads the Secret
        // and writes its volumes.
        let security = &pod["securityContext"];
        assert_eq!(security["runAsNonRoot"].as_bool(), Some(true), "{name}: runAsNonRoot");
        assert_eq!((security["runAsUser"].as_i64(), security["runAsGroup"].as_i64()), (Some(image_uid), Some(image_gid)), "{name}: runs as the image's user");
        assert_eq!(security["fsGroup"].as_i64(), Some(image_gid), "{name}: fsGroup");
        // /tls as this pod sees it: only the Secret's files it mounts.
        let mounted: Vec<String> = volumes.values().filter(|v| v["secret"].is_mapping()).flat_map(|v| secret_files(v)).collect();
        let pod_tls = tls_with(tls.path(), &mounted);
        let tls = &pod_tls;
        for container in seq(pod, "containers") {
            assert_eq!(container["securityContext"]["allowPrivilegeEscalation"].as_bool(), Some(false), "{name}: allowPrivilegeEscalation");
            assert_eq!(str_of(container, &["image"]), image_name, "{name}: image");
            let ports: BTreeMap<&str, i64> = seq(container, "ports").iter().map(|p| (str_of(p, &["name"]), p["containerPort"].as_i64().unwrap())).collect();
            let mut env = BTreeMap::new();
            for var in seq(container, "env") {
                let r = &var["valueFrom"]["configMapKeyRef"];
                let (cm, key) = (str_of(r, &["name"]), str_of(r, &["key"]));
                assert!(config_maps.get(cm).is_some_and(|keys| keys.contains(key)), "{name}: {cm}/{key} does not exist");
                let value = if cm == "lcrl-run" { literals[key] } else { key };
                env.insert(format!("$({})", str_of(var, &["name"])), value.to_string());
            }
            for mount in seq(container, "volumeMounts") {
                let volume = volumes.get(str_of(mount, &["name"])).unwrap_or_else(|| panic!("{name}: mounts an undeclared volume"));
                if volume["secret"].is_mapping() {
                    assert_eq!((str_of(mount, &["mountPath"]), mount["readOnly"].as_bool()), ("/tls", Some(true)), "{name}: the secret is mounted read-only at /tls");
                }
            }
            for probe in ["readinessProbe", "livenessProbe"] {
                let p = &container[probe];
                if let Some(port) = p["grpc"]["port"].as_i64() {
                    assert!(ports.values().any(|&c| c == port), "{name}: {probe} on port {port}, not a container port");
                    if let Some(service) = p["grpc"]["service"].as_str() {
                        assert!(["lcrl.v1.Graph", "lcrl.v1.Learner", "lcrl.v1.Policy"].contains(&service), "{name}: {probe} asks for {service}");
                    }
                } else if let Some(port) = p["httpGet"]["port"].as_str() {
                    assert!(ports.contains_key(port), "{name}: {probe} on port {port}");
                    // An actor's liveness is its progress (/healthz), not
                    // that its metrics endpoint answers.
                    if probe == "livenessProbe" {
                        assert_eq!(str_of(p, &["httpGet", "path"]), "/healthz", "{name}: {probe}");
                    }
                } else if let Some(command) = p["exec"]["command"].as_sequence() {
                    let words: Vec<&str> = command.iter().filter_map(Value::as_str).collect();
                    let port = check_health_command(&words, tls.path(), &format!("{name} {probe}"));
                    assert!(ports.values().any(|&c| c == i64::from(port)), "{name}: {probe} on port {port}, not a container port");
                }
            }
            // Arguments: placeholders defined, URLs naming a Service port, and
            // the whole command line accepted by the real CLI.
            let args: Vec<String> = seq(container, "args")
                .iter()
                .map(|a| env.iter().fold(a.as_str().unwrap().to_string(), |s, (var, value)| s.replace(var, value)))
                .collect();
            for arg in &args {
                assert!(!arg.contains("$("), "{name}: {arg} uses an undefined variable");
                assert!(!arg.starts_with("http://"), "{name}: {arg} is plain text between pods");
                if let Some(rest) = arg.strip_prefix("https://") {
                    let (host, port) = rest.split_once(':').unwrap();
                    let service = services.get(host).unwrap_or_else(|| panic!("{name}: no Service {host}"));
                    assert!(seq(&service["spec"], "ports").iter().any(|p| p["port"].as_str().map(str::to_string).or(p["port"].as_i64().map(|n| n.to_string())).as_deref() == Some(port)), "{name}: Service {host} has no port {port}");
                }
            }
            for file in args.iter().filter_map(|a| a.strip_prefix("/tls/")) {
                assert!(tls.path().join(file).is_file(), "{name}: /tls/{file} is not a file `lcrl certs` writes");
            }
            let command = dry_run(&args, run_dir.path(), tls.path());
            assert!(command.contains("--token-file") && command.contains("--tls-"), "{name}: runs without TLS or token: {command}");
            let binary = command.split_whitespace().next().unwrap().to_string();
            if binary == "lcrl-actor" {
                // A client: the CA, its certificate and key; never the server's key.
                assert!(!mounted.iter().any(|f| f.starts_with("server.")), "{name}: an actor mounts the server's key or certificate: {mounted:?}");
            } else {
                // `lcrl launch` listens on loopback unless told: a server in a
                // pod says 0.0.0.0 on its gRPC port.
                let grpc = ports.get("grpc").unwrap_or_else(|| panic!("{name}: a server without a grpc port"));
                assert!(command.contains(&format!("--listen 0.0.0.0:{grpc}")), "{name}: not reachable by its Service: `{command}`");
            }
            roles.insert(binary);
        }
    }
    assert_eq!(roles, ["lcrl-actor", "lcrl-graph-builder", "lcrl-learner"].map(String::from).into_iter().collect());

    for (name, service) in &services {
        let selector = service["spec"]["selector"].as_mapping().unwrap();
        let targets: Vec<&&Value> = deployments
            .iter()
            .filter(|d| selector.iter().all(|(k, v)| &d["spec"]["template"]["metadata"]["labels"][k.as_str().unwrap()] == v))
            .collect();
        assert_eq!(targets.len(), 1, "Service {name} selects {} Deployments", targets.len());
        let container_ports: BTreeSet<String> = seq(&targets[0]["spec"]["template"]["spec"], "containers")
            .iter()
            .flat_map(|c| seq(c, "ports"))
            .map(|p| str_of(p, &["name"]).to_string())
            .collect();
        for port in seq(&service["spec"], "ports") {
            assert!(container_ports.contains(str_of(port, &["targetPort"])), "Service {name}: targetPort {:?} is no container port", port["targetPort"]);
        }
    }

    // Network policies: each guards one Deployment's pods, admits only the
    // peers the design names, on ports those pods declare.
    let labels_of = |d: &Value| d["spec"]["template"]["metadata"]["labels"]["app.kubernetes.io/name"].as_str().unwrap().to_string();
    let selects = |selector: &Value| -> Vec<String> {
        let wanted = selector["matchLabels"].as_mapping().unwrap();
        deployments.iter().filter(|d| wanted.iter().all(|(k, v)| &d["spec"]["template"]["metadata"]["labels"][k.as_str().unwrap()] == v)).map(|d| labels_of(d)).collect()
    };
    let mut admitted: BTreeMap<String, BTreeSet<String>> = BTreeMap::new();
    for policy in of_kind("NetworkPolicy") {
        let name = str_of(policy, &["metadata", "name"]);
        let guarded = selects(&policy["spec"]["podSelector"]);
        assert_eq!(guarded.len(), 1, "NetworkPolicy {name} selects {guarded:?}");
        let target = deployments.iter().find(|d| labels_of(d) == guarded[0]).unwrap();
        let ports: BTreeSet<String> = seq(&target["spec"]["template"]["spec"], "containers").iter().flat_map(|c| seq(c, "ports")).map(|p| str_of(p, &["name"]).to_string()).collect();
        for rule in seq(&policy["spec"], "ingress") {
            let rule_ports: Vec<&str> = seq(rule, "ports").iter().map(|p| str_of(p, &["port"])).collect();
            for port in &rule_ports {
                assert!(ports.contains(*port), "NetworkPolicy {name}: port {port} is not a port of {}", guarded[0]);
            }
            for peer in seq(rule, "from") {
                let source = if peer["podSelector"].is_mapping() {
                    let from = selects(&peer["podSelector"]);
                    assert_eq!(from.len(), 1, "NetworkPolicy {name}: a podSelector matching {from:?}");
                    from[0].clone()
                } else {
                    format!("namespace {}", str_of(peer, &["namespaceSelector", "matchLabels", "kubernetes.io/metadata.name"]))
                };
                for port in &rule_ports {
                    admitted.entry(format!("{}:{port}", guarded[0])).or_default().insert(source.clone());
                }
            }
        }
    }
    let expect = |s: &[&str]| s.iter().map(|x| x.to_string()).collect::<BTreeSet<String>>();
    assert_eq!(admitted["lcrl-learner:grpc"], expect(&["lcrl-actor"]), "only actors reach the learner's gRPC port");
    assert_eq!(admitted["lcrl-graph-builder:grpc"], expect(&["lcrl-learner"]), "only the learner reaches the graph builder");
    for metrics in ["lcrl-learner:metrics", "lcrl-actor:metrics"] {
        assert_eq!(admitted[metrics], expect(&["namespace monitoring"]), "{metrics}");
    }
}

#[test]
fn compose_commands_are_accepted_by_the_cli() {
    let tls = certs();
    let plain = load_docs(&repo().join("deploy/compose.yaml")).remove(0);
    check_compose(&plain, tls.path(), false);
    // compose.secure.yaml laid over compose.yaml, as compose merges them:
    // its commands, health checks and volumes per service.
    let secure_file = load_docs(&repo().join("deploy/compose.secure.yaml")).remove(0);
    let mut secure = plain.clone();
    let mut overlay = secure_file.clone();
    overlay.apply_merge().expect("compose.secure.yaml merge keys");
    for (name, service) in overlay["services"].as_mapping().unwrap() {
        let target = secure["services"][name.as_str().unwrap()].as_mapping_mut().unwrap_or_else(|| panic!("compose.secure.yaml names a service {name:?} compose.yaml lacks"));
        for (key, value) in service.as_mapping().unwrap() {
            target.insert(key.clone(), value.clone());
        }
    }
    check_compose(&secure, tls.path(), true);
}

fn check_compose(compose: &Value, tls: &Path, secure: bool) {
    let mut compose = compose.clone();
    compose.apply_merge().expect("compose merge keys (<<: *lcrl)");
    let services = compose["services"].as_mapping().unwrap();
    let run_dir = tempfile::tempdir().unwrap();
    let substitute = |s: &str| s.replace("${LCRL_PRESET:-lti-paper.toml}", "lti-paper.toml").replace("${LCRL_RUN_ID:-compose}", "compose").replace("${LCRL_EPISODES:-0}", "0");
    let compose_sh = std::fs::read_to_string(repo().join("deploy/compose.sh")).unwrap();
    let mut binaries = BTreeSet::new();
    for (name, service) in services {
        let name = name.as_str().unwrap();
        let command: Vec<String> = seq(service, "command").iter().map(|a| substitute(a.as_str().unwrap())).collect();
        let launched = dry_run(&command, run_dir.path(), tls);
        let binary = launched.split_whitespace().next().unwrap().to_string();
        assert_eq!(launched.contains("--tls-"), secure, "{name}: `{launched}`");
        let mounts: Vec<&str> = seq(service, "volumes").iter().filter_map(|v| v.as_str()).collect();
        if secure {
            let tls_mounts: Vec<&&str> = mounts.iter().filter(|m| m.contains(":/tls")).collect();
            assert!(!tls_mounts.is_empty() && tls_mounts.iter().all(|m| m.ends_with(":ro")), "{name}: /tls is not mounted read-only: {mounts:?}");
            assert_eq!(service["environment"]["LCRL_TOKEN_FILE"].as_str(), Some("/tls/token"), "{name}: token");
            if binary == "lcrl-actor" {
                // A client: the CA, its certificate and key, the token; never
                // the server's key (nor the whole folder that holds it).
                let targets: BTreeSet<String> = tls_mounts.iter().map(|m| with_defaults(m).split(':').nth(1).unwrap().to_string()).collect();
                assert_eq!(targets, ["/tls/ca.pem", "/tls/client.key", "/tls/client.pem", "/tls/token"].map(String::from).into_iter().collect(), "{name}: {mounts:?}");
                let files: Vec<String> = targets.iter().map(|t| t.trim_start_matches("/tls/").to_string()).collect();
                let actor_tls = tls_with(tls, &files);
                dry_run(&command, run_dir.path(), actor_tls.path());
            }
        } else {
            // The token compose.sh generates at set-up, in every container.
            assert_eq!(service["environment"]["LCRL_TOKEN_FILE"].as_str(), Some("/secrets/token"), "{name}: token");
            let secrets = mounts.iter().find(|m| m.contains(":/secrets")).unwrap_or_else(|| panic!("{name}: the token's folder is not mounted: {mounts:?}"));
            assert!(secrets.ends_with(":/secrets:ro"), "{name}: {secrets}");
            let default = with_defaults(secrets);
            let folder = default.split(':').next().unwrap().trim_start_matches("../");
            assert!(compose_sh.contains(&format!("$repo/{folder}")), "deploy/compose.sh does not write the token where compose.yaml mounts it ({folder})");
        }
        // Servers listen on 0.0.0.0 in their container: plain text only with
        // --insecure said, and `lcrl launch` refuses it without.
        let insecure = command.iter().any(|a| a == "--insecure");
        assert_eq!(insecure, !secure && binary != "lcrl-actor", "{name}: --insecure where and only where plain text listens beyond loopback: {command:?}");
        if insecure {
            let without: Vec<String> = command.iter().filter(|a| *a != "--insecure").cloned().collect();
            let out = launch_here(&without, run_dir.path(), tls).arg("--dry-run").output().unwrap();
            super::common::assert_clean_failure(&out, "--insecure");
        }
        binaries.insert(binary);
        // Never root: the host user compose.sh names, 10001 by default.
        let user = service["user"].as_str().unwrap_or_else(|| panic!("{name}: no user (it would run as root)"));
        let ids: Vec<i64> = with_defaults(user).split(':').map(|id| id.parse().unwrap_or_else(|_| panic!("{name}: user {user} is not UID:GID"))).collect();
        assert!(ids.len() == 2 && ids.iter().all(|&id| id > 0), "{name}: user {user} is root by default");
        // Published ports on loopback only.
        for port in seq(service, "ports") {
            let port = port.as_str().unwrap();
            assert!(port.starts_with("127.0.0.1:"), "{name}: port {port} is published beyond this host");
        }
        assert!(service["image"].as_str().unwrap().contains("lcrl:local"), "{name}: image");
        if let Some(test) = service["healthcheck"]["test"].as_sequence() {
            let words: Vec<&str> = test.iter().filter_map(Value::as_str).collect();
            assert_eq!(words[0], "CMD", "{name}: health check");
            let port = if secure { check_health_command(&words[1..], tls, name).to_string() } else { words[3].rsplit(':').next().unwrap().to_string() };
            assert!(launched.contains(&format!("--listen 0.0.0.0:{port}")), "{name}: health check on port {port}, but it runs `{launched}`");
        }
    }
    assert_eq!(binaries.len(), 3, "{binaries:?}");
}

/// Builds the image and runs the stack (deploy/compose-e2e.sh); the script
/// itself skips, with a message, when no Docker engine is reachable.
#[test]
fn compose_stack_trains_and_survives_a_killed_actor() {
    let out = std::process::Command::new("bash").arg(repo().join("deploy/compose-e2e.sh")).output().unwrap();
    let (out_text, err_text) = (stdout(&out), stderr(&out));
    println!("{out_text}");
    assert!(out.status.success(), "compose-e2e failed:\n{out_text}\n{err_text}");
    assert!(out_text.contains("compose-e2e: PASSED") || out_text.contains("compose-e2e: SKIPPED"), "{out_text}");
}

#[test]
fn launch_refuses_presets_that_serve_python() {
    let preset = repo().join("configs/halfcheetah-ddpg-local.toml");
    let out = lcrl().args(["launch", "learner", "--dry-run", "--config"]).arg(&preset).output().unwrap();
    super::common::assert_clean_failure(&out, "serve it yourself");
}

/// `lcrl launch` serves on loopback unless told, and refuses plain text on
/// an address other hosts reach unless --insecure is said (issue 61).
#[test]
fn launch_listens_on_loopback_and_refuses_plain_text_beyond_it() {
    let preset = repo().join("configs/lti-paper.toml");
    let run_dir = tempfile::tempdir().unwrap();
    for (role, binary, port) in [("graph-builder", "lcrl-graph-builder", 50051), ("learner", "lcrl-learner", 50052)] {
        let launch = || {
            let mut cmd = lcrl();
            cmd.args(["launch", role, "--config"]).arg(&preset).arg("--run-dir").arg(run_dir.path()).env_remove("LCRL_TOKEN_FILE");
            cmd
        };
        let out = launch().arg("--dry-run").output().unwrap();
        assert!(out.status.success(), "{role}: {}", stderr(&out));
        assert!(stdout(&out).starts_with(binary) && stdout(&out).contains(&format!("--listen 127.0.0.1:{port}")), "{role}: {}", stdout(&out));
        // Not a dry run: the real command stops before starting anything.
        for listen in ["0.0.0.0:0", "[::]:0"] {
            let out = launch().args(["--listen", listen]).output().unwrap();
            super::common::assert_clean_failure(&out, "--insecure");
            assert!(stderr(&out).contains("--tls-dir"), "{role}: {}", stderr(&out));
        }
        let out = launch().args(["--listen", "0.0.0.0:0", "--insecure", "--dry-run"]).output().unwrap();
        assert!(out.status.success() && stdout(&out).contains("--listen 0.0.0.0:0"), "{role}: {}", stderr(&out));
        let tls = certs();
        let out = launch().args(["--listen", "0.0.0.0:0", "--dry-run", "--tls-dir"]).arg(tls.path()).output().unwrap();
        assert!(out.status.success(), "{role} with TLS: {}", stderr(&out));
    }
}
