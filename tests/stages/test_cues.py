"""The cues stage on stored predictions: deterministic packs and evaluation; small data; the report
stage's rendering of them (summary, figures)."""

from __future__ import annotations

import json
from pathlib import Path

import pandas as pd
import pytest
import typer
from typer.testing import CliRunner

from pipeline.cues.document import read_cue_evaluation
from pipeline.modelling.checkpoint import save_checkpoint
from pipeline.modelling.fit import fit
from pipeline.modelling.kinds.ls import LSParams
from pipeline.modelling.split_predictions import predict_all
from pipeline.reporting import cue_figures
from pipeline.reporting import cues as cue_report
from pipeline.stages import cues
from tests.cues.synthetic import ANGLES, make_split, write_processed
from tests.helpers import tree_hash


@pytest.fixture(scope="module")
def train_by_angle() -> dict[float, pd.DataFrame]:
    return {float(a): make_split(a, ["b1", "b2"], 3, seed=1) for a in ANGLES}


def invoke(*args: str):
    app = typer.Typer()
    app.command()(cues.main)
    return CliRunner().invoke(app, list(args))


def train_and_predict(processed: Path, frames: dict, tmp_path: Path) -> Path:
    """An LS model per angle (the real checkpoint format) and the predict stage's output for them."""
    for a, frame in frames.items():
        save_checkpoint(
            fit("ls", LSParams(), frame).checkpoint, tmp_path / "models" / "ls" / f"{a:g}" / "model.pt"
        )
    pred = tmp_path / "predictions"
    predict_all(processed, tmp_path / "models", pred, ["ls"], list(frames), lambda _m: None)
    return pred


def render(out: Path) -> str:
    """What the report stage makes of the cues stage's outputs: summary.md and the two figures."""
    evaluation = read_cue_evaluation(out / "evaluation.json")
    packs = {float(p.stem): json.loads(p.read_text()) for p in sorted((out / "packs").glob("*.json"))}
    cue_figures.plot_confusion(evaluation, out / "confusion.png")
    cue_figures.plot_time_to_cue(evaluation, out / "time_to_cue.png")
    return cue_report.angle_cues(evaluation, packs)


def test_stage_writes_deterministic_outputs(tmp_path: Path, train_by_angle: dict) -> None:
    # given: processed data, an LS model per angle and its stored predictions
    processed = write_processed(tmp_path / "processed", train_by_angle, 1)
    pred = train_and_predict(processed, train_by_angle, tmp_path)
    params = tmp_path / "params.yaml"
    params.write_text("cues:\n  kinds: [ls]\n  evidence_levels: [0.05, 0.1, 0.2]\n")
    # when: running the stage twice
    outs = [tmp_path / "out1", tmp_path / "out2"]
    for out in outs:
        result = invoke(
            str(processed), str(pred), str(tmp_path / "no-calibration"), str(out), "--params", str(params)
        )
        assert result.exit_code == 0, result.output
    # then: every output, byte-identical both times
    h1, h2 = tree_hash(outs[0]), tree_hash(outs[1])
    assert h1 == h2
    assert set(h1) == {"evaluation.json", *(f"packs/{a}.json" for a in ANGLES)}
    pack = json.loads((outs[0] / "packs" / "30.json").read_text())
    assert set(pack["thresholds"]["profile"]) == {"reference", "ls"}
    # and the report stage's section links its figures relative to reports/
    summary = render(outs[0])
    assert summary.startswith("## Angle cues")
    assert "(cues/confusion.png)" in summary and "(cues/time_to_cue.png)" in summary


def test_stage_names_missing_inputs(tmp_path: Path) -> None:
    # given: no processed data / when: running the stage / then: exit 1 naming the folder
    params = tmp_path / "params.yaml"
    params.write_text("{}\n")
    (tmp_path / "predictions").mkdir()
    result = invoke(
        str(tmp_path / "nowhere"),
        str(tmp_path / "predictions"),
        str(tmp_path / "no-calibration"),
        str(tmp_path / "out"),
        "--params",
        str(params),
    )
    assert result.exit_code == 1
    assert "nowhere" in result.output


def test_stage_without_external_trials_writes_every_output(tmp_path: Path) -> None:
    # given: a lab-sized batch: two angles, 2 + 1 training trials, no external split, an LS model each
    processed = tmp_path / "processed"
    frames = {}
    for a, n in ((30, 2), (45, 1)):
        frame = make_split(a, ["lab"], n, seed=6)
        (processed / f"{a}").mkdir(parents=True)
        frame.to_parquet(processed / f"{a}" / "train.parquet", index=False)
        frame.iloc[:0].to_parquet(processed / f"{a}" / "external.parquet", index=False)
        frames[float(a)] = frame
    pred = train_and_predict(processed, frames, tmp_path)
    yaml = tmp_path / "params.yaml"
    yaml.write_text("cues:\n  kinds: [ls]\n  evidence_levels: [0.05, 0.1, 0.2]\n")
    # when: running the stage twice
    outs = [tmp_path / "out1", tmp_path / "out2"]
    results = [
        invoke(str(processed), str(pred), str(tmp_path / "no-calibration"), str(o), "--params", str(yaml))
        for o in outs
    ]
    # then: exit 0, every output written (byte-identical both times), and what was skipped said, and why
    for result in results:
        assert result.exit_code == 0, result.output
    assert "warning: cue evaluation skipped: no external trials" in results[0].output
    assert "warning: no angle estimator" in results[0].output
    h1 = tree_hash(outs[0])
    assert h1 == tree_hash(outs[1])
    assert set(h1) == {"evaluation.json", "packs/30.json", "packs/45.json"}
    evaluation = json.loads((outs[0] / "evaluation.json").read_text())
    assert evaluation["skipped"].startswith("no external trials") and evaluation["results"] == {}
    assert evaluation["unavailable"]["30"]["angle_estimator"]
    pack = json.loads((outs[0] / "packs" / "30.json").read_text())
    assert pack["angle_estimator"] is None and set(pack["thresholds"]["profile"]) == {"reference", "ls"}
    # and the report stage still renders a section that says what was skipped, and why
    summary = render(outs[0])
    assert summary.startswith("## Angle cues")
    assert "**No angle estimator**" in summary and "**Cue evaluation skipped**: no external trials" in summary
    for png in ("confusion.png", "time_to_cue.png"):
        assert (outs[0] / png).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
