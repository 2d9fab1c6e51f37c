//! `lcrl experiment k8s`: the study as a Kubernetes Indexed Job. Each
//! completion index is one task of the plan (`lcrl experiment task FILE
//! --out DIR`, the index from $JOB_COMPLETION_INDEX); all pods share one
//! volume, so `lcrl experiment report` reads the result there.

use std::fmt::Write as _;
use std::path::Path;

use anyhow::bail;

use super::config::Experiment;
use super::plan::Task;
use crate::output::write_atomic;

/// Where the pods see the experiment file and the shared volume.
pub const FILE_IN_POD: &str = "/experiment/experiment.toml";
pub const DATA_IN_POD: &str = "/data";

pub struct K8sOptions {
    /// Pods at a time.
    pub parallelism: usize,
    /// The image deploy/build-image.sh builds.
    pub image: String,
    /// Size of the shared volume claim.
    pub storage: String,
}

/// The output folder of the study inside the pods.
pub fn out_in_pod(e: &Experiment) -> String {
    format!("{DATA_IN_POD}/{}", e.file.name)
}

/// Writes kustomization.yaml, job.yaml, report-job.yaml and a copy of the
/// experiment file into `dir`.
pub fn write(e: &Experiment, file: &Path, tasks: &[Task], dir: &Path, opts: &K8sOptions) -> anyhow::Result<()> {
    if let Some(env) = e.file.environments.iter().find(|env| !lcrl_sim::known_env_names().contains(&env.as_str())) {
        bail!("environment \"{env}\" is a file, which the lcrl image does not hold; on a cluster use registered environments ({})", lcrl_sim::known_env_names().join(", "));
    }
    if !opts.image.contains(':') {
        bail!("--image {} needs a tag, e.g. lcrl:local (the tag deploy/build-image.sh builds)", opts.image);
    }
    let name = format!("lcrl-experiment-{}", e.file.name);
    std::fs::create_dir_all(dir)?;
    write_atomic(&dir.join("experiment.toml"), &std::fs::read_to_string(file)?)?;
    write_atomic(
        &dir.join("kustomization.yaml"),
        &format!(
            "# Experiment \"{exp}\" on Kubernetes (written by `lcrl experiment k8s`).\n\
             # kubectl apply -k {dir}; when the Job completes, kubectl apply -f {dir}/report-job.yaml.\n\
             apiVersion: kustomize.config.k8s.io/v1beta1\nkind: Kustomization\nresources:\n  - job.yaml\n\
             configMapGenerator:\n  - name: {name}\n    files:\n      - experiment.toml\n\
             # report-job.yaml, applied later with -f, names the ConfigMap as is.\n\
             generatorOptions:\n  disableNameSuffixHash: true\n",
            exp = e.file.name,
            dir = dir.display()
        ),
    )?;
    let mut index = String::new();
    for (i, task) in tasks.iter().enumerate() {
        let _ = writeln!(index, "#   {i:>4}  {}", task.id());
    }
    let out = out_in_pod(e);
    let pod = |role: &str, args: &str| {
        format!(
            "  template:\n    metadata:\n      labels:\n        app.kubernetes.io/name: lcrl-experiment\n        lcrl.io/experiment: {exp}\n        lcrl.io/role: {role}\n\
             \x20   spec:\n      restartPolicy: Never\n      containers:\n        - name: {role}\n          image: {image}\n          imagePullPolicy: IfNotPresent\n\
             \x20         args: [{args}]\n\
             \x20         # One libtorch thread per run; the replay buffer of 1e6 peg\n          # transitions is ~0.2 GB.\n\
             \x20         resources:\n            requests:\n              cpu: \"1\"\n              memory: 1Gi\n            limits:\n              memory: 4Gi\n\
             \x20         volumeMounts:\n            - name: experiment\n              mountPath: /experiment\n              readOnly: true\n            - name: data\n              mountPath: {DATA_IN_POD}\n\
             \x20     volumes:\n        - name: experiment\n          configMap:\n            name: {name}\n        - name: data\n          persistentVolumeClaim:\n            claimName: lcrl-experiments\n",
            exp = e.file.name,
            image = opts.image
        )
    };
    let quoted = |args: &[&str]| args.iter().map(|a| format!("\"{a}\"")).collect::<Vec<_>>().join(", ");
    let job = format!(
        "# One completion index per task of experiment \"{exp}\" ({n} tasks); a pod\n\
         # runs `lcrl experiment task` with its index from $JOB_COMPLETION_INDEX.\n\
         # A retried or preempted pod resumes its run from the newest checkpoint.\n{index}\
         apiVersion: v1\nkind: PersistentVolumeClaim\nmetadata:\n  name: lcrl-experiments\n\
         spec:\n  # Every pod writes here at once: a ReadWriteMany class (NFS, CephFS, EFS, …).\n  accessModes:\n    - ReadWriteMany\n  resources:\n    requests:\n      storage: {storage}\n---\n\
         apiVersion: batch/v1\nkind: Job\nmetadata:\n  name: {name}\nspec:\n  completionMode: Indexed\n  completions: {n}\n  parallelism: {p}\n  backoffLimitPerIndex: 2\n{pod}",
        exp = e.file.name,
        n = tasks.len(),
        p = opts.parallelism,
        storage = opts.storage,
        pod = pod("task", &quoted(&["experiment", "task", FILE_IN_POD, "--out", &out]))
    );
    write_atomic(&dir.join("job.yaml"), &job)?;
    let report = format!(
        "# Apply once {name} has completed: writes report.json, report.md,\n# curves.png and traces.png into {out} on the shared volume.\n\
         apiVersion: batch/v1\nkind: Job\nmetadata:\n  name: {name}-report\nspec:\n  backoffLimit: 1\n{pod}",
        pod = pod("report", &quoted(&["experiment", "report", &out]))
    );
    write_atomic(&dir.join("report-job.yaml"), &report)
}
