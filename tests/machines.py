"""Other x86-64 machines, emulated on this one: for each instruction-set level, the environment
that makes the numeric libraries take the code paths a CPU of that level would give them.

Every library that picks kernels by the CPU has a switch for it: numpy's dispatch
(`NPY_DISABLE_CPU_FEATURES`), glibc's ifuncs, libm's FMA variants among them (`GLIBC_TUNABLES`),
OpenBLAS's core type, MKL's and oneDNN's instruction sets, torch's ATen capability and Arrow's
SIMD level. A level above this machine's own cannot be emulated, so `switchable_levels` lists the
ones at or below it.
"""

from __future__ import annotations

LEVELS: dict[str, dict[str, str]] = {
    "x86-64-v2": {  # SSE4.2, no AVX: numpy's baseline
        "NPY_DISABLE_CPU_FEATURES": "X86_V3 X86_V4 AVX512_ICL AVX512_SPR",
        "GLIBC_TUNABLES": "glibc.cpu.hwcaps=-AVX,-AVX2,-FMA,-FMA4,-AVX512F,-BMI1,-BMI2,-F16C,-LZCNT,-MOVBE",
        "OPENBLAS_CORETYPE": "Nehalem",
        "MKL_ENABLE_INSTRUCTIONS": "SSE4_2",
        "ONEDNN_MAX_CPU_ISA": "SSE41",
        "ATEN_CPU_CAPABILITY": "default",
        "ARROW_USER_SIMD_LEVEL": "SSE4_2",
    },
    "x86-64-v3": {  # AVX2 and FMA
        "NPY_DISABLE_CPU_FEATURES": "X86_V4 AVX512_ICL AVX512_SPR",
        "GLIBC_TUNABLES": "glibc.cpu.hwcaps=-AVX512F,-AVX512DQ,-AVX512BW,-AVX512VL,-AVX512CD",
        "OPENBLAS_CORETYPE": "Haswell",
        "MKL_ENABLE_INSTRUCTIONS": "AVX2",
        "ONEDNN_MAX_CPU_ISA": "AVX2",
        "ATEN_CPU_CAPABILITY": "avx2",
        "ARROW_USER_SIMD_LEVEL": "AVX2",
    },
    "x86-64-v4": {  # AVX-512
        "NPY_DISABLE_CPU_FEATURES": "AVX512_SPR",
        "GLIBC_TUNABLES": "",
        "OPENBLAS_CORETYPE": "SkylakeX",
        "MKL_ENABLE_INSTRUCTIONS": "AVX512",
        "ONEDNN_MAX_CPU_ISA": "AVX512_CORE",
        "ATEN_CPU_CAPABILITY": "avx512",
        "ARROW_USER_SIMD_LEVEL": "AVX512",
    },
}


def switchable_levels() -> list[str]:
    """The levels this machine can emulate: numpy finds the level's features and torch the matching
    ATen capability (x86-64-v2 always: numpy needs it)."""
    import torch
    from numpy._core._multiarray_umath import __cpu_features__

    capability = torch.backends.cpu.get_cpu_capability()  # "DEFAULT", "AVX2", "AVX512", ...
    out = ["x86-64-v2"]
    if __cpu_features__.get("X86_V3") and capability != "DEFAULT":
        out.append("x86-64-v3")
    if __cpu_features__.get("X86_V4") and capability.startswith("AVX512"):
        out.append("x86-64-v4")
    return out
