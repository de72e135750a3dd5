"""The angle cues: the pack, the tracker (causal, right on identifiable angles), the scoring, the stage."""

from __future__ import annotations

import itertools
import json
import math
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import typer
from pydantic import ValidationError
from typer.testing import CliRunner

from pipeline import cues
from pipeline.config import load_section
from pipeline.cues import CuesParams, CueTracker, Run, build_cue_pack, evaluate_cues, summarise_runs
from tests.helpers import tree_hash

RATE = 30.0
CHANNELS = ("fsr1", "fsr2", "fsr3")
ANGLES = (0, 15, 30, 45)


# --- synthetic data: an estimator whose rest reading and loading direction depend on the angle ---


def rest_volts(angle: float) -> np.ndarray:
    a = math.radians(angle)
    return np.array([0.50 + 0.08 * math.sin(a), 0.55 - 0.06 * math.sin(a), 0.58 + 0.02 * math.cos(a)])


def loading_direction(angle: float) -> np.ndarray:
    u = np.array([1.0 - angle / 45.0, 1.0, 0.4 + angle / 60.0])
    return u / np.linalg.norm(u)


def make_trial(angle: float, seed: int, batch_id: str, trial_id: str) -> pd.DataFrame:
    """One insertion: rest, 4 s of insertion (loading ramps up), dwell, retraction, rest."""
    rng = np.random.default_rng(seed)
    t0 = 2.0 + rng.uniform(0, 0.3)
    t = np.arange(0, t0 + 4.0 + 0.5 + 1.5 + 1.0, 1 / RATE)
    ramp = np.clip((t - t0) / 4.0, 0, 1) * (t < t0 + 4.5) + np.clip(1 - (t - t0 - 4.5) / 1.5, 0, 1) * (
        t >= t0 + 4.5
    )
    phase = np.where(
        t < t0,
        "rest",
        np.where(
            t < t0 + 4.0,
            "insertion",
            np.where(t < t0 + 4.5, "dwell", np.where(t < t0 + 6.0, "retraction", "rest")),
        ),
    )
    a = math.radians(angle)
    force = 0.6 * ramp[:, None] * np.array([math.sin(a), 0.3, -math.cos(a)])
    s = 0.8 * 0.6 * ramp[:, None] * loading_direction(angle)
    gain = 1 + rng.normal(0, 0.002, 3)
    volts = rest_volts(angle) * gain * np.exp(s) + rng.normal(0, 0.0008, (len(t), 3))
    return pd.DataFrame(
        {
            "batch_id": batch_id,
            "trial_id": trial_id,
            "angle_deg": float(angle),
            "tissue_point": "p1",
            "t_s": t,
            "phase": phase,
            **{c: volts[:, i] for i, c in enumerate(CHANNELS)},
            "fx": force[:, 0],
            "fy": force[:, 1],
            "fz": force[:, 2],
        }
    )


def make_split(angle: float, batches: list[str], per_batch: int, seed: int) -> pd.DataFrame:
    return pd.concat(
        [
            make_trial(angle, seed * 1000 + 100 * b + k + int(angle), name, f"a{angle:g}-{name}-{k}")
            for b, name in enumerate(batches)
            for k in range(per_batch)
        ],
        ignore_index=True,
    )


@pytest.fixture(scope="module")
def train_by_angle() -> dict[float, pd.DataFrame]:
    return {float(a): make_split(a, ["b1", "b2"], 3, seed=1) for a in ANGLES}


@pytest.fixture(scope="module")
def params() -> CuesParams:
    return CuesParams(kinds=("ls",), evidence_levels=(0.05, 0.1, 0.2))


@pytest.fixture(scope="module")
def pack30(train_by_angle: dict[float, pd.DataFrame], params: CuesParams) -> dict:
    return build_cue_pack(train_by_angle, 30, params)


def run_tracker(tracker: CueTracker, frame: pd.DataFrame, force: np.ndarray | None = None) -> list:
    tracker.reset()
    v = frame[list(CHANNELS)].to_numpy()
    f = frame[["fx", "fy", "fz"]].to_numpy() if force is None else force
    return [tracker.update(t, v[i], f[i]) for i, t in enumerate(frame["t_s"].to_numpy())]


# --- the pack ---------------------------------------------------------------------------------


def test_pack_is_small_json_and_round_trips(pack30: dict) -> None:
    # given: a pack built from the training splits
    # when: it goes through JSON
    text = json.dumps(pack30)
    back = json.loads(text)
    # then: nothing is lost, it is small, and it says what it is
    assert back == pack30
    assert len(text) < 100_000
    assert pack30["format"] == "needlecue-cues/1"
    assert pack30["channels"] == list(CHANNELS)
    assert pack30["angles"] == [float(a) for a in ANGLES]
    assert pack30["rate_hz"] == pytest.approx(RATE, rel=1e-3)
    prof = pack30["standard_profile"]
    assert len(prof["mean_n"]) == len(prof["sd_n"]) and len(prof["mean_n"][0]) == 3
    assert set(pack30["thresholds"]["profile"]) == {"reference"}  # no predictor given


def test_tracker_from_round_tripped_pack_behaves_the_same(pack30: dict) -> None:
    # given: the pack and its JSON copy
    copy = json.loads(json.dumps(pack30))
    trial = make_trial(15, seed=77, batch_id="x", trial_id="x1")
    # when: both track the same trial
    a = run_tracker(CueTracker(pack30, 30), trial)
    b = run_tracker(CueTracker(copy, 30), trial)
    # then: the same states
    assert a == b


def test_pack_is_only_for_its_own_preset_angle(pack30: dict) -> None:
    # given: the 30° pack / when: a tracker is asked for 45° / then: a clear error
    with pytest.raises(ValueError, match="preset angle 30"):
        CueTracker(pack30, 45)
    with pytest.raises(ValueError, match="needlecue-cues/1"):
        CueTracker({"format": "other"}, 30)


# --- the tracker ------------------------------------------------------------------------------


def test_tracker_is_causal(pack30: dict) -> None:
    # given: a trial, and the same trial whose second half is replaced by something else
    trial = make_trial(45, seed=5, batch_id="x", trial_id="x1")
    half = len(trial) // 2
    other = trial.copy()
    rng = np.random.default_rng(0)
    other.loc[half:, list(CHANNELS)] = rng.uniform(0.2, 1.5, (len(trial) - half, 3))
    other.loc[half:, ["fx", "fy", "fz"]] = rng.uniform(-3, 3, (len(trial) - half, 3))
    tracker = CueTracker(pack30, 30)
    # when: tracking both
    full = run_tracker(tracker, trial)
    changed = run_tracker(tracker, other)
    # then: the states before the change are identical (the future never leaks into the past)
    assert full[:half] == changed[:half]


@pytest.mark.parametrize(
    ("true_angle", "expected"), [(30, "continue"), (15, "correct"), (45, "correct"), (0, "stop")]
)
def test_tracker_cues_by_deviation(pack30: dict, true_angle: int, expected: str) -> None:
    # given: a fresh (held-out) trial at the true angle, the preset being 30°
    trial = make_trial(true_angle, seed=900 + true_angle, batch_id="held", trial_id="h1")
    # when: tracking it frame by frame
    states = run_tracker(CueTracker(pack30, 30), trial)
    end = int(np.flatnonzero(trial["phase"].to_numpy() == "insertion")[-1])
    # then: the cue at the end of the insertion matches the deviation, with the right angle estimate
    assert states[end].cue == expected
    assert states[end].angle_est_deg == pytest.approx(true_angle)
    assert states[0].cue == "wait"  # no evidence yet on the first frame
    assert states[end].reason


def test_tracker_debounces(pack30: dict) -> None:
    # given: a 30° trial tracked with the default 0.2 s debounce
    trial = make_trial(30, seed=3, batch_id="x", trial_id="x1")
    states = run_tracker(CueTracker(pack30, 30), trial)
    cues_seq = [s.cue for s in states]
    t = trial["t_s"].to_numpy()
    # then: every cue shown lasts at least the debounce time (or to the end of the trial)
    changes = [i for i in range(1, len(cues_seq)) if cues_seq[i] != cues_seq[i - 1]] + [len(cues_seq) - 1]
    for a, b in itertools.pairwise(changes):
        assert t[b] - t[a] >= 0.2 - 1e-9 or b == len(cues_seq) - 1


def test_force_above_range_means_stop(pack30: dict) -> None:
    # given: an on-angle trial whose predicted force is far above anything seen in training
    trial = make_trial(30, seed=4, batch_id="x", trial_id="x1")
    force = trial[["fx", "fy", "fz"]].to_numpy() * 10
    # when: tracking it / then: the combined cue stops for the force, the paper method too
    states = run_tracker(CueTracker(pack30, 30), trial, force)
    end = int(np.flatnonzero(trial["phase"].to_numpy() == "insertion")[-1])
    assert states[end].cue == "stop"
    assert "force" in states[end].reason


# --- scoring ----------------------------------------------------------------------------------


def test_summarise_runs_hand_checked() -> None:
    # given: three runs on a 0.5 s grid, insertion from frame 2 to frame 7
    t = np.arange(10) * 0.5
    W, C, K, S = 0, 1, 2, 3  # wait, continue, correct, stop
    runs = [
        # preset 30, true 30 -> continue; wrong (correct) at frame 4, right from frame 5 on: 5 -> 1.5 s
        Run("ls", "combined", 30, 30, t, np.array([W, W, C, C, K, C, C, C, C, C]), 2, 7),
        # preset 30, true 45 -> correct; right from the start (before the insertion): 0 s
        Run("ls", "combined", 30, 45, t, np.array([W, K, K, K, K, K, K, K, S, S]), 2, 7),
        # preset 30, true 60 -> stop; ends on correct: never right
        Run("ls", "combined", 30, 60, t, np.array([W, W, W, S, S, S, K, K, K, K]), 2, 7),
        # preset 0, true 30 -> stop; right from frame 7 (the last one): 2.5 s
        Run("ls", "combined", 0, 30, t, np.array([W, W, W, W, W, W, W, S, C, C]), 2, 7),
    ]
    # when
    res = summarise_runs(runs)["ls"]["combined"]
    # then: the final-cue confusion (rows continue/correct/stop; columns wait/continue/correct/stop)
    assert res["confusion_final"]["counts"] == [[0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 1, 1]]
    assert res["accuracy_final"] == pytest.approx(3 / 4)
    # per frame over frames 2..7: run 1: C,C,K,C,C,C; run 2: K x6; run 3: W,S,S,S,K,K; run 4: W x5, S
    assert res["confusion_frames"]["counts"] == [[0, 5, 1, 0], [0, 0, 6, 0], [6, 0, 2, 4]]
    ttc = res["time_to_cue"]
    assert ttc["0"] == {
        "trials": 1,
        "right_at_end": 1,
        "never_right": 0,
        "median_s": 1.5,
        "p90_s": 1.5,
        "seconds": [1.5],
    }
    assert ttc["15"]["median_s"] == 0.0
    assert ttc["30"]["trials"] == 2 and ttc["30"]["never_right"] == 1 and ttc["30"]["seconds"] == [2.5]
    assert ttc[">=45"]["trials"] == 0 and ttc[">=45"]["median_s"] is None


def test_time_to_cue_edge_cases() -> None:
    t = np.arange(5) * 1.0
    assert cues.time_to_cue(t, np.array([1, 1, 1, 1, 1], bool), 1, 3) == 0.0
    assert cues.time_to_cue(t, np.array([1, 0, 1, 1, 0], bool), 1, 3) == 1.0
    assert cues.time_to_cue(t, np.array([1, 1, 1, 0, 1], bool), 1, 3) is None


class ZeroModel:
    """A stand-in model that predicts no force at all."""

    kind = "ls"

    def predict(self, frame: pd.DataFrame) -> np.ndarray:
        assert "fx" not in frame.columns  # the evaluation never shows a model the answer
        return np.zeros((len(frame), 3))


def write_processed(root: Path, train_by_angle: dict[float, pd.DataFrame], external_per_angle: int) -> Path:
    for a, train in train_by_angle.items():
        folder = root / f"{a:g}"
        folder.mkdir(parents=True, exist_ok=True)
        train.to_parquet(folder / "train.parquet", index=False)
        make_split(a, ["heldout"], external_per_angle, seed=9).to_parquet(
            folder / "external.parquet", index=False
        )
    return root


def test_evaluate_cues_tiny_case(
    tmp_path: Path, train_by_angle: dict, params: CuesParams, pack30: dict
) -> None:
    # given: 2 held-out trials per angle (0, 15, 30, 45), the 30° preset, and angles that the rest
    # reading alone identifies, so the cue is right before the insertion even starts
    processed = write_processed(tmp_path / "processed", train_by_angle, 2)
    # when
    ev = evaluate_cues(
        processed,
        tmp_path / "models",
        params,
        {30: pack30},
        loader=lambda _p: ZeroModel(),
        log=lambda _m: None,
    )
    # then: hand-checked: 0° -> stop (2), 15° and 45° -> correct (4), 30° -> continue (2), all right
    ours = ev["results"]["ls"]["combined"]
    assert ours["confusion_final"]["counts"] == [[0, 2, 0, 0], [0, 0, 4, 0], [0, 0, 0, 2]]
    assert ours["accuracy_final"] == 1.0
    for group, n in (("0", 2), ("15", 4), ("30", 2)):
        assert ours["time_to_cue"][group] == {
            "trials": n,
            "right_at_end": n,
            "never_right": 0,
            "median_s": 0.0,
            "p90_s": 0.0,
            "seconds": [0.0] * n,
        }
    frames = {a: int((make_split(a, ["heldout"], 2, seed=9)["phase"] == "insertion").sum()) for a in ANGLES}
    assert ours["confusion_frames"]["counts"] == [
        [0, frames[30], 0, 0],
        [0, 0, frames[15] + frames[45], 0],
        [0, 0, 0, frames[0]],
    ]
    assert ev["angle_estimate_at_insertion_end"]["exact"] == 1.0
    # the paper's method and its measured-force bound are scored on the same trials
    assert np.sum(ev["results"]["ls"]["paper"]["confusion_final"]["counts"]) == 8
    assert np.sum(ev["results"]["reference"]["paper"]["confusion_final"]["counts"]) == 8


# --- params and the stage ---------------------------------------------------------------------


def test_bad_params_fail_loudly(tmp_path: Path) -> None:
    # given: a typo, a wrong value, and an inconsistent pair
    with pytest.raises(ValidationError, match="debounce"):
        CuesParams.model_validate({"debounce": 0.3})
    with pytest.raises(ValidationError):
        CuesParams.model_validate({"kinds": ["gru"]})
    with pytest.raises(ValidationError, match="increasing"):
        CuesParams(evidence_levels=(0.2, 0.1))
    with pytest.raises(ValidationError, match="stop_from_deg"):
        CuesParams(continue_below_deg=20, stop_from_deg=10)
    # and through params.yaml: an unknown key in the section fails, a missing section is the defaults
    path = tmp_path / "params.yaml"
    path.write_text("cues:\n  min_confidense: 0.8\n")
    with pytest.raises(ValidationError, match="min_confidense"):
        load_section(CuesParams, "cues", path)
    path.write_text("train:\n  angles: [0]\n")
    assert load_section(CuesParams, "cues", path) == CuesParams()


def invoke(*args: str):
    app = typer.Typer()
    app.command()(cues.main)
    return CliRunner().invoke(app, list(args))


def test_stage_writes_deterministic_outputs(tmp_path: Path, train_by_angle: dict) -> None:
    # given: processed data and an LS model per angle (the real checkpoint format)
    from pipeline.models import LSParams, fit, save_checkpoint

    processed = write_processed(tmp_path / "processed", train_by_angle, 1)
    for a, frame in train_by_angle.items():
        save_checkpoint(
            fit("ls", LSParams(), frame).checkpoint, tmp_path / "models" / "ls" / f"{a:g}" / "model.pt"
        )
    params = tmp_path / "params.yaml"
    params.write_text("cues:\n  kinds: [ls]\n  evidence_levels: [0.05, 0.1, 0.2]\n")
    # when: running the stage twice
    outs = [tmp_path / "out1", tmp_path / "out2"]
    for out in outs:
        result = invoke(str(processed), str(tmp_path / "models"), str(out), "--params", str(params))
        assert result.exit_code == 0, result.output
    # then: every output, byte-identical both times
    h1, h2 = tree_hash(outs[0]), tree_hash(outs[1])
    assert h1 == h2
    assert set(h1) == {
        "evaluation.json",
        "confusion.png",
        "time_to_cue.png",
        "summary.md",
        *(f"packs/{a}.json" for a in ANGLES),
    }
    summary = (outs[0] / "summary.md").read_text()
    assert summary.startswith("## Angle cues")
    assert "(cues/confusion.png)" in summary and "(cues/time_to_cue.png)" in summary
    pack = json.loads((outs[0] / "packs" / "30.json").read_text())
    assert set(pack["thresholds"]["profile"]) == {"reference", "ls"}


def test_stage_names_missing_inputs(tmp_path: Path) -> None:
    # given: no processed data / when: running the stage / then: exit 1 naming the folder
    params = tmp_path / "params.yaml"
    params.write_text("{}\n")
    (tmp_path / "models").mkdir()
    result = invoke(
        str(tmp_path / "nowhere"), str(tmp_path / "models"), str(tmp_path / "out"), "--params", str(params)
    )
    assert result.exit_code == 1
    assert "nowhere" in result.output


# --- small or unusual data: two angles, no estimator, no profile, nothing to score ------------


def end_of_insertion(trial: pd.DataFrame) -> int:
    return int(np.flatnonzero(trial["phase"].to_numpy() == "insertion")[-1])


def test_binary_lda_in_the_multiclass_form_gives_sklearns_posterior() -> None:
    # given: a two-class LDA (scikit-learn keeps one row of coefficients for it)
    rng = np.random.default_rng(0)
    x = np.vstack([rng.normal(0, 1, (8, 3)), rng.normal(1, 1, (8, 3))])
    y = np.repeat([0, 1], 8)
    model = cues._fit_lda("auto", 2, x, y)
    # when: put in the two-row form, and scored the same way
    coef, intercept = cues._multiclass_form(model)
    scores = cues._scores(model, x)
    # then: two rows, and the softmax of the scores is scikit-learn's posterior
    assert coef.shape == (2, 3) and intercept.shape == (2,)
    np.testing.assert_allclose(x @ coef.T + intercept, scores, atol=1e-9)
    np.testing.assert_allclose(cues._softmax(scores), model.predict_proba(x), atol=1e-9)


@pytest.fixture(scope="module")
def two_angle_pack(params: CuesParams) -> dict:
    train = {a: make_split(a, ["b1"], 3, seed=2) for a in (30.0, 45.0)}
    return build_cue_pack(train, 30, params)


def test_two_angles_give_a_two_class_estimator(two_angle_pack: dict) -> None:
    # given / when: a pack from two angles' training trials
    est = two_angle_pack["angle_estimator"]
    # then: every stage scores both classes, and the pack is strict JSON
    assert est["classes_deg"] == [30.0, 45.0]
    for stage in est["stages"]:
        assert np.asarray(stage["coef"]).shape == (2, 3 * (est["stages"].index(stage) + 1))
        assert len(stage["intercept"]) == 2
    assert "unavailable" not in two_angle_pack
    json.dumps(two_angle_pack, allow_nan=False)


@pytest.mark.parametrize(("true_angle", "expected"), [(30, "continue"), (45, "correct")])
def test_two_angle_tracker_gives_the_right_cue(two_angle_pack: dict, true_angle: int, expected: str) -> None:
    # given: a held-out trial, the preset being 30°
    trial = make_trial(true_angle, seed=700 + true_angle, batch_id="held", trial_id="h1")
    # when: tracking it
    states = run_tracker(CueTracker(two_angle_pack, 30), trial)
    # then: the right cue and angle estimate at the end of the insertion
    end = end_of_insertion(trial)
    assert (states[end].cue, states[end].angle_est_deg) == (expected, true_angle)


@pytest.mark.parametrize(
    ("angles", "per_batch", "why"),
    [((30,), 3, "only 30° has training trials"), ((30, 45), 1, "more than 3 in all")],
    ids=["one angle", "too few trials"],
)
def test_without_an_estimator_the_tracker_falls_back_to_the_paper_method(
    params: CuesParams, angles: tuple, per_batch: int, why: str
) -> None:
    # given: training data an angle estimator cannot be fitted on
    train = {float(a): make_split(a, ["b1"], per_batch, seed=3) for a in angles}
    logs: list[str] = []
    # when: building the 30° pack and tracking an on-angle trial with both methods
    pack = build_cue_pack(train, 30, params, log=logs.append)
    trial = make_trial(30, seed=31, batch_id="held", trial_id="h1")
    tracker = CueTracker(pack, 30)
    states = run_tracker(tracker, trial)
    paper = run_tracker(CueTracker(pack, 30, method="paper"), trial)
    # then: a pack without an estimator that says why (strict JSON, as the registry needs), a warning,
    # and a combined cue that is the paper method's, its reason saying the angle estimate is unavailable
    assert pack["angle_estimator"] is None and why in pack["unavailable"]["angle_estimator"]
    json.dumps(pack, allow_nan=False)
    assert any(m.startswith("warning: no angle estimator") for m in logs)
    assert [s.cue for s in states] == [s.cue for s in paper]
    end = end_of_insertion(trial)
    assert states[end].cue == paper[end].cue != "wait" and states[end].angle_est_deg is None
    assert all(s.reason.startswith("angle estimate unavailable") for s in states[1:])
    assert why in states[end].reason and "paper method: predicted force" in states[end].reason


def test_without_a_contact_there_is_no_profile_and_the_tracker_says_so(params: CuesParams) -> None:
    # given: training trials at the preset angle whose volts never move (no contact detected)
    flat = make_split(30, ["b1"], 3, seed=4)
    flat[list(CHANNELS)] = 0.5
    train = {30.0: flat, 45.0: make_split(45, ["b1"], 3, seed=4)}
    # when: building the 30° pack and tracking a trial
    pack = build_cue_pack(train, 30, params)
    states = run_tracker(
        CueTracker(pack, 30, method="paper"), make_trial(30, seed=5, batch_id="x", trial_id="1")
    )
    # then: no profile, no thresholds, each with its reason, and a paper method that waits saying why
    assert pack["standard_profile"] is None and pack["thresholds"]["profile"] == {}
    assert "contact" in pack["unavailable"]["standard_profile"]
    json.dumps(pack, allow_nan=False)
    assert {s.cue for s in states} == {"wait"}
    assert "standard profile unavailable" in states[-1].reason


def test_stage_without_external_trials_writes_every_output(tmp_path: Path, params: CuesParams) -> None:
    # given: a lab-sized batch: two angles, 2 + 1 training trials, no external split, an LS model each
    from pipeline.models import LSParams, fit, save_checkpoint

    processed = tmp_path / "processed"
    for a, n in ((30, 2), (45, 1)):
        frame = make_split(a, ["lab"], n, seed=6)
        (processed / f"{a}").mkdir(parents=True)
        frame.to_parquet(processed / f"{a}" / "train.parquet", index=False)
        frame.iloc[:0].to_parquet(processed / f"{a}" / "external.parquet", index=False)
        save_checkpoint(
            fit("ls", LSParams(), frame).checkpoint, tmp_path / "models" / "ls" / f"{a}" / "model.pt"
        )
    yaml = tmp_path / "params.yaml"
    yaml.write_text("cues:\n  kinds: [ls]\n  evidence_levels: [0.05, 0.1, 0.2]\n")
    # when: running the stage twice
    outs = [tmp_path / "out1", tmp_path / "out2"]
    results = [invoke(str(processed), str(tmp_path / "models"), str(o), "--params", str(yaml)) for o in outs]
    # then: exit 0, every output written (byte-identical both times), and what was skipped said, and why
    for result in results:
        assert result.exit_code == 0, result.output
    assert "warning: cue evaluation skipped: no external trials" in results[0].output
    assert "warning: no angle estimator" in results[0].output
    h1 = tree_hash(outs[0])
    assert h1 == tree_hash(outs[1])
    assert set(h1) == {
        "evaluation.json",
        "confusion.png",
        "time_to_cue.png",
        "summary.md",
        "packs/30.json",
        "packs/45.json",
    }
    evaluation = json.loads((outs[0] / "evaluation.json").read_text())
    assert evaluation["skipped"].startswith("no external trials") and evaluation["results"] == {}
    assert evaluation["unavailable"]["30"]["angle_estimator"]
    summary = (outs[0] / "summary.md").read_text()
    assert summary.startswith("## Angle cues")
    assert "**No angle estimator**" in summary and "**Cue evaluation skipped**: no external trials" in summary
    pack = json.loads((outs[0] / "packs" / "30.json").read_text())
    assert pack["angle_estimator"] is None and set(pack["thresholds"]["profile"]) == {"reference", "ls"}
    for png in ("confusion.png", "time_to_cue.png"):
        assert (outs[0] / png).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_evaluation_without_an_estimator_scores_the_paper_method_only(
    tmp_path: Path, train_by_angle: dict, params: CuesParams
) -> None:
    # given: a pack whose estimator could not be fitted, and external trials
    processed = write_processed(tmp_path / "processed", train_by_angle, 1)
    pack = build_cue_pack(train_by_angle, 30, params, estimator_unavailable="a reason")
    # when: scoring it
    ev = evaluate_cues(
        processed, tmp_path / "models", params, {30: pack}, loader=lambda _p: ZeroModel(), log=lambda _m: None
    )
    # then: the paper method only, no angle estimate, the reason kept, and a report that says so
    assert set(ev["results"]["ls"]) == {"paper"}
    assert ev["angle_estimate_at_insertion_end"] is None
    assert ev["unavailable"] == {"30": {"angle_estimator": "a reason"}}
    summary = cues.render_summary(json.loads(cues.dump_json(ev)), {30.0: pack})
    assert "**No angle estimator** (a reason)" in summary and "| LS | profile comparison (paper) |" in summary
    cues.plot_confusion(ev, tmp_path / "c.png")
    cues.plot_time_to_cue(ev, tmp_path / "t.png")
