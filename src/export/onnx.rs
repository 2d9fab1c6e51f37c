//! `--format onnx`: the TorchScript module converted by PyTorch's own
//! exporter, in the project's Python (clients/python/lcrl_export_onnx.py),
//! and checked with ONNX Runtime against the served policy.

use std::path::Path;
use std::process::Command;

use anyhow::{bail, Context};
use serde::Deserialize;

use super::file::{install, partial_of, write_torchscript, Prepared};
use super::manifest::FileEntry;
use crate::binaries::{lcrl_python, project_file};

/// The script's answer: the ONNX file's actions on the probe states
/// (ONNX Runtime), and what converted and ran it.
#[derive(Debug, Deserialize)]
struct Report {
    actions: Vec<f32>,
    opset: i64,
    torch: String,
    onnxruntime: String,
}

/// Writes `out` as ONNX, checked like the TorchScript file.
pub fn write(prepared: &Prepared, out: &Path) -> anyhow::Result<FileEntry> {
    let python = lcrl_python().context("`--format onnx` runs PyTorch's ONNX exporter in Python")?;
    let script = project_file("clients/python/lcrl_export_onnx.py")?;
    let work = tempfile::tempdir().context("a temporary folder for the TorchScript module")?;
    let torchscript = work.path().join("policy.pt");
    write_torchscript(prepared, &torchscript)?;
    let probes = work.path().join("probes.json");
    let probe_json = serde_json::json!({ "state_dim": prepared.state_dim, "states": prepared.probes });
    std::fs::write(&probes, probe_json.to_string()).with_context(|| format!("writing {}", probes.display()))?;
    let report_path = work.path().join("report.json");
    let partial = partial_of(out)?;
    let result = Command::new(&python)
        .arg(&script)
        .arg("--torchscript")
        .arg(&torchscript)
        .arg("--out")
        .arg(&partial)
        .arg("--probes")
        .arg(&probes)
        .arg("--report")
        .arg(&report_path)
        .output()
        .with_context(|| format!("starting {}", python.display()))?;
    if !result.status.success() {
        let _ = std::fs::remove_file(&partial);
        let stderr = String::from_utf8_lossy(&result.stderr);
        // The script's own message is its last line (a traceback's too).
        let last = stderr.lines().rev().find(|l| !l.trim().is_empty()).unwrap_or("no message");
        bail!(
            "{} {} failed ({}): {last}{}",
            python.display(),
            script.display(),
            result.status,
            if result.status.code() == Some(3) { "" } else { "; run `bash scripts/setup.sh` (it installs torch, onnx and onnxruntime into .venv), or set $LCRL_PYTHON" }
        );
    }
    let report = std::fs::read_to_string(&report_path)
        .with_context(|| format!("{} wrote no report", script.display()))
        .and_then(|text| serde_json::from_str::<Report>(&text).with_context(|| format!("reading {}'s report", script.display())));
    let report = match report {
        Ok(report) => report,
        Err(e) => {
            let _ = std::fs::remove_file(&partial);
            return Err(e);
        }
    };
    tracing::info!(opset = report.opset, torch = %report.torch, onnxruntime = %report.onnxruntime, "ONNX export");
    install(&partial, out, prepared, &report.actions)
}
