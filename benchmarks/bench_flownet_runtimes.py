"""FastFlowNet on the CPU: eager PyTorch against OpenVINO and ONNX Runtime (issue 49, item 3).

The shipped weights on one demo-size pair (1200 x 675 px, the network's input 1216 x 704),
one thread each, the three runtimes alternated so that the machine's drift hits them alike.
Prints each runtime's largest difference from eager (in the network's output units) and
the seconds a pair. Neither runtime is a dependency of flowmod: run it in a scratch venv
that has them (``pip install openvino onnxruntime onnx onnxscript``: they pull numpy>=2,
which the devkit refuses, so never into the project's .venv).

    PYTHONPATH=src <scratch-venv>/bin/python benchmarks/bench_flownet_runtimes.py
"""

from __future__ import annotations

import tempfile
import time
import warnings
from pathlib import Path

import numpy as np
import torch

from flowmod.flow import architectures as nets

WEIGHTS = Path(__file__).resolve().parents[1] / "weights" / "fastflownet_synth" / "weights.pt"


def main(reps: int = 4) -> None:
    """Time eager, OpenVINO and ONNX Runtime on the same inputs; print one line a rep."""
    import onnxruntime as ort
    import openvino as ov

    warnings.filterwarnings("ignore")
    torch.set_num_threads(1)
    model = nets.load_weights(nets.FastFlowNet(), nets.read_checkpoint(WEIGHTS), str(WEIGHTS))
    model.eval()
    rng = np.random.default_rng(0)
    img1 = torch.from_numpy(rng.integers(0, 255, (1, 3, 675, 1200)).astype(np.float32))
    x1, x2 = nets.fastflownet_inputs(img1, torch.roll(img1, 3, dims=3))
    with torch.inference_mode():
        ref = model(x1, x2).numpy()
    vino = ov.Core().compile_model(ov.convert_model(model, example_input=(x1, x2)), "CPU", {
        "INFERENCE_NUM_THREADS": "1", "INFERENCE_PRECISION_HINT": "f32"})
    onnx = Path(tempfile.mkdtemp()) / "fastflownet.onnx"
    torch.onnx.export(model, (x1, x2), str(onnx), dynamo=True, opset_version=18)
    so = ort.SessionOptions()
    so.intra_op_num_threads = so.inter_op_num_threads = 1
    sess = ort.InferenceSession(str(onnx), so, providers=["CPUExecutionProvider"])
    feed = dict(zip([i.name for i in sess.get_inputs()], (x1.numpy(), x2.numpy()), strict=True))
    runs = {"eager": lambda: model(x1, x2).numpy(),
            "openvino": lambda: vino((x1.numpy(), x2.numpy()))[0],
            "onnxruntime": lambda: sess.run(None, feed)[0]}
    with torch.inference_mode():
        for name, run in runs.items():
            print(f"{name}: largest difference from eager {np.abs(run() - ref).max():.1e}")
        for _ in range(reps):
            secs = {}
            for name, run in runs.items():
                t = time.perf_counter()
                run()
                secs[name] = time.perf_counter() - t
            print("  ".join(f"{k} {v:.3f} s" for k, v in secs.items()))


if __name__ == "__main__":
    main()
