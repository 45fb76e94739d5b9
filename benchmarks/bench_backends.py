"""Benchmark inference backends for a checkpoint's transformer and autoencoder decoder: eager
PyTorch (fp32, and bf16 autocast where the CPU has native bf16) against ONNX Runtime and OpenVINO
on the same exported graphs.

Two parts, each with the checkpoint's weights so the outputs can be compared:
- transformer: one sampler pass at the sampler's batch (1 clip without guidance, 2 with text
  guidance: conditional + unconditional in one forward);
- decoder (latent checkpoints): the autoencoder decoding one clip's 16 latent frames to RGB-D-N.
The table gives the median milliseconds per call, the seconds a whole clip spends in that part (the
checkpoint's sampler steps × the pass, or one decode), and the mean and largest absolute difference
from eager fp32 (model space, values in [-1, 1]). The CPU model and ISA are printed first.

`--cap-isa avx2` runs as an AVX2-only CPU: eager PyTorch and OpenVINO's oneDNN kernels are capped;
ONNX Runtime's own kernels (MLAS) and OpenVINO's non-oneDNN kernels have no such switch in their
release builds, so their capped rows still use the CPU's full ISA (the table says so).

ONNX Runtime and OpenVINO are not dependencies of tesseract4d; install them to run this benchmark:

  .venv/bin/pip install -c scripts/constraints.txt onnx onnxscript onnxruntime openvino
  .venv/bin/python benchmarks/bench_backends.py [--checkpoint DIR] [--repeats 10] [--threads 2] [--cap-isa avx2]
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

from measure import add_isa_cap_argument, apply_isa_cap, machine_line, median_seconds

from tesseract4d.model.checkpoint import SHIPPED_CHECKPOINT  # no torch: the ISA cap is applied later


def _transformer_inputs(pipe, batch: int):
    """Sampler-pass inputs of the pipeline's shapes: x_t, condition, text embeddings, time."""
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
    return (x_t, cond, text, t), ["x_t", "condition", "text", "t"]


def _decoder_part(pipe):
    """The autoencoder's decode of one clip's latent frames, as a module with its input."""
    import torch

    autoencoder = pipe.codec.autoencoder

    class Decode(torch.nn.Module):
        def __init__(self):
            super().__init__()
            self.autoencoder = autoencoder

        def forward(self, z):
            return self.autoencoder.decode(z)

    p = pipe.preset
    nt = pipe.codec.num_latent_frames(p.num_frames)
    first = pipe.codec.encode(torch.zeros(1, 1, 7, p.height, p.width))
    z = torch.randn((nt, *first.shape[2:]), generator=torch.Generator().manual_seed(1))
    return Decode().eval(), (z,), ["z"]


def bench_part(name: str, module, inputs, names, calls_per_clip: int, args, bf16: bool, capped: bool) -> list:
    """Rows (part, backend, ms per call, s per clip, mean and max |diff| vs eager fp32, note) for one module."""
    import numpy as np
    import torch

    rows = []
    with torch.no_grad():
        reference = module(*inputs).float().numpy()

    def add(backend: str, seconds: float, out, note: str = "") -> None:
        err = np.abs(np.asarray(out, dtype=np.float32) - reference)
        rows.append((name, backend, seconds * 1000, seconds * calls_per_clip, float(err.mean()), float(err.max()), note))
        print(f"  {name} {backend}: {seconds * 1000:.1f} ms/call, |diff| mean {err.mean():.1e} max {err.max():.1e} {note}",
              flush=True)

    with torch.no_grad():
        add("eager fp32", median_seconds(lambda: module(*inputs), args.repeats, warmup=True), reference)
        if bf16:
            def bf16_call():
                with torch.autocast("cpu", dtype=torch.bfloat16):
                    return module(*inputs).float()

            add("eager bf16 autocast", median_seconds(bf16_call, args.repeats, warmup=True), bf16_call().numpy())

    with tempfile.TemporaryDirectory() as tmp:
        onnx_path = Path(tmp) / f"{name}.onnx"
        t0 = time.perf_counter()
        try:
            torch.onnx.export(module, inputs, str(onnx_path), input_names=names, output_names=["out"], dynamo=True,
                              external_data=False)
        except Exception as e:  # an export failure is a result of this benchmark, not a crash of it
            rows.append((name, "ONNX export", *[float("nan")] * 4, f"failed: {type(e).__name__}"))
            return rows
        export_note = f"(export {time.perf_counter() - t0:.0f} s)"
        feeds = {n: v.numpy() for n, v in zip(names, inputs)}
        try:
            import onnxruntime as ort

            opts = ort.SessionOptions()
            opts.intra_op_num_threads = args.threads
            opts.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
            sess = ort.InferenceSession(str(onnx_path), opts, providers=["CPUExecutionProvider"])
            run = lambda: sess.run(None, feeds)[0]  # noqa: E731
            note = export_note + (" full ISA: MLAS has no cap" if capped else "")
            add(f"ONNX Runtime {ort.__version__}", median_seconds(run, args.repeats, warmup=True), run(), note)
        except ImportError:
            rows.append((name, "ONNX Runtime", *[float("nan")] * 4, "not installed"))
        try:
            import openvino as ov

            core = ov.Core()
            for hint in ("f32", "bf16") if bf16 else ("f32",):
                compiled = core.compile_model(str(onnx_path), "CPU", {
                    "INFERENCE_NUM_THREADS": args.threads, "INFERENCE_PRECISION_HINT": hint,
                    "PERFORMANCE_HINT": "LATENCY"})
                request = compiled.create_infer_request()
                run = lambda: request.infer(feeds)[compiled.output(0)]  # noqa: E731
                note = " oneDNN capped, own kernels not" if capped else ""
                add(f"OpenVINO {ov.__version__.split('-')[0]} {hint}", median_seconds(run, args.repeats, warmup=True),
                    np.asarray(run()), note)
        except ImportError:
            rows.append((name, "OpenVINO", *[float("nan")] * 4, "not installed"))
    return rows


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--checkpoint", type=Path, default=SHIPPED_CHECKPOINT, help="inference checkpoint (default: the shipped default, v2-2step)")
    parser.add_argument("--repeats", type=int, default=10, help="timed calls per backend (median reported)")
    parser.add_argument("--threads", type=int, default=2, help="intra-op threads for every backend")
    add_isa_cap_argument(parser)
    args = parser.parse_args(argv)
    apply_isa_cap(args.cap_isa)

    from tesseract4d import runtime

    runtime.configure()
    import torch

    from tesseract4d.model.pipeline import guidance_passes
    from tesseract4d.model.predict import load_pipeline
    from tesseract4d.precision import resolve_precision

    torch.set_num_threads(args.threads)
    pipe = load_pipeline(args.checkpoint, precision="fp32")
    p = pipe.preset
    bf16 = resolve_precision("auto", "cpu", warn=False).bf16
    capped = args.cap_isa is not None
    batch = len(guidance_passes(p.text_guidance, p.image_guidance))
    inputs, names = _transformer_inputs(pipe, batch)
    rows = bench_part("transformer", pipe.transformer.eval(), inputs, names, p.num_steps, args, bf16, capped)
    if hasattr(pipe.codec, "autoencoder"):
        module, inputs, names = _decoder_part(pipe)
        rows += bench_part("decoder", module, inputs, names, 1, args, bf16, capped)

    print()
    print(machine_line(f"checkpoint {args.checkpoint}"))  # names an ISA cap
    print(f"transformer: one sampler pass = batch {batch}; a clip = {p.num_steps} passes. "
          f"decoder: {pipe.codec.num_latent_frames(p.num_frames)} latent frames, once per clip")
    header = f"{'part':<12} {'backend':<26} {'ms/call':>8} {'s per clip':>11} {'mean |diff|':>12} {'max |diff|':>11}  note"
    print(header)
    print("-" * len(header))
    for part, backend, ms, s, mean, big, note in rows:
        print(f"{part:<12} {backend:<26} {ms:>8.1f} {s:>11.3f} {mean:>12.1e} {big:>11.1e}  {note}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
