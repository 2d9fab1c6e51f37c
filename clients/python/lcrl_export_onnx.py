"""Converts an lcrl policy's TorchScript module to ONNX (`lcrl export --format onnx`).

`lcrl export` writes the TorchScript module, then runs this script with
the project's Python (.venv, scripts/setup.sh): PyTorch's TorchScript-based
ONNX exporter converts it, with a dynamic batch axis, input `state`
[batch, m] float32 and output `action` [batch, n] float32; the ONNX checker
validates it; ONNX Runtime runs it on the probe states, and the actions go
back to `lcrl export`, which checks them against the served policy.

    python lcrl_export_onnx.py --torchscript policy.pt --out policy.onnx \
        --probes probes.json [--report report.json] [--opset 17]

Exit status 3: a package is missing (the message says which).
"""

import argparse
import json
import sys
import warnings

OPSET = 17


def need(module):
    try:
        return __import__(module)
    except ImportError as e:
        print(
            f"lcrl_export_onnx: {sys.executable} lacks {module} ({e}); "
            "run `bash scripts/setup.sh` (it installs torch, onnx and onnxruntime into .venv), "
            "or set $LCRL_PYTHON to a Python that has them",
            file=sys.stderr,
        )
        sys.exit(3)


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--torchscript", required=True, help="the module lcrl export wrote")
    parser.add_argument("--out", required=True, help="the ONNX file to write")
    parser.add_argument("--probes", required=True, help="JSON {state_dim, states (flat rows)}: the example and the check")
    parser.add_argument("--report", help="where to write the actions on the probes (JSON)")
    parser.add_argument("--opset", type=int, default=OPSET)
    args = parser.parse_args()

    torch = need("torch")
    onnx = need("onnx")
    ort = need("onnxruntime")
    import numpy as np

    module = torch.jit.load(args.torchscript, map_location="cpu")
    module.eval()
    with open(args.probes) as f:
        probes = json.load(f)
    m = int(probes["state_dim"])
    states = np.asarray(probes["states"], dtype=np.float32).reshape(-1, m)
    example = torch.from_numpy(states[: min(4, len(states))].copy())
    with warnings.catch_warnings():
        # The TorchScript exporter is the one that takes a ScriptModule;
        # its deprecation notice is not the user's concern here.
        warnings.simplefilter("ignore")
        torch.onnx.export(
            module,
            (example,),
            args.out,
            dynamo=False,
            input_names=["state"],
            output_names=["action"],
            dynamic_axes={"state": {0: "batch"}, "action": {0: "batch"}},
            opset_version=args.opset,
            do_constant_folding=True,
        )
    model = onnx.load(args.out)
    onnx.checker.check_model(model, full_check=True)
    session = ort.InferenceSession(args.out, providers=["CPUExecutionProvider"])
    (actions,) = session.run(["action"], {"state": states})
    if args.report:
        with open(args.report, "w") as f:
            json.dump(
                {
                    "actions": [float(v) for v in np.asarray(actions, dtype=np.float32).reshape(-1)],
                    "opset": args.opset,
                    "torch": torch.__version__,
                    "onnxruntime": ort.__version__,
                },
                f,
            )


if __name__ == "__main__":
    main()
