"""`needlecue repro`: what it plans, and that independent stages really run side by side."""

from __future__ import annotations

import io
import re
import signal
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from pipeline.execution import repro
from tests.projects import make_repo, run

# a diamond: a -> (b, c) -> d, and e on its own
ORDER = ("a", "b", "c", "d", "e")
DEPENDS = {"b": {"a"}, "c": {"a"}, "d": {"b", "c"}}


def test_the_stage_graph_read_from_dvc_is_the_one_dvc_dag_prints() -> None:
    # given: this repository's dvc.yaml (DVC's internal stage graph is what `needlecue repro` reads)
    root = Path(__file__).resolve().parents[1]
    # when: reading it, and asking DVC's own command for its edges
    order, depends_on = repro.dvc_graph(root)
    dot = subprocess.run(
        [sys.executable, "-m", "dvc", "dag", "--dot"], cwd=root, capture_output=True, text=True, check=True
    ).stdout
    nodes = re.findall(r'^"([^"]+)";$', dot, re.M)
    edges = {(a, b) for a, b in re.findall(r'"([^"]+)" -> "([^"]+)"', dot)}
    # then: the same stages, in the same order, and the same dependencies (dot: upstream -> stage)
    assert len(order) > 30 and order == nodes
    assert {(up, s) for s, ups in depends_on.items() for up in ups} == edges


def test_a_changed_stage_plans_itself_and_everything_downstream() -> None:
    # when: b is out of date
    plan = repro.plan_of(ORDER, DEPENDS, {"b"})
    # then: b and d run, d after b only (a and c are up to date: nothing to wait for)
    assert plan.order == ("b", "d")
    assert plan.waits_for == {"b": frozenset(), "d": frozenset({"b"})}


def test_stages_start_as_soon_as_what_they_depend_on_has_succeeded() -> None:
    # given: everything out of date
    plan = repro.plan_of(ORDER, DEPENDS, set(ORDER))
    # then: a and e first; once a succeeded, b and c; d only after both
    assert plan.ready(set(), set()) == ["a", "e"]
    assert plan.ready({"a"}, {"a", "e"}) == ["b", "c"]
    assert plan.ready({"a", "e", "b"}, {"a", "e", "b", "c"}) == []
    assert plan.ready({"a", "e", "b", "c"}, {"a", "e", "b", "c"}) == ["d"]


def test_targets_limit_the_plan_to_them_and_their_upstream() -> None:
    # when: only c is asked for, with everything out of date
    plan = repro.plan_of(ORDER, DEPENDS, set(ORDER), targets=["c"])
    # then: c and what it depends on, nothing downstream or beside it
    assert plan.order == ("a", "c")
    # and an unknown target is refused with the stages there are
    with pytest.raises(ValueError, match=r"no stage named x in dvc.yaml; stages: a, b, c, d, e"):
        repro.plan_of(ORDER, DEPENDS, set(), targets=["x"])


def test_nothing_out_of_date_plans_nothing() -> None:
    assert repro.plan_of(ORDER, DEPENDS, set()).order == ()


# Stage b waits for a file c writes and c for one b writes: they pass only when run side by side
# (each gives up after PATIENCE s: run one at a time, the first fails).
MEET = """import pathlib, sys, time
me, other = sys.argv[1:]
pathlib.Path(me + ".here").touch()
t = time.time()
while not pathlib.Path(other + ".here").exists():
    assert time.time() - t < PATIENCE, "never met " + other
    time.sleep(0.05)
pathlib.Path(me).write_text(open("a").read() + me)
"""


def toy_project(root: Path, failing: str | None = None, patience: float = 60) -> Path:
    """A DVC project of the diamond above: a writes a file, b and c must meet (within `patience`
    seconds), d joins them, e is on its own; `failing` names a stage whose command fails."""
    stages = {
        "a": {"cmd": "python -c \"open('a', 'w').write('a')\"", "outs": ["a"]},
        "b": {"cmd": "python meet.py b c", "deps": ["a", "meet.py"], "outs": ["b"]},
        "c": {"cmd": "python meet.py c b", "deps": ["a", "meet.py"], "outs": ["c"]},
        "d": {
            "cmd": "python -c \"open('d', 'w').write(open('b').read() + open('c').read())\"",
            "deps": ["b", "c"],
            "outs": ["d"],
        },
        "e": {"cmd": "python -c \"open('e', 'w').write('e')\"", "outs": ["e"]},
    }
    if failing:
        stages[failing]["cmd"] = "python -c \"raise SystemExit('this stage fails')\""
    dvc_project(root, stages)
    (root / "meet.py").write_text(MEET.replace("PATIENCE", str(patience)))
    return root


def dvc_project(root: Path, stages: dict) -> Path:
    """A git + DVC project at `root` with `stages` in its dvc.yaml."""
    make_repo(root)
    (root / "dvc.yaml").write_text(yaml.safe_dump({"stages": stages}, sort_keys=False))
    return root


def test_independent_stages_run_side_by_side_and_write_what_dvc_repro_writes(tmp_path: Path) -> None:
    # given: the diamond project
    root = toy_project(tmp_path / "toy")
    # when: needlecue repro runs it on two jobs
    out = io.StringIO()
    plan = repro.dvc_plan(root)
    outcome = repro.reproduce(root, plan, jobs=2, out=out)
    # then: every stage ran (b and c met: they ran at the same time), d saw both
    assert outcome.code == 0, out.getvalue()
    assert sorted(outcome.ran) == ["a", "b", "c", "d", "e"]
    assert (root / "d").read_text() == "abac"
    # and each stage's lines carry its name
    assert "b | Running stage 'b':" in out.getvalue()
    # and DVC recorded every stage: nothing is out of date, and the command says so
    assert run(root, "dvc", "status").strip() == "Data and pipelines are up to date."
    again = run(root, sys.executable, "-m", "pipeline.cli", "repro")
    assert again.strip() == "Data and pipelines are up to date."
    # and the meeting test holds: one stage at a time, as a plain `dvc repro` runs them, b waits for
    # c in vain (what it wrote before is the same: stage a's outputs)
    plain = toy_project(tmp_path / "plain", patience=2)
    with pytest.raises(AssertionError, match="never met"):
        run(plain, "dvc", "repro")  # one stage at a time: b waits for c in vain
    outs = lambda r: {n: s["outs"] for n, s in yaml.safe_load((r / "dvc.lock").read_text())["stages"].items()}  # noqa: E731
    assert outs(root)["a"] == outs(plain)["a"]


def test_a_failed_stage_stops_what_depends_on_it_and_names_itself(tmp_path: Path) -> None:
    # given: the diamond, with a failing
    root = toy_project(tmp_path / "toy", failing="a")
    # when: it runs on two jobs
    out = io.StringIO()
    outcome = repro.reproduce(root, repro.dvc_plan(root), jobs=2, out=out)
    # then: a failed, e (independent) ran, nothing downstream of a started
    assert outcome.code == 1 and outcome.failed == ["a"]
    assert "this stage fails" in "\n".join(outcome.tail)
    assert set(outcome.spans) <= {"a", "e"}
    assert not (root / "b").exists() and not (root / "d").exists()


def test_outside_a_dvc_project_the_command_says_where_it_looked(tmp_path: Path) -> None:
    # when: needlecue repro runs in a folder that is no DVC project
    cli = [sys.executable, "-m", "pipeline.cli", "repro", "--project", str(tmp_path)]
    done = subprocess.run(cli, capture_output=True, text=True, timeout=120)
    # then: exit 2, naming the folder, without a traceback
    assert done.returncode == 2
    assert done.stderr.startswith(f"error: {tmp_path}: ") and "not inside of a DVC repository" in done.stderr
    assert "Traceback" not in done.stderr


def test_a_stage_whose_output_is_not_utf8_still_runs_to_the_end(tmp_path: Path) -> None:
    # given: a project whose one stage writes bytes that are not UTF-8 to its output
    cmd = "python -c \"import sys; sys.stdout.buffer.write(b'caf\\xe9\\n'); open('x', 'w').write('x')\""
    root = dvc_project(tmp_path / "bytes", {"x": {"cmd": cmd, "outs": ["x"]}})
    # when: it runs
    out = io.StringIO()
    outcome = repro.reproduce(root, repro.dvc_plan(root), jobs=2, out=out)
    # then: it ran, its line shown with a replacement character
    assert outcome.code == 0 and outcome.ran == ["x"], out.getvalue()
    assert "x | caf\ufffd" in out.getvalue()


def test_data_tracked_by_a_dvc_file_is_verified_and_what_reads_it_reruns(tmp_path: Path) -> None:
    # given: a file tracked with `dvc add` (as docs/retraining.md versions raw batches) and a stage
    # reading it, reproduced; then the file changes
    root = dvc_project(tmp_path / "added", {})
    (root / "raw.txt").write_text("hello")
    run(root, "dvc", "add", "-q", "raw.txt")
    upper = "python -c \"open('up.txt', 'w').write(open('raw.txt').read().upper())\""
    (root / "dvc.yaml").write_text(
        yaml.safe_dump({"stages": {"up": {"cmd": upper, "deps": ["raw.txt"], "outs": ["up.txt"]}}})
    )
    assert repro.reproduce(root, repro.dvc_plan(root), jobs=2, out=io.StringIO()).code == 0
    (root / "raw.txt").write_text("changed")
    # when: needlecue repro runs
    plan = repro.dvc_plan(root)
    out = io.StringIO()
    outcome = repro.reproduce(root, plan, jobs=2, out=out)
    # then: as `dvc repro` does, DVC verifies the tracked file (its .dvc file takes the new hash)
    # and the stage reading it runs after that
    assert set(plan.order) == {"raw.txt.dvc", "up"} and plan.waits_for["up"] == {"raw.txt.dvc"}
    assert outcome.code == 0 and outcome.ran == ["up"], out.getvalue()
    assert "raw.txt.dvc | done in" in out.getvalue() and "(data verified)" in out.getvalue()
    assert (root / "up.txt").read_text() == "CHANGED"
    assert run(root, "dvc", "status").strip() == "Data and pipelines are up to date."


def test_sigterm_stops_the_running_stages_and_leaves_no_lock(tmp_path: Path) -> None:
    # given: two independent stages that would run for a minute, started by needlecue repro
    sleep = "python -c \"import time; time.sleep(60); open('{0}', 'w').write('{0}')\""
    stages = {s: {"cmd": sleep.format(s), "outs": [s]} for s in ("s1", "s2")}
    root = dvc_project(tmp_path / "slow", stages)
    cli = [sys.executable, "-m", "pipeline.cli", "repro"]
    proc = subprocess.Popen(cli, cwd=root, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    assert proc.stdout is not None
    started = 0
    for line in proc.stdout:  # both commands are running once DVC has shown both
        started += line.startswith(("s1 | > python", "s2 | > python"))
        if started == 2:
            break
    # when: the launcher alone gets SIGTERM (as from a scheduler or `timeout`), not its stages
    proc.send_signal(signal.SIGTERM)
    rest, _ = proc.communicate(timeout=60)
    # then: it exits 143 soon, its stages stopped with it, and DVC's locks are free again
    assert proc.returncode == 128 + signal.SIGTERM, rest
    assert not (root / "s1").exists() and not (root / "s2").exists()
    status = run(root, "dvc", "status")
    assert "s1" in status and "s2" in status  # still to do, and DVC can say so: no lock is held
