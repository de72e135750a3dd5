"""The evaluate stage: the paper's metrics, angle-gap summaries, metrics.json and the computed report."""

from __future__ import annotations

import json
import math
import re
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from pipeline import evaluate as ev

CHANNELS = ["fsr1", "fsr2", "fsr3"]
ANGLES = ["0", "15", "30", "45"]
AXIS_SCALE = np.array([1.0, 2.0, 3.0])  # per-axis error multiplier, so the axes differ

# error(model, train angle, data angle) -> constant offset (N) before AXIS_SCALE
ErrorFn = Callable[[str, float, float], float]


def gap_error(model: str, train: float, data: float) -> float:
    """0.1 N per 15° of gap, plus 0.001 N per 15° of train angle so that every pair differs."""
    return 0.1 * abs(train - data) / 15 + 0.001 * train / 15


def trial_frame(angle: float, batch: str, trial: str, n: int = 31) -> pd.DataFrame:
    """One trial whose forces equal its channels and span exactly [0, 1] N on every axis."""
    ramp = np.linspace(0.0, 1.0, n)
    cols = {
        "batch_id": [batch] * n,
        "trial_id": [trial] * n,
        "angle_deg": [float(angle)] * n,
        "tissue_point": ["p1"] * n,
        "t_s": np.arange(n) / 30.0,
        "phase": ["insertion"] * n,
    }
    for k, (ch, ax) in enumerate(zip(CHANNELS, ev.AXES, strict=True)):
        values = np.roll(ramp, 3 * k)  # different shapes per axis, same [0, 1] range
        cols[ch] = values
        cols[ax] = values
    return pd.DataFrame(cols)


def angle_frame(angle: str, batch: str, n_trials: int = 2) -> pd.DataFrame:
    return pd.concat(
        [trial_frame(float(angle), batch, f"a{angle}-t{k:02d}") for k in range(1, n_trials + 1)],
        ignore_index=True,
    )


class FakePredictor:
    """Predicts the true force (readable from the channels) plus an error set by the angle gap."""

    def __init__(self, model: str, angle: str, error: ErrorFn = gap_error, channels: list[str] = CHANNELS):
        self.kind, self.angle_deg, self.channels = model, float(angle), tuple(channels)
        self.error = error

    def predict(self, frame: pd.DataFrame) -> np.ndarray:
        assert not set(ev.AXES) & set(frame.columns), "forces must not reach the model"
        truth = frame[CHANNELS].to_numpy(dtype=float)
        data = frame["angle_deg"].to_numpy(dtype=float)
        offset = np.array([self.error(self.kind, self.angle_deg, d) for d in data])
        return truth + offset[:, None] * AXIS_SCALE


def write_processed(root: Path, angles: list[str] = ANGLES, no_external: tuple[str, ...] = ()) -> Path:
    """A tiny split-stage output: external and test files per angle."""
    for a in angles:
        d = root / a
        d.mkdir(parents=True)
        external = angle_frame(a, f"sim-heldout-{a}deg", 2)
        if a in no_external:
            external = external.iloc[:0]
        external.to_parquet(d / "external.parquet")
        angle_frame(a, "sim-tissue-1", 1).to_parquet(d / "test.parquet")
    return root


def write_models(root: Path, models: list[str], angles: list[str] = ANGLES) -> Path:
    for m in models:
        for a in angles:
            (root / m / a).mkdir(parents=True)
            (root / m / a / "model.pt").write_bytes(b"fake")
    return root


def fake_loader(error: ErrorFn = gap_error) -> Callable[[Path], FakePredictor]:
    return lambda model_dir: FakePredictor(model_dir.parent.name, model_dir.name, error)


def in_memory_metrics(error: ErrorFn, models: tuple[str, ...] = ("ls", "fnn", "lstm")) -> dict:
    """metrics for all angles x models without touching disk (for the report tests)."""
    angles = ["0", "15", "30", "45", "60", "75"]
    sets = {a: ev.EvalSet(a, "external", angle_frame(a, "h"), angle_frame(a, "t", 1)) for a in angles}
    preds = ev.Predictions()
    for m in models:
        for t in angles:
            p = FakePredictor(m, t, error)
            preds.loaded.append((m, t))
            for d, es in sets.items():
                preds.on_eval[(m, t, d)] = p.predict(es.frame.drop(columns=list(ev.AXES)))
            preds.on_test[(m, t)] = p.predict(sets[t].test.drop(columns=list(ev.AXES)))
    return ev.compute_metrics(sets, preds, (15, 30))


def quiet(_: str) -> None:
    pass


# --- eq. (3)-(4) -------------------------------------------------------------------------------


def test_rmse_and_nrmse_match_hand_computed_values():
    # given one axis where only the last sample is off by 2 over a reference range of 4
    pred, ref = np.array([1.0, 2.0, 3.0]), np.array([1.0, 2.0, 5.0])
    # when scored, then RMSE = sqrt(4/3) and NRMSE = 100 * RMSE / 4
    assert ev.rmse(pred, ref) == pytest.approx(math.sqrt(4 / 3))
    assert ev.nrmse_pct(pred, ref) == pytest.approx(100 * math.sqrt(4 / 3) / 4)


def test_scores_are_per_axis():
    # given three axes: the case above, an all-zero prediction of 0, 1, 2, and a perfect one
    pred = np.array([[1.0, 0.0, 7.0], [2.0, 0.0, 8.0], [3.0, 0.0, 9.0]])
    ref = np.array([[1.0, 0.0, 7.0], [2.0, 1.0, 8.0], [5.0, 2.0, 9.0]])
    # when scored
    s = ev.axis_scores(pred, ref)
    # then each axis has its own RMSE and range
    assert s["fx"]["rmse"] == pytest.approx(math.sqrt(4 / 3))
    assert s["fx"]["nrmse_pct"] == pytest.approx(100 * math.sqrt(4 / 3) / 4)
    assert s["fy"]["rmse"] == pytest.approx(math.sqrt(5 / 3))
    assert s["fy"]["nrmse_pct"] == pytest.approx(100 * math.sqrt(5 / 3) / 2)
    assert s["fz"] == {"rmse": 0.0, "nrmse_pct": 0.0}


def test_constant_reference_has_no_nrmse_and_shapes_must_match():
    assert math.isnan(float(ev.nrmse_pct(np.array([1.0, 2.0]), np.array([3.0, 3.0]))))
    with pytest.raises(ValueError, match="shape"):
        ev.rmse(np.zeros((3, 3)), np.zeros((4, 3)))


# --- angle gaps ---------------------------------------------------------------------------------


def test_gap_summary_averages_exactly_the_pairs_with_that_gap():
    # given a matrix whose NRMSE is 100 * gap_error (reference range 1 N)
    matrix = {
        t: {
            d: dict(zip(ev.AXES, 100 * gap_error("fnn", float(t), float(d)) * AXIS_SCALE, strict=True))
            for d in ANGLES
        }
        for t in ANGLES
    }
    # when summarised per gap
    s15, n15 = ev.gap_summary(matrix, 15)
    s30, n30 = ev.gap_summary(matrix, 30)
    s45, n45 = ev.gap_summary(matrix, 45)
    # then: 15° pairs (0,15) (15,0) (15,30) (30,15) (30,45) (45,30) -> 10 + 0.1 * mean train index
    assert n15 == 6 and s15["fx"] == pytest.approx((10 + 10.1 + 10.1 + 10.2 + 10.2 + 10.3) / 6)
    assert n30 == 4 and s30["fx"] == pytest.approx((20 + 20.2 + 20.1 + 20.3) / 4)
    assert n45 == 2 and s45["fx"] == pytest.approx((30 + 30.3) / 2)
    assert s15["fz"] == pytest.approx(3 * s15["fx"])
    assert ev.gap_summary(matrix, 60) == ({}, 0)


def test_run_summarises_angle_gaps_from_fake_predictors(tmp_path: Path):
    # given four angles of data and LS, FNN models whose error depends on the angle gap
    data = write_processed(tmp_path / "processed")
    models = write_models(tmp_path / "models", ["ls", "fnn"])
    train = ev.TrainParams(angles=(0, 15, 30, 45), models=("ls", "fnn"))
    # when evaluated
    m = ev.run(data, models, tmp_path / "reports", train, ev.EvaluateParams(), fake_loader(), quiet)
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


def test_fig8_pairs_prefer_the_15_degree_model_and_fall_back():
    assert ev.gap_examples(ANGLES, ANGLES, (15, 30)) == [("15", "30"), ("15", "45")]
    assert ev.gap_examples(["0", "30", "60"], ["0", "30", "60"], (15, 30)) == [("0", "30")]


# --- metrics.json and the stage -----------------------------------------------------------------


def test_metrics_json_has_the_required_shape_and_is_byte_identical(tmp_path: Path):
    # given the same inputs evaluated twice
    data = write_processed(tmp_path / "processed")
    models = write_models(tmp_path / "models", ["ls", "fnn", "lstm"])
    train = ev.TrainParams(angles=(0, 15, 30, 45))
    outs = [tmp_path / "r1", tmp_path / "r2"]
    for out in outs:
        ev.run(data, models, out, train, ev.EvaluateParams(), fake_loader(), quiet)
    # then every output is byte-identical
    names = ["metrics.json", "report.md", "plots/gap.csv", "plots/profile.csv"]
    for name in names + [f"figures/{f}" for f in ev.FIGURES]:
        assert (outs[0] / name).read_bytes() == (outs[1] / name).read_bytes(), name
    # and metrics.json has the documented shape with sorted keys and 4-decimal floats
    text = (outs[0] / "metrics.json").read_text()
    m = json.loads(text)
    assert text == json.dumps(m, indent=2, sort_keys=True) + "\n"
    assert set(m) >= {"within_angle", "within_angle_test", "angle_gap", "angle_gap_matrix", "mean"}
    for key in ("within_angle", "within_angle_test"):
        assert set(m[key]) == {"ls", "fnn", "lstm"}
        assert set(m[key]["fnn"]) == set(ANGLES)
        assert set(m[key]["fnn"]["15"]) == set(ev.AXES)
        assert set(m[key]["fnn"]["15"]["fy"]) == {"rmse", "nrmse_pct"}
    assert set(m["angle_gap"]["lstm"]) == {"15", "30"}
    assert set(m["angle_gap"]["lstm"]["30"]) == set(ev.AXES)
    assert set(m["angle_gap_matrix"]["ls"]["0"]) == set(ANGLES)
    assert set(m["mean"]["fnn"]["within_angle"]) == set(ev.AXES)
    assert isinstance(m["mean"]["fnn"]["accuracy_pct"], float)
    floats = [float(x) for x in re.findall(r"-?\d+\.\d+", text)]
    assert all(round(x, 4) == x for x in floats)
    profile = (outs[0] / "plots" / "profile.csv").read_text().splitlines()
    assert profile[0] == "t_s,reference,ls,fnn,lstm" and len(profile) == 1 + 31


def test_main_on_a_fake_folder_skips_missing_models_with_a_warning(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
):
    # given data at 0/15/30, an angle with no external rows, and no LSTM at 30°
    data = write_processed(tmp_path / "processed", ["0", "15", "30"], no_external=("15",))
    models = write_models(tmp_path / "models", ["ls", "fnn", "lstm"], ["0", "15", "30"])
    (models / "lstm" / "30" / "model.pt").unlink()
    params = tmp_path / "params.yaml"
    params.write_text(
        "train:\n  angles: [0, 15, 30]\n  models: [ls, fnn, lstm]\nevaluate:\n  gaps_deg: [15, 30]\n"
    )
    monkeypatch.setattr(ev, "load_model", fake_loader())
    # when the stage entry point runs
    ev.main(data, models, tmp_path / "reports", params)
    # then it warned, skipped that model, fell back to the test split and wrote everything
    err = capsys.readouterr().err
    assert "lstm at 30° skipped" in err and "scoring on its test split" in err
    m = json.loads((tmp_path / "reports" / "metrics.json").read_text())
    assert "30" not in m["within_angle"]["lstm"] and "30" in m["within_angle"]["fnn"]
    assert m["datasets"]["15"]["source"] == "test" and m["datasets"]["0"]["source"] == "external"
    for f in ev.FIGURES:
        assert (tmp_path / "reports" / "figures" / f).read_bytes().startswith(b"\x89PNG")
    report = (tmp_path / "reports" / "report.md").read_text()
    assert "](figures/fig7_profiles.png)" in report and "| 15° | test |" in report


def test_a_model_missing_channels_is_skipped_on_that_angle(tmp_path: Path):
    # given a model that needs a channel the data do not have
    data = write_processed(tmp_path / "processed", ["0", "15"])
    models = write_models(tmp_path / "models", ["fnn"], ["0", "15"])
    logs: list[str] = []

    def loader(d: Path) -> FakePredictor:
        return FakePredictor("fnn", d.name, channels=["fsr9"] if d.name == "15" else CHANNELS)

    train = ev.TrainParams(angles=(0, 15), models=("fnn",))
    m = ev.run(data, models, tmp_path / "reports", train, ev.EvaluateParams(), loader, logs.append)
    # then it is skipped with a warning, and the other model still scores
    assert "15" not in m["angle_gap_matrix"]["fnn"] and "0" in m["angle_gap_matrix"]["fnn"]
    assert any("fsr9" in line for line in logs)


# --- the report's computed statements ------------------------------------------------------------


def network_error(ls: float, fnn: float, lstm: float) -> ErrorFn:
    """Base error per model at its own angle, growing by 0.1 N per 15° of gap."""
    base = {"ls": ls, "fnn": fnn, "lstm": lstm}
    return lambda model, train, data: base[model] + 0.1 * abs(train - data) / 15


def finding(metrics: dict, start: str) -> ev.Finding:
    return next(f for f in ev.findings(metrics) if f.claim.startswith(start))


def test_report_states_ls_is_worse_when_it_is():
    # given LS 20 %, FNN 5 %, LSTM 6 % at every angle (times 1, 2, 3 per axis)
    m = in_memory_metrics(network_error(0.20, 0.05, 0.06))
    report = ev.render_report(m)
    # then the statement counts every angle and agrees with the paper
    assert (
        "LS is worse than both networks (FNN, LSTM, each where it has results) on every axis at 6 of 6"
        in report
    )
    assert "exceptions" not in finding(m, "LS is worse").ours.text
    assert "**LS is worse than the networks at every angle (Table I): agree.**" in report
    assert "**FNN beats LSTM at 30° (Table III): agree.**" in report
    assert "**FNN error grows with the angle gap (Table II): agree.**" in report
    assert "- yes: LSTM: 12.00% (0°) → 32.00% (15°) → 52.00% (30°): grows with the gap." in report


def test_report_states_exceptions_when_ls_is_not_worse():
    # given LS better than the FNN at 30° only, and an LSTM better than the FNN everywhere
    def error(model: str, train: float, data: float) -> float:
        if model == "ls" and train == 30:
            return 0.01
        return network_error(0.20, 0.05, 0.04)(model, train, data)

    m = in_memory_metrics(error)
    report = ev.render_report(m)
    # then the count, the exceptions and the verdicts follow the numbers
    ls = finding(m, "LS is worse")
    assert ls.ours.holds is False and ls.verdict == "disagree"
    assert "on every axis at 5 of 6 angles; exceptions: 30° Fx (LS 1.00% vs FNN 5.00%, LSTM 4.00%)" in report
    assert "**FNN beats LSTM at 30° (Table III): disagree.**" in report
    assert "at 30°: FNN 10.00% vs LSTM 8.00% (mean over axes); FNN lower on 0 of 3 axes" in report


def test_report_says_no_when_error_does_not_grow_with_the_gap():
    # given a FNN that is worse at its own angle than anywhere else
    def error(model: str, train: float, data: float) -> float:
        return 0.5 if train == data else 0.05

    m = in_memory_metrics(error, models=("fnn",))
    report = ev.render_report(m)
    assert finding(m, "FNN error grows").verdict == "disagree"
    assert "- no: FNN: 100.00% (0°) → 10.00% (15°) → 10.00% (30°): does not grow with the gap." in report
    assert "cannot compare" in report  # no LS, no LSTM: those claims cannot be checked


def test_the_paper_side_is_computed_from_the_paper_tables():
    paper = ev.paper_metrics()
    assert ev.check_ls_worse(paper).holds is True
    assert ev.check_gap_growth(paper, "fnn").text.startswith("FNN: 8.13% (0°) → 15.64% (15°) → 35.29% (30°)")
    assert ev.check_fnn_beats_lstm_at(paper, "30").holds is True
    assert ev.check_fnn_beats_lstm_gap(paper, "15").holds is False


def test_no_trained_model_still_writes_every_output(tmp_path: Path):
    # given data but an empty models folder (before the train stage has run)
    data = write_processed(tmp_path / "processed", ["0", "15"])
    (tmp_path / "models").mkdir()
    logs: list[str] = []
    train = ev.TrainParams(angles=(0, 15))
    # when evaluated
    m = ev.run(
        data,
        tmp_path / "models",
        tmp_path / "reports",
        train,
        ev.EvaluateParams(),
        fake_loader(),
        logs.append,
    )
    # then it warns, and the report says the claims cannot be compared instead of inventing a verdict
    assert m["within_angle"] == {} and any("no trained model" in line for line in logs)
    report = (tmp_path / "reports" / "report.md").read_text()
    verdicts = re.findall(r"^- \*\*.*: ([a-z ]+)\.\*\*$", report, flags=re.MULTILINE)
    assert verdicts and set(verdicts) == {"cannot compare"}
    assert (tmp_path / "reports" / "plots" / "gap.csv").read_text() == "gap_deg,ls,fnn,lstm\n"
