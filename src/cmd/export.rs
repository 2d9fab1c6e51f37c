//! `lcrl export`: a trained policy as one TorchScript (or ONNX) file with
//! policy.json beside it, for a robot controller that loads it without
//! lcrl (src/export/, docs/export.md).

use std::path::PathBuf;

use lcrl::export::{export, Format, Request};

/// Write a trained policy as one file a controller loads with libtorch or
/// ONNX Runtime: raw state in, applied action out.
#[derive(Debug, clap::Args)]
pub struct ExportArgs {
    /// The run directory (`lcrl train --run-dir`, `lcrl run`'s runs/<preset>),
    /// or a policy folder (RUN/selected, RUN/checkpoints/epNNNNNN).
    #[arg(value_name = "RUN_DIR")]
    pub run: PathBuf,
    /// The file to write (default: RUN_DIR/policy.pt, or RUN_DIR/policy.onnx
    /// with --format onnx, beside the run it comes from); policy.json is
    /// written beside it, same name.
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// torchscript (libtorch, Python or C++) or onnx (ONNX Runtime; made
    /// from the TorchScript module by PyTorch's exporter in the project's
    /// .venv Python, or $LCRL_PYTHON).
    #[arg(long, value_enum, default_value_t = Format::Torchscript)]
    pub format: Format,
    /// Another policy than the run's selected one (RUN/selected, or its
    /// newest checkpoint when the run has none): a checkpoint name
    /// (ep000900, under RUN/checkpoints), `newest`, or a folder.
    #[arg(long, value_name = "epNNNNNN|newest|DIR")]
    pub checkpoint: Option<String>,
    /// The environment, where the name the policy was trained on no longer
    /// builds it (a TOML file moved, a served environment's new address);
    /// its normalization and action box go into the file.
    #[arg(long)]
    pub env: Option<String>,
}

pub fn run(args: &ExportArgs) -> anyhow::Result<()> {
    // By default beside the run it comes from, never the working folder.
    let out = args.out.clone().unwrap_or_else(|| args.run.join(if args.format == Format::Onnx { "policy.onnx" } else { "policy.pt" }));
    let request = Request { run: args.run.clone(), checkpoint: args.checkpoint.clone(), env: args.env.clone(), out, format: args.format };
    let outcome = export(&request)?;
    let source = &outcome.manifest.source;
    let m = &outcome.manifest;
    // What the policy is: the training behind it, and the version a
    // distributed learner served it as (lcrl train's runs have none).
    let mut what = format!("after episode {}", source.episode);
    if let Some(updates) = source.updates {
        what.push_str(&format!(", {updates} actor updates"));
    }
    if source.policy_version > 0 {
        what.push_str(&format!(", served as policy version {}", source.policy_version));
    }
    println!(
        "{:?}/{:?} policy on {} ({} states -> {} actions), {}: {} ({what})",
        m.algo,
        m.graph.connection,
        m.env,
        m.state.len(),
        m.action.len(),
        source.chosen,
        source.checkpoint.display()
    );
    println!(
        "checked on {} states against the served policy: largest action difference {:.1e}",
        outcome.entry.checked_states, outcome.entry.max_abs_difference
    );
    println!("wrote {} ({} bytes) and {}", outcome.file.display(), outcome.entry.bytes, outcome.manifest_path.display());
    Ok(())
}
