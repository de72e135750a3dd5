"""What a simulator runs is what the lab registered: a model folder's graph and description checked
before anything runs (client/needlecue_client/folder.py), from a fetched folder, offline from the cache, and
through `needlecue replay --model-dir`; a malformed field is one line naming the file and the field."""

from __future__ import annotations

import shutil
from collections.abc import Callable
from pathlib import Path
from urllib.parse import urlparse

import pytest
from typer.testing import CliRunner

import needlecue_client as fc
from needlecue_runtime.registry import store
from pipeline.cli import app
from tests.client.builders import UNREACHABLE, Registered, register_unit, unit_document

pytestmark = pytest.mark.filterwarnings("ignore::needlecue_client.force.UncalibratedUnit")


def _edit_mlmodel(old: str, new: str) -> Callable[[Path], None]:
    def edit(folder: Path) -> None:
        text = (folder / "MLmodel").read_text()
        assert old in text, f"{old!r} not in the MLmodel"
        (folder / "MLmodel").write_text(text.replace(old, new, 1))

    return edit


def _flip_a_bit(folder: Path) -> None:
    graph = bytearray((folder / "model.onnx").read_bytes())
    graph[len(graph) // 2] ^= 0x10
    (folder / "model.onnx").write_bytes(bytes(graph))


def _truncate(folder: Path) -> None:
    graph = (folder / "model.onnx").read_bytes()
    (folder / "model.onnx").write_bytes(graph[: len(graph) // 3])


TAMPERED = {
    # an input setting the client computes its features with
    "input setting": (_edit_mlmodel("rest_s: 0.5", "rest_s: 5.0"), "needlecue block is not the description"),
    # the cue pack's evidence levels
    "cue pack": (
        _edit_mlmodel("needlecue-cues/5", "needlecue-cues/3"),
        "needlecue block is not the description",
    ),
    "a bit of the graph": (_flip_a_bit, "graph was changed, damaged or swapped"),
    "the graph truncated": (_truncate, "graph was changed, damaged or swapped"),
}


@pytest.mark.parametrize("tamper", list(TAMPERED))
def test_a_folder_changed_after_registration_is_refused(fetched: Path, tmp_path: Path, tamper: str) -> None:
    # given: a copy of a fetched model with one thing changed
    change, why = TAMPERED[tamper]
    folder = shutil.copytree(fetched, tmp_path / "model")
    change(folder)
    # when / then: the client refuses it, naming the file and what is wrong
    with pytest.raises(fc.ModelRefused, match=why) as refused:
        fc.ForceClient.from_dir(folder)
    assert str(folder) in str(refused.value)


def test_the_fetched_folder_itself_passes_and_names_what_differs(fetched: Path, tmp_path: Path) -> None:
    # given: the fetched folder, and a copy whose description claims another angle
    fc.ForceClient.from_dir(fetched)
    folder = shutil.copytree(fetched, tmp_path / "model")
    _edit_mlmodel("angle_deg: 30.0", "angle_deg: 45.0")(folder)
    # when / then: the field that differs from the graph's own description is named
    with pytest.raises(fc.ModelRefused, match=r"needlecue\.angle_deg differs from the graph's own"):
        fc.ForceClient.from_dir(folder)


def test_another_models_graph_in_the_folder_is_refused(
    fetched: Path, registered: Registered, tmp_path: Path
) -> None:
    # given: the folder with the graph of another export of the checkpoint (no description hash)
    from pipeline.modelling.export import to_onnx

    folder = shutil.copytree(fetched, tmp_path / "model")
    (folder / "model.onnx").write_bytes(to_onnx(registered.checkpoint))
    # when / then
    with pytest.raises(fc.ModelRefused, match="changed, damaged or swapped"):
        fc.ForceClient.from_dir(folder)


def test_unverified_runs_a_changed_folder_loudly_and_a_broken_graph_is_still_one_line(
    fetched: Path, tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    # given: an edited input setting, and a truncated graph
    edited = shutil.copytree(fetched, tmp_path / "edited")
    _edit_mlmodel("rest_s: 0.5", "rest_s: 5.0")(edited)
    broken = shutil.copytree(fetched, tmp_path / "broken")
    _truncate(broken)
    # when: asked to run them unverified
    with caplog.at_level("WARNING", logger="needlecue_client"):
        client = fc.ForceClient.from_dir(edited, unverified=True)
    # then: the edited one runs, with its edit, after a loud warning; the broken one is a clear error
    assert client.inputs.rest_s == 5.0
    assert any("UNVERIFIED" in m and str(edited) in m for m in caplog.messages)
    with pytest.raises(fc.ModelFolderError, match=r"model\.onnx: not an ONNX graph onnxruntime can run"):
        fc.ForceClient.from_dir(broken, unverified=True)


def _set_field(text: str, key: str, value: str | None) -> str:
    """The MLmodel text with needlecue's `key` (and its list items) set to the YAML `value`, or
    removed (None)."""
    lines = text.splitlines(keepends=True)
    start = next(i for i, line in enumerate(lines) if line.startswith(f"    {key}:"))
    end = start + 1
    while end < len(lines) and lines[end].startswith(("    - ", "      ")):
        end += 1
    return "".join([*lines[:start], *([f"    {key}: {value}\n"] if value is not None else []), *lines[end:]])


MALFORMED = {
    "channels an int": ("channels", "3", r"field needlecue\.channels is 3; expected a list of distinct"),
    "kind missing": ("kind", None, r"field needlecue\.kind is missing; expected a model kind"),
    "window a word": ("window", "fifteen", r"field needlecue\.window is 'fifteen'; expected an integer >= 1"),
    "rate negative": ("rate_hz", "-30.0", r"field needlecue\.rate_hz is -30\.0; expected the sample rate"),
    "inputs a list": (
        "inputs",
        "[volts]",
        r"field needlecue\.inputs is \['volts'\]; expected the input settings",
    ),
    "a python object tag": (
        "kind",
        "!!python/object/apply:os.system ['true']",
        r"not valid YAML: line \d+, column \d+: could not determine a constructor for the tag .* refused",
    ),
}


@pytest.mark.parametrize("case", list(MALFORMED))
def test_a_malformed_field_is_one_line_naming_file_and_field(
    fetched: Path, tmp_path: Path, case: str
) -> None:
    # given: a folder whose MLmodel has one field of the wrong type, or missing
    key, value, message = MALFORMED[case]
    folder = shutil.copytree(fetched, tmp_path / "model")
    (folder / "MLmodel").write_text(_set_field((folder / "MLmodel").read_text(), key, value))
    # when / then: one line naming the file and the field, verified or not
    for unverified in (False, True):
        with pytest.raises(fc.ModelFolderError, match=message) as err:
            fc.ForceClient.from_dir(folder, unverified=unverified)
        assert str(folder / "MLmodel") in str(err.value) and "\n" not in str(err.value)


def test_offline_a_cached_copy_with_an_edited_setting_is_refused(
    registered: Registered, tmp_path: Path
) -> None:
    # given: the champion fetched, then one input setting edited in the cached MLmodel
    cache = tmp_path / "cache"
    folder = fc.fetch(30, cache_dir=cache, tracking_uri=registered.uri)
    _edit_mlmodel("rest_s: 0.5", "rest_s: 5.0")(folder)
    # when / then: offline, the copy is refused rather than run with the edited setting
    with pytest.raises(fc.CachedCopyRefused, match="needlecue block is not the description registered"):
        fc.fetch(30, cache_dir=cache, tracking_uri=UNREACHABLE)
    # and: online, the edited copy is replaced by the registered version
    assert (
        "rest_s: 0.5" in (fc.fetch(30, cache_dir=cache, tracking_uri=registered.uri) / "MLmodel").read_text()
    )


def test_offline_a_garbled_version_json_is_named_not_called_missing(
    registered: Registered, tmp_path: Path
) -> None:
    # given: a fetched copy whose version.json was garbled
    cache = tmp_path / "cache"
    folder = fc.fetch(30, cache_dir=cache, tracking_uri=registered.uri)
    (folder / "version.json").write_text("{ not json")
    # when / then: offline, the message says the copy is there and what is wrong with it
    with pytest.raises(fc.CachedCopyRefused, match=r"version\.json.*unreadable") as err:
        fc.fetch(30, cache_dir=cache, tracking_uri=UNREACHABLE)
    assert "there is no local copy" not in str(err.value)


def test_a_unit_calibration_changed_in_the_store_is_refused(
    registered: Registered, tmp_path: Path, mlflow_store: str
) -> None:
    # given: a unit's calibration registered, then its document edited where the store keeps it
    register_unit(mlflow_store, unit_document("est-f1", {30: registered.checkpoint}))
    client = store.connect(mlflow_store)
    source = client.get_model_version_download_uri("needle-unit-est-f1", "1")
    doc = Path(urlparse(source).path) / "calibration.json"
    doc.write_text(doc.read_text().replace('"ridge": 0.01', '"ridge": 0.02'))
    # when / then: fetching it is refused, naming the registered hash
    with pytest.raises(ValueError, match="is not the document registered"):
        fc.fetch_unit("est-f1", cache_dir=tmp_path / "cache", tracking_uri=mlflow_store)


def test_replay_model_dir_refuses_a_swapped_graph_unless_unverified(
    fetched: Path, registered: Registered, tmp_path: Path
) -> None:
    # given: a processed trial and a model folder whose graph was damaged
    from tests.client.builders import cue_trials

    trial = tmp_path / "trial.parquet"
    cue_trials(30, 1, "b9").to_parquet(trial, index=False)
    folder = shutil.copytree(fetched, tmp_path / "model")
    _edit_mlmodel("rest_s: 0.5", "rest_s: 5.0")(folder)
    # when: replaying through it, then again with --unverified
    refused = CliRunner().invoke(app, ["replay", str(trial), "--model-dir", str(folder)])
    loud = CliRunner().invoke(
        app,
        ["replay", str(trial), "--model-dir", str(folder), "--unverified", "--out", str(tmp_path / "r.png")],
    )
    # then: refused with one line naming the file; run only when asked, with a warning
    assert refused.exit_code == 1 and "needlecue block is not the description" in refused.output
    assert loud.exit_code == 0, loud.output
    assert "UNVERIFIED" in loud.output
