"""The evaluate and report stages on stored fake predictions: metrics.json, plots, figures, report."""

from __future__ import annotations

import json
import re
from pathlib import Path

import pytest

from needlecue_runtime.vocab import AXES
from pipeline.reporting.figures import FIGURES
from pipeline.stages import evaluate, report
from tests.metrics.fakes import ANGLES, CHANNELS, write_predictions, write_processed


def params_file(tmp_path: Path, angles: str = "[0, 15, 30, 45]", kinds: str = "[ls, fnn, lstm]") -> Path:
    path = tmp_path / "params.yaml"
    path.write_text(f"train:\n  angles: {angles}\n  kinds: {kinds}\nevaluate:\n  gaps_deg: [15, 30]\n")
    return path


def run(data: Path, pred: Path, reports: Path, params: Path) -> dict:
    """evaluate, then report, as dvc.yaml runs them; returns the full evaluation.json."""
    evaluate.main(
        data,
        pred,
        data / "no-calibration",
        reports / "cues" / "evaluation.json",
        reports / "evaluation.json",
        reports / "metrics.json",
        params,
    )
    report.main(data, pred, reports, params)
    return json.loads((reports / "evaluation.json").read_text())


def test_run_summarises_angle_gaps_from_fake_predictors(tmp_path: Path):
    # given four angles of data and LS, FNN models whose error depends on the angle gap
    data = write_processed(tmp_path / "processed")
    pred = write_predictions(tmp_path / "predictions", data, ["ls", "fnn"])
    # when evaluated
    m = run(data, pred, tmp_path / "reports", params_file(tmp_path, kinds="[ls, fnn]"))
    # then the gap rows and the matrix are exactly the hand-computed ones
    assert m["angle_gap"]["fnn"]["15"]["fx"] == pytest.approx(10.15)
    assert m["angle_gap"]["fnn"]["30"]["fy"] == pytest.approx(2 * 20.15)
    assert m["angle_gap_pairs"]["ls"] == {"15": 6, "30": 4}
    assert m["angle_gap_matrix"]["fnn"]["45"]["0"]["fz"] == pytest.approx(3 * 100 * (0.3 + 0.003))
    assert m["within_angle"]["fnn"]["30"]["fx"] == {"rmse": 0.002, "nrmse_pct": 0.2}
    assert m["gap_curve"]["fnn"]["45"]["mean"] == pytest.approx(2 * 30.15)
    assert m["mean"]["fnn"]["accuracy_pct"] == pytest.approx(100 - 2 * 0.15)
    gap_csv = (tmp_path / "reports" / "plots" / "gap.csv").read_text().splitlines()
    assert gap_csv[0] == "gap_deg,ls,fnn"
    assert [r.split(",")[0] for r in gap_csv[1:]] == ["0", "15", "30", "45"]


def test_metrics_json_has_the_required_shape_and_is_byte_identical(tmp_path: Path):
    # given the same inputs evaluated twice
    data = write_processed(tmp_path / "processed")
    pred = write_predictions(tmp_path / "predictions", data, ["ls", "fnn", "lstm"])
    outs = [tmp_path / "r1", tmp_path / "r2"]
    for out in outs:
        run(data, pred, out, params_file(tmp_path))
    # then every output is byte-identical
    names = ["evaluation.json", "metrics.json", "report.md", "plots/gap.csv", "plots/profile.csv"]
    for name in names + [f"figures/{f}" for f in FIGURES]:
        assert (outs[0] / name).read_bytes() == (outs[1] / name).read_bytes(), name
    # and evaluation.json has the documented shape with sorted keys and 4-decimal floats
    text = (outs[0] / "evaluation.json").read_text()
    m = json.loads(text)
    assert text == json.dumps(m, indent=2, sort_keys=True) + "\n"
    assert set(m) >= {"within_angle", "within_angle_test", "angle_gap", "angle_gap_matrix", "mean"}
    for key in ("within_angle", "within_angle_test"):
        assert set(m[key]) == {"ls", "fnn", "lstm"}
        assert set(m[key]["fnn"]) == set(ANGLES)
        assert set(m[key]["fnn"]["15"]) == set(AXES)
        assert set(m[key]["fnn"]["15"]["fy"]) == {"rmse", "nrmse_pct"}
    assert set(m["angle_gap"]["lstm"]) == {"15", "30"}
    assert set(m["angle_gap"]["lstm"]["30"]) == set(AXES)
    assert set(m["angle_gap_matrix"]["ls"]["0"]) == set(ANGLES)
    assert set(m["mean"]["fnn"]["within_angle"]) == set(AXES)
    assert isinstance(m["mean"]["fnn"]["accuracy_pct"], float)
    floats = [float(x) for x in re.findall(r"-?\d+\.\d+", text)]
    assert all(round(x, 4) == x for x in floats)
    profile = (outs[0] / "plots" / "profile.csv").read_text().splitlines()
    assert profile[0] == "t_s,reference,ls,fnn,lstm" and len(profile) == 1 + 31
    # and metrics.json holds the headline of it only: a few dozen numbers DVC's tables can show
    headline = json.loads((outs[0] / "metrics.json").read_text())
    assert headline["nrmse_pct"]["fnn"] == pytest.approx(
        sum(m["within_angle"]["fnn"][a][x]["nrmse_pct"] for a in ANGLES for x in AXES) / (3 * len(ANGLES)),
        abs=1e-4,
    )
    assert headline["gap_nrmse_pct"]["lstm"]["30"] == m["gap_curve"]["lstm"]["30"]["mean"]
    assert len(re.findall(r"-?\d+\.\d+|null", (outs[0] / "metrics.json").read_text())) <= 40


def test_main_on_a_fake_folder_skips_missing_models_with_a_warning(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
):
    # given data at 0/15/30, an angle with no external rows, and no LSTM at 30°
    data = write_processed(tmp_path / "processed", ["0", "15", "30"], no_external=("15",))
    pred = write_predictions(tmp_path / "predictions", data, ["ls", "fnn", "lstm"], ["0", "15", "30"])
    (pred / "lstm" / "30.parquet").unlink()  # as the predict stage leaves a model without checkpoint
    params = tmp_path / "params.yaml"
    params.write_text(
        "train:\n  angles: [0, 15, 30]\n  kinds: [ls, fnn, lstm]\nevaluate:\n  gaps_deg: [15, 30]\n"
    )
    # when the stage entry points run
    run(data, pred, tmp_path / "reports", params)
    # then it warned, skipped that model, fell back to the test split and wrote everything
    err = capsys.readouterr().err
    assert "lstm at 30° skipped" in err and "scoring on its test split" in err
    m = json.loads((tmp_path / "reports" / "evaluation.json").read_text())
    assert "30" not in m["within_angle"]["lstm"] and "30" in m["within_angle"]["fnn"]
    assert m["datasets"]["15"]["source"] == "test" and m["datasets"]["0"]["source"] == "external"
    for f in FIGURES:
        assert (tmp_path / "reports" / "figures" / f).read_bytes().startswith(b"\x89PNG")
    report = (tmp_path / "reports" / "report.md").read_text()
    assert "](figures/fig7_profiles.png)" in report and "| 15° | test |" in report


def test_a_model_missing_channels_is_skipped_on_that_angle(tmp_path: Path):
    # given a model that needs a channel the data do not have
    data = write_processed(tmp_path / "processed", ["0", "15"])
    logs: list[str] = []

    def channels(_model: str, angle: str) -> list[str]:
        return ["fsr9"] if angle == "15" else CHANNELS

    pred = write_predictions(
        tmp_path / "predictions", data, ["fnn"], ["0", "15"], channels=channels, log=logs.append
    )
    m = run(data, pred, tmp_path / "reports", params_file(tmp_path, "[0, 15]", "[fnn]"))
    # then it is skipped with a warning, and the other model still scores
    assert "15" not in m["angle_gap_matrix"]["fnn"] and "0" in m["angle_gap_matrix"]["fnn"]
    assert any("fsr9" in line for line in logs)


def test_no_trained_model_still_writes_every_output(tmp_path: Path, capsys: pytest.CaptureFixture[str]):
    # given data but an empty models folder (before the train stage has run)
    data = write_processed(tmp_path / "processed", ["0", "15"])
    (tmp_path / "predictions").mkdir()
    # when evaluated
    m = run(data, tmp_path / "predictions", tmp_path / "reports", params_file(tmp_path, "[0, 15]"))
    # then it warns, and the report says the claims cannot be compared instead of inventing a verdict
    assert m["within_angle"] == {} and "no trained model" in capsys.readouterr().err
    report = (tmp_path / "reports" / "report.md").read_text()
    verdicts = re.findall(r"^- \*\*.*: ([a-z ]+)\.\*\*$", report, flags=re.MULTILINE)
    assert verdicts and set(verdicts) == {"cannot compare"}
    assert (tmp_path / "reports" / "plots" / "gap.csv").read_text() == "gap_deg,ls,fnn,lstm\n"
