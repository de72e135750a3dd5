"""report.md's computed statements: verdicts follow the numbers, never written in advance."""

from __future__ import annotations

from pipeline.metrics.document import Evaluation
from pipeline.metrics.paper import Finding, findings
from pipeline.reporting.report import render
from tests.metrics.fakes import ErrorFn, in_memory_metrics


def network_error(ls: float, fnn: float, lstm: float) -> ErrorFn:
    """Base error per model at its own angle, growing by 0.1 N per 15° of gap."""
    base = {"ls": ls, "fnn": fnn, "lstm": lstm}
    return lambda model, train, data: base[model] + 0.1 * abs(train - data) / 15


def finding(metrics: Evaluation, start: str) -> Finding:
    return next(f for f in findings(metrics) if f.claim.startswith(start))


def test_report_states_ls_is_worse_when_it_is():
    # given LS 20 %, FNN 5 %, LSTM 6 % at every angle (times 1, 2, 3 per axis)
    m = in_memory_metrics(network_error(0.20, 0.05, 0.06))
    report = render(m)
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
    report = render(m)
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

    m = in_memory_metrics(error, kinds=("fnn",))
    report = render(m)
    assert finding(m, "FNN error grows").verdict == "disagree"
    assert "- no: FNN: 100.00% (0°) → 10.00% (15°) → 10.00% (30°): does not grow with the gap." in report
    assert "cannot compare" in report  # no LS, no LSTM: those claims cannot be checked


def test_an_angle_without_an_external_set_is_said_in_words():
    # Given metrics where 30° was scored on its test split (its held-out trials all set aside)
    m = in_memory_metrics(network_error(0.20, 0.05, 0.06))
    on_test = m.model_copy(
        update={"datasets": {**m.datasets, "30": m.datasets["30"].model_copy(update={"source": "test"})}}
    )
    # When the report is rendered, then it says so in a sentence, not only in the table's column
    assert "**No external set at 30°.**" in render(on_test)
    # and says nothing of the kind when every angle has one
    assert "No external set" not in render(m)


def test_trials_used_with_a_flag_are_named_in_the_datasets_section():
    # Given seven trials the ledger lists as used with a flag (a low alignment quality, kept)
    m = in_memory_metrics(network_error(0.20, 0.05, 0.06))
    flagged = [
        {"batch_id": "b", "trial_id": f"t{k}", "flag": "alignment quality 0.31, kept"} for k in range(7)
    ]
    # When the report is rendered with them
    report = render(m, flagged=flagged)
    # Then the Datasets section counts them, names the first few with why, and points to the ledger
    assert "**7 trial(s) used with a flag**" in report
    assert "`b/t0` (alignment quality 0.31, kept)" in report and "and 2 more" in report
    assert "`reports/ledger/ledger.md` lists them all" in report
    assert "used with a flag" not in render(m)


def _fz_only(error: ErrorFn) -> Evaluation:
    """`in_memory_metrics` of a lab whose references recorded fz alone: frames and models without fx, fy."""
    from pipeline.metrics.evaluation import EvalSet, Scored, compute_metrics
    from tests.metrics.fakes import FakePredictor, angle_frame, evaluation

    angles = ["0", "15", "30", "45", "60", "75"]
    sets = {
        a: EvalSet(
            a, "external", *(angle_frame(a, s, k).drop(columns=["fx", "fy"]) for s, k in (("h", 2), ("t", 1)))
        )
        for a in angles
    }
    preds = Scored()
    for m in ("ls", "fnn", "lstm"):
        for t in angles:
            p = FakePredictor(m, t, error)
            preds.loaded.append((m, t))
            preds.axes[(m, t)] = ("fz",)
            for d, es in sets.items():
                preds.on_eval[(m, t, d)] = p.predict(es.frame.drop(columns=["fz"]))[:, [2]]
            preds.on_test[(m, t)] = p.predict(sets[t].test.drop(columns=["fz"]))[:, [2]]
    return evaluation(**compute_metrics(sets, preds, (15, 30)))


def test_a_lab_that_recorded_fz_alone_gets_tables_of_fz_alone():
    # Given the evaluation of models of fz alone (a one-axis load cell), and batches whose fx and fy the
    # ledger says their angle left out
    m = _fz_only(network_error(0.20, 0.05, 0.06))
    left_out = [
        {
            "batch_id": "cast-1",
            "trial_id": f"t{k}",
            "angle": "30",
            "use": "train",
            "unused_axes": ["fx", "fy"],
        }
        for k in range(3)
    ]
    # When the report is rendered
    report = render(m, left_out=left_out)
    # Then every table has an Fz column and none for Fx or Fy; the Datasets section says which axes
    tables = [line for line in report.splitlines() if line.startswith("|")]
    assert "| Fz | paper Fz |" in report and not [t for t in tables if "Fx" in t or "Fy" in t]
    # (the paper's own findings on fx and fy are quoted, and ours said to need those axes)
    assert "Ours: needs FNN at the 30° gap and LS averages, on fx and fy." in report
    assert "**Force axes: fz.**" in report
    # and names the batch whose recorded axes its angle leaves out, once, with its use
    assert "**Force axes left out.**" in report and "30°: `cast-1`'s fx, fy (train)" in report
    # and a three-axis evaluation says neither
    three = render(in_memory_metrics(network_error(0.20, 0.05, 0.06)))
    assert "Force axes" not in three and "| Fx | Fy | Fz |" in three


def test_table_3_shows_the_papers_comparison_whatever_else_was_trained():
    # given: an evaluation of the paper's kinds and of one it never ran
    def error(model: str, train: float, data: float) -> float:
        return 0.05 + 0.1 * abs(train - data) / 15

    report = render(in_memory_metrics(error, kinds=("ls", "fnn", "lstm", "gru")))
    # when: reading Table III
    table3 = report.split("## Table III")[1].split("\n## ")[0]
    rows = [line.split(" | ")[0] for line in table3.splitlines() if line.startswith("| ") and "°" in line]
    # then: the rows are the paper's LSTM and FNN, at the angle and at the gap, and no other kind
    assert rows == ["| LSTM (30°)", "| FNN (30°)", "| LSTM (angle gap 15°)", "| FNN (angle gap 15°)"]
    assert "GRU (" in report.split("## Table III")[0]  # the other tables show every kind
