"""Run one stage on pinned numeric code paths: `python -m pipeline.execution.run STAGE ARGS...`.

dvc.yaml runs every stage this way, so that the pipeline writes the same bytes, and `dvc.lock`
the same hashes, on any x86-64 machine. numpy, glibc's libm, OpenBLAS, MKL, oneDNN and torch pick
their kernels at run time by the CPU they find (SSE, AVX2 and FMA, AVX-512), and those kernels
round differently in the last bit; training then turns a last-bit difference in its inputs into
different weights. This launcher sets the environment that makes each of them take the code path
every supported machine has (x86-64-v2, numpy's baseline), with one thread each (a parallel
reduction's order depends on the thread count), then replaces itself with
`python -m pipeline.stages.STAGE ARGS...`, or runs it in a warm interpreter that loaded those
libraries under the same environment (`pipeline.execution.preload`). The environment is read when those
libraries load, which is why it is set here, before the stage's interpreter starts, and not from
inside it.
docs/reproducibility.md says what is guaranteed.
"""

from __future__ import annotations

import os
import sys
from collections.abc import Iterable, Mapping
from pathlib import Path

from pipeline.execution import preload

# numpy 2.4's run-time dispatch targets above its x86-64-v2 baseline
# (`numpy._core._multiarray_umath.__cpu_dispatch__`; tests/test_run.py checks the list is complete).
NUMPY_DISPATCH = ("X86_V3", "X86_V4", "AVX512_ICL", "AVX512_SPR")
# CPU features above x86-64-v2 that glibc's ifunc resolvers select on: libm's exp, log, pow, sin
# and cos have FMA variants that round differently.
GLIBC_ABOVE_V2 = ("AVX", "AVX2", "FMA", "FMA4", "AVX512F", "AVX512DQ", "AVX512BW", "AVX512VL", "AVX512CD")
PINNED = {
    "ATEN_CPU_CAPABILITY": "default",  # torch's own kernels: the build without AVX2/AVX-512
    "MKL_CBWR": "COMPATIBLE",  # MKL (torch's BLAS): its reproducible, CPU-independent code path
    "ONEDNN_MAX_CPU_ISA": "SSE41",  # oneDNN, should torch reach it (training turns it off too)
    "OPENBLAS_CORETYPE": "Nehalem",  # numpy's and scipy's OpenBLAS: the x86-64-v2 kernels
    "OPENBLAS_NUM_THREADS": "1",
    "MKL_NUM_THREADS": "1",
    "OMP_NUM_THREADS": "1",
}
STAGES = Path(__file__).parents[1] / "stages"


def _union(existing: Iterable[str], ours: Iterable[str]) -> list[str]:
    """`existing`'s items, then ours, each once (a machine's own mask stays in force)."""
    return list(dict.fromkeys([*(i for i in existing if i), *ours]))


def _glibc_tunables(existing: str) -> str:
    """GLIBC_TUNABLES (`name=value:name=value`) with our features masked in `glibc.cpu.hwcaps`."""
    tunables = [t for t in existing.split(":") if t]
    hwcaps = [t for t in tunables if t.startswith("glibc.cpu.hwcaps=")]
    others = [t for t in tunables if not t.startswith("glibc.cpu.hwcaps=")]
    theirs = (mask for t in hwcaps for mask in t.split("=", 1)[1].split(","))
    masks = _union(theirs, (f"-{f}" for f in GLIBC_ABOVE_V2))
    return ":".join([*others, f"glibc.cpu.hwcaps={','.join(masks)}"])


def pinned_env(env: Mapping[str, str]) -> dict[str, str]:
    """`env` with the numeric libraries pinned to x86-64-v2 code paths and one thread."""
    out = {k: v for k, v in env.items() if k != "NPY_ENABLE_CPU_FEATURES"}  # it would contradict ours
    disabled = env.get("NPY_DISABLE_CPU_FEATURES", "").replace(",", " ").split()  # numpy takes either
    out["NPY_DISABLE_CPU_FEATURES"] = " ".join(_union(disabled, NUMPY_DISPATCH))
    out["GLIBC_TUNABLES"] = _glibc_tunables(env.get("GLIBC_TUNABLES", ""))
    out.update(PINNED)
    return out


def main(argv: list[str]) -> None:
    if not argv or not (STAGES / f"{argv[0]}.py").is_file() or argv[0].startswith("_"):
        known = ", ".join(sorted(p.stem for p in STAGES.glob("[!_]*.py")))
        sys.exit(f"usage: python -m pipeline.execution.run STAGE [ARGS...]; STAGE is one of: {known}")
    stage, *args = argv
    env = pinned_env(os.environ)
    module = [f"pipeline.stages.{stage}", *args]
    sys.stdout.flush()
    status = preload.run_stage(module, env)  # in a warm interpreter, when one is up
    if status is not None:
        sys.exit(status)
    os.execve(sys.executable, [sys.executable, "-m", *module], env)


if __name__ == "__main__":
    main(sys.argv[1:])
