"""Numeric precision chosen by what the processor can do.

bf16 autocast pays only where the hardware has bf16 arithmetic: Intel AMX (``amx_bf16``) or
AVX512-BF16 (``avx512_bf16``) on a CPU, or a GPU that supports it. Elsewhere PyTorch emulates it
and it is far slower than fp32. Measured with ``benchmarks/bench_model.py`` (shipped ``tiny``
preset, batch 4, one 16-frame clip at 10 steps with text guidance):

    CPU                             train fp32 / bf16 (steps/s)   sample fp32 / bf16 (s/clip)
    Intel Xeon, AMX-BF16            1.19 / 1.79                   1.46 / 0.87
    AMD EPYC, AVX2 only             0.56 / 0.03                   4.05 / 13.8

So ``auto`` (the default of every command that runs a model) picks bf16 only where it is fast,
and forcing bf16 elsewhere warns with those numbers. Importing this module is cheap (no torch).

A oneDNN ISA cap in the environment (``ONEDNN_MAX_CPU_ISA=AVX2``, as the benchmarks' ``--cap-isa``
sets with ``ATEN_CPU_CAPABILITY`` and ``MKL_ENABLE_INSTRUCTIONS`` to run a CPU as an AVX2-only one)
takes native bf16 away from PyTorch's kernels, so ``auto`` then picks fp32 too.
"""

from __future__ import annotations

import os
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Iterable

from tesseract4d.configs import knob
from tesseract4d.errors import UserError

PRECISIONS = ("auto", "fp32", "bf16")
# /proc/cpuinfo flags of CPUs with native bf16 arithmetic.
FAST_BF16_CPU_FLAGS = ("amx_bf16", "avx512_bf16")
SLOW_BF16_WARNING = (
    "bf16 was forced on a CPU without AMX or AVX512-BF16; PyTorch emulates bf16 there, which was "
    "measured far slower than fp32 (AMD EPYC with AVX2: training 0.03 vs 0.56 steps/s, sampling "
    "13.8 vs 4.05 s per clip); use --precision auto or fp32"
)
CPUINFO = Path("/proc/cpuinfo")
# ONEDNN_MAX_CPU_ISA values that still allow native bf16 matmuls (any other cap removes them).
BF16_ISA_CAPS = ("ALL", "AVX512_CORE_BF16", "AVX512_CORE_FP16", "AVX512_CORE_AMX", "AVX512_CORE_AMX_FP16",
                 "AVX10_1_512", "AVX10_1_512_AMX", "AVX10_1_512_AMX_FP16", "AVX10_2_512", "AVX10_2_512_AMX_2")


@dataclass(frozen=True)
class Precision:
    """A resolved precision: ``name`` is "fp32" or "bf16"; ``reason`` says why it was chosen."""

    name: str
    reason: str

    @property
    def bf16(self) -> bool:
        return self.name == "bf16"

    @property
    def accelerate_mixed_precision(self) -> str:
        """The value of ``accelerate.Accelerator(mixed_precision=...)``."""
        return "bf16" if self.bf16 else "no"

    def describe(self) -> str:
        return f"precision: {self.name} ({self.reason})"


def _read_cpuinfo() -> str:
    try:
        return CPUINFO.read_text(errors="replace")
    except OSError:
        return ""


def cpu_flags(cpuinfo: str | None = None) -> frozenset[str]:
    """The instruction-set flags of the first CPU in ``cpuinfo`` (default: /proc/cpuinfo)."""
    text = _read_cpuinfo() if cpuinfo is None else cpuinfo
    for line in text.splitlines():
        key, _, value = line.partition(":")
        if key.strip() in ("flags", "Features"):
            return frozenset(value.split())
    return frozenset()


def cpu_model(cpuinfo: str | None = None) -> str:
    """The CPU's model name from ``cpuinfo`` (default: /proc/cpuinfo), or the platform's processor."""
    text = _read_cpuinfo() if cpuinfo is None else cpuinfo
    for line in text.splitlines():
        key, _, value = line.partition(":")
        if key.strip() == "model name" and value.strip():
            return value.strip()
    import platform

    return platform.processor() or platform.machine() or "unknown CPU"


def has_fast_bf16(flags: Iterable[str]) -> bool:
    """True when the CPU flags include native bf16 arithmetic (AMX-BF16 or AVX512-BF16)."""
    return any(f in set(flags) for f in FAST_BF16_CPU_FLAGS)


def isa_cap(environ: dict | None = None) -> str | None:
    """The oneDNN ISA cap of the environment (``ONEDNN_MAX_CPU_ISA``, or its older name
    ``DNNL_MAX_CPU_ISA``) when it takes native bf16 away, else None."""
    env = os.environ if environ is None else environ
    cap = (env.get("ONEDNN_MAX_CPU_ISA") or env.get("DNNL_MAX_CPU_ISA") or "").strip().upper()
    return cap if cap and cap not in BF16_ISA_CAPS else None


def cpu_isa(flags: Iterable[str] | None = None) -> str:
    """A short ISA summary for benchmark tables, e.g. "AVX512, avx512_bf16" or "AVX2"."""
    flags = cpu_flags() if flags is None else frozenset(flags)
    if "avx512f" in flags:
        base = "AVX512"
    elif "avx2" in flags:
        base = "AVX2"
    elif "asimd" in flags:
        base = "NEON"
    else:
        base = "baseline"
    extras = [f for f in ("amx_bf16", "avx512_bf16") if f in flags]
    cap = isa_cap()
    return ", ".join([base, *extras]) + (f"; capped to {cap} by ONEDNN_MAX_CPU_ISA" if cap else "")


def describe_cpu(cpuinfo: str | None = None) -> str:
    """"MODEL (ISA)" for the first line of every benchmark table."""
    text = _read_cpuinfo() if cpuinfo is None else cpuinfo
    return f"{cpu_model(text)} ({cpu_isa(cpu_flags(text))})"


def resolve_precision(requested: str = "auto", device: str = "cpu", cpuinfo: str | None = None,
                      warn: bool = True, environ: dict | None = None) -> Precision:
    """Turn ``auto|fp32|bf16`` into the precision to run with on ``device``.

    ``auto``: bf16 on a CPU with AMX-BF16/AVX512-BF16 or a CUDA device that supports bf16, else fp32.
    ``bf16`` forced on a CPU without native bf16 prints a warning with the measured slowdown.
    ``cpuinfo`` (the text of /proc/cpuinfo) and ``environ`` (for the ISA cap, :func:`isa_cap`) are
    for tests; by default the machine's own are read.
    """
    if requested not in PRECISIONS:
        raise UserError(f"unknown precision {requested!r}; choose one of: {', '.join(PRECISIONS)}")
    kind = str(device).split(":")[0]
    if kind == "cuda":
        import torch

        fast = bool(torch.cuda.is_available() and torch.cuda.is_bf16_supported())
        where = "the GPU supports bf16" if fast else "the GPU lacks bf16"
    elif kind == "cpu":
        flags = cpu_flags(cpuinfo)
        fast = has_fast_bf16(flags)
        native = [f for f in FAST_BF16_CPU_FLAGS if f in flags]
        where = f"the CPU has {native[0]}" if fast else "the CPU has no AMX or AVX512-BF16"
        cap = isa_cap(environ)
        if fast and cap:
            fast, where = False, f"the CPU has {native[0]}, but ONEDNN_MAX_CPU_ISA={cap} takes it away"
    else:
        fast, where = False, f"device {device!r}"
    if requested == "fp32":
        return Precision("fp32", "requested")
    if requested == "bf16":
        if kind == "cpu" and not fast and warn:
            print(f"warning: {SLOW_BF16_WARNING}", file=sys.stderr)
        return Precision("bf16", "requested" + ("" if fast else f"; {where}"))
    return Precision("bf16" if fast else "fp32", f"auto: {where}")


_announced: set[str] = set()


def announce(precision: Precision) -> None:
    """Print the chosen precision once per process (commands call this where the model starts)."""
    line = precision.describe()
    if line not in _announced:
        _announced.add(line)
        print(line, file=sys.stderr)


PRECISION_HELP = ("numeric precision: auto (default) = bf16 only where the CPU has AMX or AVX512-BF16 (or on a GPU "
                  "with bf16), else fp32; forcing bf16 elsewhere is much slower")


def precision_field():
    """The ``precision`` field of a config dataclass (auto|fp32|bf16), with its help."""
    return knob("auto", PRECISION_HELP, choices=PRECISIONS)
