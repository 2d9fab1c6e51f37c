//! deploy/: the Kubernetes kustomization checked by parsing every manifest
//! and the references between them (no cluster is reachable here), the
//! compose file's commands checked against the real CLI, and the compose
//! end-to-end script run on this machine's Docker engine when there is one.

use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};

use serde_yaml::Value;

use super::common::{lcrl, load_docs, seq, stderr, stdout, str_of};

fn repo() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
}

/// `lcrl launch ARGS --dry-run` with the manifest's placeholders filled in:
/// the command line it would run.
fn dry_run(args: &[String], run_dir: &Path) -> String {
    let configs = repo().join("configs");
    let args: Vec<String> = args
        .iter()
        .map(|a| a.replace("/configs", &configs.display().to_string()).replace("/runs", &run_dir.display().to_string()))
        .collect();
    let out = lcrl().args(&args).arg("--dry-run").output().unwrap();
    assert!(out.status.success(), "`lcrl {}` fails: {}", args.join(" "), stderr(&out));
    stdout(&out)
}

#[test]
fn kubernetes_manifests_reference_each_other_consistently() {
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
    // Every preset (a config with a [job] section) is in the ConfigMap.
    for entry in std::fs::read_dir(repo().join("configs")).unwrap() {
        let path = entry.unwrap().path();
        let name = path.file_name().unwrap().to_string_lossy().into_owned();
        if std::fs::read_to_string(&path).unwrap().contains("[job]") {
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
        }
        for container in seq(pod, "containers") {
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
                assert!(volumes.contains_key(str_of(mount, &["name"])), "{name}: mounts an undeclared volume");
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
                if let Some(rest) = arg.strip_prefix("http://") {
                    let (host, port) = rest.split_once(':').unwrap();
                    let service = services.get(host).unwrap_or_else(|| panic!("{name}: no Service {host}"));
                    assert!(seq(&service["spec"], "ports").iter().any(|p| p["port"].as_str().map(str::to_string).or(p["port"].as_i64().map(|n| n.to_string())).as_deref() == Some(port)), "{name}: Service {host} has no port {port}");
                }
            }
            let command = dry_run(&args, run_dir.path());
            roles.insert(command.split_whitespace().next().unwrap().to_string());
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
}

#[test]
fn compose_commands_are_accepted_by_the_cli() {
    let mut compose = load_docs(&repo().join("deploy/compose.yaml")).remove(0);
    compose.apply_merge().expect("compose.yaml merge keys (<<: *lcrl)");
    let services = compose["services"].as_mapping().unwrap();
    let run_dir = tempfile::tempdir().unwrap();
    let substitute = |s: &str| s.replace("${LCRL_PRESET:-lti-paper.toml}", "lti-paper.toml").replace("${LCRL_RUN_ID:-compose}", "compose").replace("${LCRL_EPISODES:-0}", "0");
    let mut binaries = BTreeSet::new();
    for (name, service) in services {
        let name = name.as_str().unwrap();
        let command: Vec<String> = seq(service, "command").iter().map(|a| substitute(a.as_str().unwrap())).collect();
        let launched = dry_run(&command, run_dir.path());
        binaries.insert(launched.split_whitespace().next().unwrap().to_string());
        assert!(service["image"].as_str().unwrap().contains("lcrl:local"), "{name}: image");
        if let Some(test) = service["healthcheck"]["test"].as_sequence() {
            let words: Vec<&str> = test.iter().filter_map(Value::as_str).collect();
            assert_eq!(&words[..3], ["CMD", "/bin/lcrl", "health"], "{name}: health check");
            let port = words[3].rsplit(':').next().unwrap();
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
