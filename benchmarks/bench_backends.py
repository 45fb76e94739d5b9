"""Benchmark inference backends for the shipped model's transformer: eager PyTorch (fp32, and bf16
autocast where the CPU has native bf16) against ONNX Runtime and OpenVINO on the same exported graph.

One network pass at the sampler's guided batch (conditional + unconditional = 2 clips), with the
shipped checkpoint's weights, so the outputs can be compared: the table gives the median seconds per
pass, the seconds of the 10 passes a 10-step guided clip needs, and the largest absolute difference
from eager fp32 (model space, where values lie in [-1, 1]). The CPU model and ISA are printed first.

ONNX Runtime and OpenVINO are not dependencies of tesseract4d; install them to run this benchmark:

  .venv/bin/pip install -c scripts/constraints.txt onnx onnxscript onnxruntime openvino
  .venv/bin/python benchmarks/bench_backends.py [--checkpoint DIR] [--repeats 20] [--threads 2]
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path
from measure import median_seconds

SHIPPED = Path(__file__).resolve().parent.parent / "tesseract4d" / "checkpoints" / "tiny"
STEPS_PER_CLIP = 10


def _inputs(pipe, batch: int):
    """Guided-pass inputs of the pipeline's shapes: x_t, condition, text embeddings, time."""
    import torch

    from tesseract4d.model.codec import make_condition

    g = torch.Generator().manual_seed(0)
    p = pipe.preset
    first = pipe.codec.encode(torch.rand(batch, 1, 7, p.height, p.width, generator=g) * 2 - 1)
    nt = pipe.codec.num_latent_frames(p.num_frames)
    cond = make_condition(first, nt, p.condition)
    x_t = torch.randn((batch, nt, *first.shape[2:]), generator=g)
    text = pipe.text_encoder.encode(["push the red cube to the left"] * batch)
    t = torch.full((batch,), 0.5)
    return x_t, cond, text, t


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--checkpoint", type=Path, default=SHIPPED, help="inference checkpoint (default: the shipped tiny)")
    parser.add_argument("--repeats", type=int, default=20, help="timed passes per backend (median reported)")
    parser.add_argument("--threads", type=int, default=2, help="intra-op threads for every backend")
    args = parser.parse_args(argv)

    from tesseract4d import runtime

    runtime.configure()
    import numpy as np
    import torch

    from tesseract4d.model.predict import load_pipeline
    from tesseract4d.precision import describe_cpu, resolve_precision

    torch.set_num_threads(args.threads)
    pipe = load_pipeline(args.checkpoint, precision="fp32")
    model = pipe.transformer.eval()
    inputs = _inputs(pipe, batch=2)
    names = ["x_t", "condition", "text", "t"]
    with torch.no_grad():
        reference = model(*inputs).float().numpy()

    rows = []

    def add(backend: str, seconds: float, out: np.ndarray | None, note: str = "") -> None:
        diff = float(np.abs(out - reference).max()) if out is not None else float("nan")
        rows.append((backend, seconds, diff, note))
        print(f"  measured {backend}: {seconds * 1000:.1f} ms/pass, max |diff| {diff:.2e} {note}", flush=True)

    with torch.no_grad():
        add("eager fp32", median_seconds(lambda: model(*inputs), args.repeats, warmup=True), reference)
        auto = resolve_precision("auto", "cpu", warn=False)
        if auto.bf16:
            def bf16_pass():
                with torch.autocast("cpu", dtype=torch.bfloat16):
                    return model(*inputs).float()

            add("eager bf16 autocast", median_seconds(bf16_pass, args.repeats, warmup=True), bf16_pass().numpy())
        else:
            rows.append(("eager bf16 autocast", float("nan"), float("nan"), "skipped: no native bf16 on this CPU"))

    with tempfile.TemporaryDirectory() as tmp:
        onnx_path = Path(tmp) / "transformer.onnx"
        t0 = time.perf_counter()
        torch.onnx.export(model, inputs, str(onnx_path), input_names=names, output_names=["x0_hat"], dynamo=True,
                          external_data=False)
        export_s = time.perf_counter() - t0
        feeds = {n: v.numpy() for n, v in zip(names, inputs)}
        try:
            import onnxruntime as ort

            opts = ort.SessionOptions()
            opts.intra_op_num_threads = args.threads
            opts.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
            sess = ort.InferenceSession(str(onnx_path), opts, providers=["CPUExecutionProvider"])
            run = lambda: sess.run(None, feeds)[0]  # noqa: E731
            add(f"ONNX Runtime {ort.__version__}", median_seconds(run, args.repeats, warmup=True), run(),
                f"(export {export_s:.0f} s)")
        except ImportError:
            rows.append(("ONNX Runtime", float("nan"), float("nan"), "not installed"))
        try:
            import openvino as ov

            core = ov.Core()
            for hint in ("f32", "bf16"):
                if hint == "bf16" and not auto.bf16:
                    continue
                compiled = core.compile_model(str(onnx_path), "CPU", {
                    "INFERENCE_NUM_THREADS": args.threads, "INFERENCE_PRECISION_HINT": hint,
                    "PERFORMANCE_HINT": "LATENCY"})
                request = compiled.create_infer_request()
                run = lambda: request.infer(feeds)[compiled.output(0)]  # noqa: E731
                add(f"OpenVINO {ov.__version__.split('-')[0]} {hint}", median_seconds(run, args.repeats, warmup=True), np.asarray(run()))
        except ImportError:
            rows.append(("OpenVINO", float("nan"), float("nan"), "not installed"))

    print()
    print(f"CPU: {describe_cpu()}; {args.threads} threads; checkpoint {args.checkpoint}")
    print(f"one guided pass = batch 2 (conditional + unconditional); a {STEPS_PER_CLIP}-step clip = {STEPS_PER_CLIP} passes")
    header = f"{'backend':<28} {'ms/pass':>8} {'s per clip (passes)':>20} {'max |diff| vs fp32':>19}  note"
    print(header)
    print("-" * len(header))
    for backend, s, diff, note in rows:
        print(f"{backend:<28} {s * 1000:>8.1f} {s * STEPS_PER_CLIP:>20.3f} {diff:>19.2e}  {note}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
