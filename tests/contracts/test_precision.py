"""Precision chosen by CPU capability (tesseract4d/precision.py)."""

from __future__ import annotations

import pytest

from tesseract4d.errors import UserError
from tesseract4d.precision import cpu_flags, cpu_isa, cpu_model, describe_cpu, has_fast_bf16, resolve_precision


def _cpuinfo(model: str, flags: str) -> str:
    # Two processors, as /proc/cpuinfo lists them; only the first one's fields are read.
    block = f"processor\t: 0\nvendor_id\t: x\nmodel name\t: {model}\nflags\t\t: {flags}\n\n"
    return block + block.replace("processor\t: 0", "processor\t: 1")


XEON_AMX = _cpuinfo("Intel(R) Xeon(R) Platinum 8480C", "fpu sse2 avx2 avx512f avx512_bf16 amx_bf16 amx_tile amx_int8")
EPYC_AVX2 = _cpuinfo("AMD EPYC 7B12", "fpu sse2 avx avx2 fma")
EPYC_AVX512_BF16 = _cpuinfo("AMD EPYC 9B14", "fpu sse2 avx2 avx512f avx512bw avx512_bf16 avx512_vnni")
OLD_XEON_AVX512 = _cpuinfo("Intel(R) Xeon(R) Gold 6148", "fpu sse2 avx2 avx512f avx512bw avx512_vnni")


@pytest.mark.parametrize("cpuinfo, expected", [
    (XEON_AMX, "bf16"), (EPYC_AVX512_BF16, "bf16"), (EPYC_AVX2, "fp32"), (OLD_XEON_AVX512, "fp32"), ("", "fp32"),
])
def test_auto_picks_bf16_only_with_native_bf16(cpuinfo, expected):
    chosen = resolve_precision("auto", "cpu", cpuinfo=cpuinfo)
    assert chosen.name == expected
    assert chosen.bf16 == (expected == "bf16")
    assert chosen.accelerate_mixed_precision == ("bf16" if expected == "bf16" else "no")
    assert chosen.reason.startswith("auto: ")


@pytest.mark.parametrize("environ, expected", [
    ({}, "bf16"), ({"ONEDNN_MAX_CPU_ISA": "AVX2"}, "fp32"), ({"ONEDNN_MAX_CPU_ISA": "avx512_core"}, "fp32"),
    ({"DNNL_MAX_CPU_ISA": "AVX2"}, "fp32"), ({"ONEDNN_MAX_CPU_ISA": "AVX512_CORE_BF16"}, "bf16"),
    ({"ONEDNN_MAX_CPU_ISA": "ALL"}, "bf16"), ({"ONEDNN_MAX_CPU_ISA": "AVX512_CORE_AMX"}, "bf16"),
])
def test_a_onednn_isa_cap_without_bf16_makes_auto_pick_fp32(environ, expected):
    chosen = resolve_precision("auto", "cpu", cpuinfo=EPYC_AVX512_BF16, environ=environ)
    assert chosen.name == expected
    if expected == "fp32":
        assert "ONEDNN_MAX_CPU_ISA" in chosen.reason


def test_flag_parsing_reads_the_first_cpu_only():
    assert has_fast_bf16(cpu_flags(XEON_AMX))
    assert not has_fast_bf16(cpu_flags(EPYC_AVX2))
    assert "avx2" in cpu_flags(EPYC_AVX2)
    assert cpu_model(EPYC_AVX2) == "AMD EPYC 7B12"
    assert cpu_isa(cpu_flags(EPYC_AVX2)) == "AVX2"
    assert cpu_isa(cpu_flags(XEON_AMX)) == "AVX512, amx_bf16, avx512_bf16"
    assert describe_cpu(EPYC_AVX512_BF16) == "AMD EPYC 9B14 (AVX512, avx512_bf16)"


def test_forcing_bf16_without_native_support_warns_with_the_measured_slowdown(capsys):
    chosen = resolve_precision("bf16", "cpu", cpuinfo=EPYC_AVX2)
    assert chosen.bf16
    err = capsys.readouterr().err
    assert "warning" in err and "AVX512-BF16" in err and "0.03 vs 0.56 steps/s" in err
    resolve_precision("bf16", "cpu", cpuinfo=XEON_AMX)
    assert capsys.readouterr().err == ""


def test_fp32_is_always_fp32_and_unknown_names_are_refused():
    assert resolve_precision("fp32", "cpu", cpuinfo=XEON_AMX).name == "fp32"
    with pytest.raises(UserError, match="auto, fp32, bf16"):
        resolve_precision("fp16", "cpu", cpuinfo=XEON_AMX)


@pytest.mark.parametrize("command", ["train", "train-autoencoder", "distill", "predict", "evaluate", "demo", "view",
                                     "rollout"])
def test_every_model_command_offers_precision(command, capsys):
    """Precision is a config option of every command that runs a model: `--set precision=...`, listed with
    its help by `--set list`, a value outside auto|fp32|bf16 refused at parse time."""
    from tesseract4d.cli import main

    with pytest.raises(SystemExit) as exit_info:
        main([command, "--set", "list"])
    assert exit_info.value.code == 0
    out = capsys.readouterr().out
    assert "precision = 'auto'" in out and "AVX512-BF16" in out
    with pytest.raises(SystemExit) as exit_info:
        main([command, "--set", "precision=fp16"])
    assert exit_info.value.code == 2 and "choose one of auto, fp32, bf16" in capsys.readouterr().err
