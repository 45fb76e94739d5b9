"""What every benchmark script shares: timing a call, the machine line and printing the result table.

Benchmarks run as scripts (`.venv/bin/python benchmarks/NAME.py`), so they import this module by
its bare name.
"""

from __future__ import annotations

import os
import statistics
import sys
import time
from pathlib import Path
from typing import Callable, Sequence


def median_seconds(fn: Callable[[], object], repeats: int, warmup: bool = False) -> float:
    """Median wall time of ``repeats`` calls of ``fn`` (after one untimed call when ``warmup``)."""
    if warmup:
        fn()
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def machine_line(*details: object) -> str:
    """The line that heads every benchmark's table: the CPU and its ISA, the threads torch uses (once
    torch is loaded), OMP_WAIT_POLICY and the load average at the time, then the benchmark's own details.
    A timing without the load beside it cannot be compared with another."""
    from tesseract4d.precision import describe_cpu  # no torch: safe before an ISA cap

    parts = [f"CPU: {describe_cpu()}", f"{os.cpu_count()} logical CPUs"]
    torch = sys.modules.get("torch")
    if torch is not None:
        parts.append(f"torch {torch.__version__}, {torch.get_num_threads()} threads")
    parts += [f"OMP_WAIT_POLICY={os.environ.get('OMP_WAIT_POLICY')}", f"load average {os.getloadavg()[0]:.1f}"]
    return "; ".join(parts + [str(d) for d in details])


def print_table(header: Sequence[str], rows: Sequence[Sequence[object]]) -> None:
    """Columns padded to their widest cell, a dashed rule under the header."""
    widths = [max(len(str(x)) for x in col) for col in zip(header, *rows)]
    for row in (header, tuple("-" * w for w in widths), *rows):
        print("  ".join(str(x).ljust(w) for x, w in zip(row, widths)))


# Environments that run this CPU as one of a lower ISA: oneDNN, ATen's vectorised kernels and MKL
# are capped, so bf16 matmuls lose their native path (tesseract4d.precision.isa_cap) as on a CPU
# without AVX512-BF16/AMX. An emulation on the same cores: a stand-in for, not a measurement of,
# another processor.
ISA_CAPS = {"avx2": {"ONEDNN_MAX_CPU_ISA": "AVX2", "ATEN_CPU_CAPABILITY": "avx2", "MKL_ENABLE_INSTRUCTIONS": "AVX2"}}


def add_isa_cap_argument(parser) -> None:
    parser.add_argument("--cap-isa", choices=sorted(ISA_CAPS),
                        help="run as an AVX2-only CPU (oneDNN, ATen and MKL capped to AVX2; the table says so)")


def apply_isa_cap(cap: str | None) -> None:
    """Re-run this script with the cap's environment, which must be set before torch loads."""
    if cap is None:
        return
    env = ISA_CAPS[cap]
    if all(os.environ.get(k) == v for k, v in env.items()):
        return
    if "torch" in sys.modules:
        raise RuntimeError("apply_isa_cap must run before torch is imported")
    os.execve(sys.executable, [sys.executable, *sys.argv], {**os.environ, **env})


def add_pipeline_arguments(parser) -> None:
    """The options of a benchmark that samples a checkpoint: which one, its steps, precision and ISA cap."""
    from tesseract4d.model.checkpoint import SHIPPED_CHECKPOINT  # no torch: the ISA cap is applied later

    parser.add_argument("--checkpoint", type=Path, default=SHIPPED_CHECKPOINT,
                        help="checkpoint folder (default: the shipped default)")
    parser.add_argument("--steps", type=int, help="sampler steps (default: the checkpoint preset's)")
    parser.add_argument("--precision", default="auto", choices=("auto", "fp32", "bf16"))
    add_isa_cap_argument(parser)


def load_benchmark_pipeline(args):
    """Apply the ISA cap, configure the runtime, load ``args.checkpoint`` and print the machine line."""
    apply_isa_cap(args.cap_isa)
    from tesseract4d import runtime

    runtime.configure()
    from tesseract4d.model.predict import load_pipeline
    from tesseract4d.precision import resolve_precision

    pipe = load_pipeline(args.checkpoint, precision=args.precision)
    print(machine_line(f"precision {resolve_precision(args.precision, 'cpu', warn=False).name}"))
    return pipe
