"""`needlecue repro`: `dvc repro` on every core, the stages that do not depend on each other side by side.

DVC runs one stage at a time. Its documented way to use more cores is several `dvc repro` processes,
each on stages that do not depend on each other (dvc.org, `repro`, "parallel stage execution"), and
DVC keeps that safe:
- each process lets go of the repository lock while its stage's command runs, and takes it back to
  record the stage in dvc.lock (waiting for it: `--wait-for-lock`);
- its read-write locks keep two processes off the same outputs.

This module decides what runs when. The plan is what `dvc repro` would consider: the stages out of
date and every stage downstream of them (`plan_of`). Each starts once the planned stages it depends
on have succeeded, at most `jobs` at a time, each through `dvc repro --single-item`. That call
still skips a stage whose dependencies turn out unchanged, as `dvc repro` does.

The outputs are the same bytes as a plain `dvc repro`: each stage runs as it would there, with its
own thread pinning and its own worker processes (docs/reproducibility.md). Only the wall time
changes: the 18 training stages of the defaults run one thread each.
"""

from __future__ import annotations

import contextlib
import os
import queue
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TextIO

TAIL_LINES = 40  # of a failed stage's output, kept for the error
STOP_GRACE_S = 30.0  # for a stage to stop after each signal of `_stop`
# DVC's advice after each `dvc repro`: said once at the end instead of after every stage
HINTS = (
    "To track the changes with git",
    "\tgit add ",
    "To enable auto staging",
    "\tdvc config core.autostage",
    "Use `dvc push`",
    "Updating lock file",
    "Generating lock file",
    "Data and pipelines are up to date.",
)


@dataclass(frozen=True)
class Plan:
    """The stages to run, in dvc.yaml's order, each with the planned stages it must wait for."""

    order: tuple[str, ...]
    waits_for: Mapping[str, frozenset[str]]

    def ready(self, succeeded: set[str], started: set[str]) -> list[str]:
        """The stages not started yet whose planned upstream stages have all succeeded, in order."""
        return [s for s in self.order if s not in started and self.waits_for[s] <= succeeded]


def plan_of(
    order: Sequence[str],
    depends_on: Mapping[str, Iterable[str]],
    changed: Iterable[str],
    targets: Iterable[str] = (),
) -> Plan:
    """What `dvc repro [targets]` considers: of the targets and their upstream stages (every stage
    without targets), those out of date (`changed`) and everything downstream of them."""
    deps = {s: set(depends_on.get(s, ())) for s in order}
    unknown = sorted(set(targets) - set(order))
    if unknown:
        raise ValueError(f"no stage named {', '.join(unknown)} in dvc.yaml; stages: {', '.join(order)}")
    scope = _closure(targets, deps) if targets else set(order)
    below = {s: set() for s in order}  # the stages that depend on s
    for s, ups in deps.items():
        for up in ups:
            below.setdefault(up, set()).add(s)
    planned = _closure((s for s in changed if s in scope), below) & scope
    chosen = tuple(s for s in order if s in planned)
    return Plan(chosen, {s: frozenset(deps[s] & planned) for s in chosen})


def _closure(start: Iterable[str], edges: Mapping[str, set[str]]) -> set[str]:
    """`start` and everything reachable from it along `edges`."""
    seen, todo = set(), list(start)
    while todo:
        s = todo.pop()
        if s not in seen:
            seen.add(s)
            todo.extend(edges.get(s, ()))
    return seen


def dvc_plan(root: Path, targets: Sequence[str] = ()) -> Plan:
    """The plan of the DVC project at `root`: its stages, their dependencies, what is out of date."""
    from dvc.repo import Repo

    with Repo(str(root)) as repo:
        order, depends_on, name = _graph(repo, root)
        changed = {name[s] for s in repo.status()}  # {stage: what changed}, the stages out of date only
    return plan_of(order, depends_on, changed, targets)


def dvc_graph(root: Path) -> tuple[list[str], dict[str, set[str]]]:
    """(the stages of the DVC project at `root` in dvc.yaml's order, {stage: the stages it depends on})."""
    from dvc.repo import Repo

    with Repo(str(root)) as repo:
        return _graph(repo, root)[:2]


def _graph(repo: Any, root: Path) -> tuple[list[str], dict[str, set[str]], dict[str, str]]:
    """(stages in order, their dependencies, {DVC's address: our name}) from DVC's stage graph: its
    internal `index.graph` (no public API gives it), checked against `dvc dag` by tests/test_repro.py
    on the DVC that requirements.lock pins."""
    # DVC names a stage relative to this process's folder: name it as `dvc repro` in root would
    name = {stage.addressing: _name(stage, root) for stage in repo.index.stages}
    order = list(name.values())
    depends_on: dict[str, set[str]] = {s: set() for s in order}
    for stage, upstream in repo.index.graph.edges:  # DVC's edges point at what a stage depends on
        depends_on[name[stage.addressing]].add(name[upstream.addressing])
    return order, depends_on, name


def _name(stage: Any, root: Path) -> str:
    """A stage's name as `dvc repro` in `root` takes it: `name` in root's dvc.yaml, `file:name` in
    another dvc.yaml, and a `.dvc` file's path for the data it tracks (`dvc add`: DVC verifies it)."""
    dvcfile = Path(stage.dvcfile.path).resolve()
    name = getattr(stage, "name", None)  # only dvc.yaml's stages have one
    if name is None:
        return os.path.relpath(dvcfile, root)
    if dvcfile == root.resolve() / "dvc.yaml":
        return name
    return f"{os.path.relpath(dvcfile, root)}:{name}"


@dataclass
class Outcome:
    """How a parallel reproduction ended."""

    code: int  # 0, or 1 when a stage failed
    ran: list[str] = field(default_factory=list)  # the stages whose command ran, as they finished
    spans: dict[str, tuple[float, float]] = field(default_factory=dict)  # each started stage's start, end (s)
    failed: list[str] = field(default_factory=list)
    tail: list[str] = field(default_factory=list)  # the first failed stage's last lines of output


@dataclass
class _Running:
    stage: str
    proc: subprocess.Popen[str]
    started: float
    ran: bool = False
    note: str = " (unchanged)"  # what DVC did instead of running it
    tail: list[str] = field(default_factory=list)


def reproduce(
    root: Path,
    plan: Plan,
    jobs: int,
    out: TextIO | None = None,
    env: Mapping[str, str] | None = None,
) -> Outcome:
    """Run `plan` in `root`, at most `jobs` stages at a time; each stage's output lines go to `out`
    (stdout by default) prefixed with its name. After a failure no new stage starts, the running
    ones finish, and the outcome names the failure. Ctrl-C or SIGTERM stops the running stages
    (`_stop`), then goes on as it would have."""
    if jobs < 1:
        raise ValueError(f"jobs must be at least 1, got {jobs}")
    out = out or sys.stdout
    width = max((len(s) for s in plan.order), default=0)
    write_lock = threading.Lock()
    finished: queue.Queue[_Running] = queue.Queue()
    base = dict(os.environ if env is None else env)
    # the stages call `python`: this interpreter's, as `dvc repro` run from this environment would
    base["PATH"] = f"{Path(sys.executable).parent}{os.pathsep}{base.get('PATH', '')}"

    def show(stage: str, line: str) -> None:
        with write_lock:
            out.write(f"{stage:<{width}} | {line}\n")
            out.flush()

    def follow(run: _Running) -> None:
        assert run.proc.stdout is not None
        try:
            for raw in run.proc.stdout:
                line = raw.rstrip("\n")
                run.tail = [*run.tail[-(TAIL_LINES - 1) :], line]
                if line.startswith(f"Running stage '{run.stage}'"):
                    run.ran, run.note = True, ""
                elif line.startswith(f"Stage '{run.stage}' is cached"):
                    run.note = " (from the run cache)"
                elif line.startswith("Verifying data sources in stage"):
                    run.note = " (data verified)"
                if line.strip() and not line.startswith(HINTS):
                    with contextlib.suppress(OSError, ValueError):  # our stdout gone: the stage goes on
                        show(run.stage, line)
        finally:  # whatever happened to the output, the loop hears of the stage's end
            run.proc.wait()
            finished.put(run)

    outcome = Outcome(code=0)
    t0 = time.perf_counter()
    # SIGTERM (a scheduler's stop, `timeout`) stops the stages as Ctrl-C does; only the main thread may
    main = threading.current_thread() is threading.main_thread()
    previous = signal.signal(signal.SIGTERM, _terminated) if main else None
    running: dict[str, _Running] = {}
    started: set[str] = set()
    succeeded: set[str] = set()
    try:
        while True:
            if not outcome.failed:
                for stage in plan.ready(succeeded, started)[: jobs - len(running)]:
                    started.add(stage)
                    running[stage] = _start(root, stage, base, follow)
            if not running:
                break
            run = finished.get()
            del running[run.stage]
            start, end = run.started - t0, time.perf_counter() - t0
            outcome.spans[run.stage] = (round(start, 1), round(end, 1))
            if run.proc.returncode == 0:
                succeeded.add(run.stage)
                if run.ran:
                    outcome.ran.append(run.stage)
                show(run.stage, f"done in {end - start:.1f} s{run.note} (from {start:.1f} to {end:.1f} s)")
            else:
                outcome.code = 1
                if not outcome.failed:
                    outcome.tail = run.tail
                outcome.failed.append(run.stage)
                show(run.stage, f"FAILED (exit {run.proc.returncode}); no new stage starts")
    except BaseException:  # Ctrl-C, SIGTERM or a crash here: the stages running stop too
        _stop(list(running.values()))
        raise
    finally:
        if main:
            signal.signal(signal.SIGTERM, previous if previous is not None else signal.SIG_DFL)
    return outcome


def _stop(runs: list[_Running]) -> None:
    """Stop each running stage as Ctrl-C in a terminal would (SIGINT to its process group: DVC
    ignores it while the stage's command runs and reports the command's end); SIGTERM, then SIGKILL,
    to a group still there after STOP_GRACE_S."""
    for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGKILL):
        alive = [run for run in runs if run.proc.poll() is None]
        for run in alive:
            with contextlib.suppress(ProcessLookupError):
                os.killpg(run.proc.pid, sig)
        deadline = time.monotonic() + STOP_GRACE_S
        for run in alive:
            with contextlib.suppress(subprocess.TimeoutExpired):
                run.proc.wait(timeout=max(0.0, deadline - time.monotonic()))


def _terminated(signum: int, _frame: Any) -> None:
    raise SystemExit(128 + signum)  # through reproduce's clean-up, as Ctrl-C goes


def _start(root: Path, stage: str, env: Mapping[str, str], follow: Callable[[_Running], None]) -> _Running:
    cmd = [sys.executable, "-m", "dvc", "--wait-for-lock", "repro", "--single-item", stage]
    proc = subprocess.Popen(
        cmd,
        cwd=root,
        env=dict(env),
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        errors="replace",  # a stage's bytes that are not UTF-8 are still shown
        bufsize=1,
        start_new_session=True,  # its own process group: stopped by `_stop`, not by a terminal's Ctrl-C twice
    )
    run = _Running(stage, proc, time.perf_counter())
    threading.Thread(target=follow, args=(run,), daemon=True).start()
    return run
