"""Where MLflow lives, how the registered force models and estimator units are named, and how an alias
is looked up: shared by the `register` stage, the simulator's client and the `needlecue` commands.

The tracking store is `MLFLOW_TRACKING_URI` if set, else `sqlite:///<project>/mlflow.db`, an
absolute path to the project's root: `dvc exp run --temp` runs stages in a copy under
`.dvc/tmp/exps/`, and a relative `sqlite:///mlflow.db` would be created (and lost) in that copy.

mlflow is imported inside the functions, so importing this module is cheap.
"""

from __future__ import annotations

import json
import logging
import os
import sqlite3
from collections.abc import Iterator
from contextlib import closing, contextmanager
from pathlib import Path
from typing import TYPE_CHECKING, Any

from needlecue_runtime.registry.mlflow_env import HTTP_SETTINGS, fluent, patience
from needlecue_runtime.vocab import ID_PATTERN

if TYPE_CHECKING:
    from mlflow import MlflowClient

EXPERIMENT = "needle-force"
CHAMPION = "champion"
CHALLENGER = "challenger"
TAG = "needlecue."  # prefix of our own tags on runs and model versions
# a unit calibration's version: the sha256 of its document's bytes, as registered (the client checks it)
CALIBRATION_SHA_TAG = f"{TAG}calibration_sha256"
# a force model version's graph format (vocab.DEPLOY_FORMAT): a champion of another format, which today's
# clients refuse, cannot defend its title, nor be rolled back to
FORMAT_TAG = f"{TAG}deploy_format"
UNIT_EXPERIMENT = "needle-units"  # one run per registered unit calibration document
UNIT_ALIAS = "current"  # needle-unit-<unit_id>@current: the calibration a simulator applies
# MLflow 3's UI opens an experiment without this tag on its GenAI view (traces, latency); ours are
# model training, so it opens on the runs and their metrics
KIND_TAG, KIND = "mlflow.experimentKind", "custom_model_development"
# A view of the runs table saved on the experiment (MLflow's "share view"): the runs with the columns
# the lab compares models by, best first. `ui_link` opens it.
VIEW_KEY = "needlecue"
VIEW_TAG = f"mlflow.sharedViewState.{VIEW_KEY}"
VIEW_COLUMNS = {
    EXPERIMENT: [
        "metrics.`external_nrmse_pct_mean`",
        "metrics.`test_nrmse_pct_mean`",
        "tags.`angle_deg`",
        "tags.`model_type`",
    ],
    UNIT_EXPERIMENT: ["tags.`unit_id`", "tags.`angles_used`", "tags.`angles_missing`", "tags.`kinds`"],
}
VIEW_ORDER = {
    EXPERIMENT: ("metrics.`external_nrmse_pct_mean`", True),
    UNIT_EXPERIMENT: ("attributes.start_time", False),
}
ABOUT = """One run per trained model: `<angle>°-<kind>` (ls, fnn, lstm), tagged `angle_deg` and `model_type`.

Metrics are named `<split>_<measure>_<axis>`: split `val`, `test` or `external` (the held-out tissue
batch, the one that decides champions), measure `rmse` (N) or `nrmse_pct` (the paper's eq. 4, in %),
axis `fx`, `fy`, `fz` or `mean`. `gap15_nrmse_pct_<axis>` / `gap30_...` are the model on the
external sets of the angles 15° / 30° away. `train_loss` / `val_loss` are the loss curves.

To compare: group runs by the tag `angle_deg`, or filter `tags.angle_deg = '30'`, and chart
`external_nrmse_pct_mean`. Registered models: `needle-force-<angle>`, aliases `champion` and
`challenger`."""
UNIT_ABOUT = """One run per estimator unit calibration document (needlecue-unit/4), named after its unit.

Params: the `calibrate` settings it was fitted with. Metrics: `<kind>_loss_before` / `<kind>_loss_after`,
the standardised force error of the frozen shared models on the unit's calibration trials without and
with its input transform. Tags: `unit_id`, `batches`, `angles_used`, `angles_missing` and
`needlecue.calibration_sha256` (of the document's bytes). The document is the artifact
`calibration/calibration.json`, registered as `needle-unit-<unit_id>`, alias `current`."""
# What an MLflow 3 tracking server answers, with no login, about itself (MLflow's own client asks it)
SERVER_INFO = "/api/3.0/mlflow/server-info"
SERVER_INFO_KEYS = {"store_type", "workspaces_enabled"}

# A writer learns that the store takes writes by writing the experiment's description (the tag the UI
# shows) back as it is: a real write that changes nothing. The internal tag earlier versions set for
# that is removed.
OLD_WRITE_CHECK_TAG = "needlecue.write_check"


class RegistryUnreachable(RuntimeError):
    """The tracking server / registry could not be reached (nothing was changed)."""


class NotMlflow(RegistryUnreachable):
    """Something answers at the tracking URI, but not as an MLflow tracking server does."""


class ReadOnlyStore(RegistryUnreachable):
    """The store answers reads but refuses writes (a read-only database, or read-only credentials)."""


def mlmodel_metadata(mlmodel: Path) -> dict[str, Any]:
    """The `metadata` mapping of an MLmodel file, read as plain YAML (no mlflow import, no pickle).
    ValueError, without the path (the caller names the file), if it is not YAML or not an MLmodel."""
    import yaml

    # libyaml's parser with PyYAML's safe constructors: the same mapping, 10x faster (a force model's
    # MLmodel, cue pack included, is about 200 kB: 0.4 s in pure Python, on every fetch and open)
    loader = getattr(yaml, "CSafeLoader", yaml.SafeLoader)
    try:
        spec = yaml.load(mlmodel.read_text(), Loader=loader) or {}
    except yaml.YAMLError as e:  # one line: the problem and where, not PyYAML's multi-line text
        mark, what = getattr(e, "problem_mark", None), getattr(e, "problem", None) or str(e)
        where = "" if mark is None else f"line {mark.line + 1}, column {mark.column + 1}: "
        tag = (
            " (a tag that builds an object: refused, plain YAML only)"
            if "constructor for the tag" in what
            else ""
        )
        raise ValueError(" ".join(f"not valid YAML: {where}{what}{tag}".split())) from e
    except UnicodeDecodeError as e:
        raise ValueError(f"not valid YAML: not UTF-8 ({e.reason} at byte {e.start})") from e
    if not isinstance(spec, dict) or not isinstance(spec.get("metadata") or {}, dict):
        raise ValueError("not an MLmodel file (a mapping with a metadata mapping)")
    return spec.get("metadata") or {}


def model_name(angle_deg: float) -> str:
    """`needle-force-30` for 30°: the registered model of one insertion angle."""
    if float(angle_deg) != int(angle_deg):
        raise ValueError(f"angles are whole degrees, got {angle_deg}")
    return f"needle-force-{int(angle_deg)}"


def model_uri(angle_deg: float, alias: str = CHAMPION) -> str:
    """`models:/needle-force-30@champion`."""
    return f"models:/{model_name(angle_deg)}@{alias}"


def unit_model_name(unit_id: str) -> str:
    """`needle-unit-est-042` for unit `est-042`: the registered calibrations of one estimator unit."""
    if not isinstance(unit_id, str) or ID_PATTERN.fullmatch(unit_id) is None:
        raise ValueError(f"not an estimator unit id: {unit_id!r} (ids match {ID_PATTERN.pattern})")
    return f"needle-unit-{unit_id}"


def project_root(start: Path | None = None) -> Path:
    """The folder holding `.dvc/` above `start` (default: cwd); a `dvc exp run --temp` copy under
    `<root>/.dvc/tmp/exps/` resolves to the outer `<root>`. Falls back to `start` itself."""
    here = (start or Path.cwd()).resolve()
    parts = here.parts
    for i in range(len(parts) - 1):
        if parts[i : i + 3] == (".dvc", "tmp", "exps"):
            return Path(*parts[:i])
    for folder in (here, *here.parents):
        if (folder / ".dvc").is_dir():
            return folder
    return here


def tracking_uri(start: Path | None = None) -> str:
    """`MLFLOW_TRACKING_URI`, or the project's own `sqlite:///<root>/mlflow.db`."""
    return os.environ.get("MLFLOW_TRACKING_URI") or f"sqlite:///{project_root(start) / 'mlflow.db'}"


def sqlite_file(uri: str) -> Path | None:
    """The database file of a `sqlite:///` store URI (also SQLite's URI form,
    `sqlite:///file:/path/mlflow.db?mode=ro&uri=true`), None for any other kind of store."""
    if not uri.startswith("sqlite:///"):
        return None
    path = uri.removeprefix("sqlite:///")
    if path.startswith("file:"):
        path = path.removeprefix("file:").split("?", 1)[0]
    return Path(path)


def experiment_id(client: MlflowClient, name: str = EXPERIMENT, about: str = ABOUT) -> str:
    """The experiment's id, creating it (described by `about`) if needed, of MLflow's kind "model
    training" and with needlecue's view of its runs (`ui_link`). With a sqlite store its artifacts go
    to `mlartifacts/` beside the database file: MLflow's own default is `./mlruns` under the cwd, which
    under `dvc exp run --temp` is a throwaway copy. A server decides for itself."""
    tags = {KIND_TAG: KIND, **({VIEW_TAG: view_state(name)} if name in VIEW_COLUMNS else {})}
    found = client.get_experiment_by_name(name)
    if found is not None:
        for key, value in tags.items():  # made by an older needlecue, or changed in the UI
            if found.tags.get(key) != value:
                client.set_experiment_tag(found.experiment_id, key, value)
        return str(found.experiment_id)
    location = None
    db = sqlite_file(client.tracking_uri)
    if db is not None:
        location = (db.parent / "mlartifacts").as_uri()
    tags["mlflow.note.content"] = about
    return str(client.create_experiment(name, artifact_location=location, tags=tags))


def view_state(name: str) -> str:
    """The saved view of experiment `name`'s runs table, as MLflow's UI stores a shared view."""
    order_by, ascending = VIEW_ORDER[name]
    state = {"selectedColumns": VIEW_COLUMNS[name], "orderByKey": order_by, "orderByAsc": ascending}
    return json.dumps(state, sort_keys=True)


def ui_link(ui_url: str, exp_id: str) -> str:
    """The MLflow UI page of the experiment's runs, as model training, in needlecue's view."""
    query = f"workflowType=machine_learning&viewStateShareKey={VIEW_KEY}"
    return f"{ui_url.rstrip('/')}/#/experiments/{exp_id}/runs?{query}"


def create_registered_model(client: MlflowClient, name: str, description: str) -> None:
    """Create `name`; one that exists (another run's, or left empty by an interrupted one) is fine."""
    from mlflow.exceptions import MlflowException

    try:
        client.create_registered_model(name, description=description)
    except MlflowException as e:
        if e.error_code != "RESOURCE_ALREADY_EXISTS":
            raise


@contextmanager
def writing(uri: str | None = None) -> Iterator[MlflowClient]:
    """A writer's session on the store at `uri`: `connect(write=True)` (refused before anything
    changes), the writer's `patience` and the fluent API on the same store, for the block."""
    with patience(write=True):
        client = connect(uri, write=True)
        with fluent(client.tracking_uri):
            yield client


def connect(uri: str | None = None, *, must_exist: bool = False, write: bool = False) -> MlflowClient:
    """A client on `uri` (default `tracking_uri()`), checked before anything changes:
    `RegistryUnreachable` if nothing answers, `NotMlflow` if what answers is not MLflow (a web server
    answering `{}` to everything, another program's sqlite file), and with `write`, `ReadOnlyStore` if
    it refuses writes (a read-only database or a simulator's read-only credentials).

    An HTTP server is asked what it is once, by MLflow's server-info endpoint; a store MLflow opens
    itself (sqlite, PostgreSQL) answers a search. A writer then sets one experiment tag.

    `must_exist`: a sqlite store that is not there yet is unreachable too, instead of being created
    empty (a reader, like the simulator's client run outside the project, wants the real one).
    Nothing global changes: HTTP timeouts are `patience`'s, the fluent API's URIs `fluent`'s.
    """
    from mlflow import MlflowClient

    uri = uri or tracking_uri()
    db = sqlite_file(uri)
    if db is not None:
        if not db.parent.is_dir():
            raise RegistryUnreachable(f"MLflow store {uri}: folder {db.parent} does not exist")
        if must_exist and not db.is_file():
            raise RegistryUnreachable(f"MLflow store {uri}: no such database (run `make repro` to create it)")
        _is_mlflow_sqlite(db, uri, must_exist)
    if uri.startswith(("http://", "https://")):
        _is_mlflow_server(uri)
        client = MlflowClient(tracking_uri=uri, registry_uri=uri)
    else:
        try:
            # MLflow opens (and for sqlite, migrates) the store here; an unknown scheme, a missing
            # database driver or a bad URI raise here too
            client = MlflowClient(tracking_uri=uri, registry_uri=uri)
            client.search_experiments(max_results=1)
        except Exception as e:
            raise RegistryUnreachable(f"cannot reach the MLflow registry at {uri}: {_said(e)}") from e
    if write:
        _takes_writes(client, uri)
    return client


def _is_mlflow_server(uri: str) -> None:
    """Ask the server what it is: `RegistryUnreachable` if it does not answer, `NotMlflow` unless it
    answers as an MLflow 3 tracking server does (its server-info JSON)."""
    from mlflow.environment_variables import MLFLOW_TRACKING_INSECURE_TLS, MLFLOW_TRACKING_SERVER_CERT_PATH
    from mlflow.utils.rest_utils import MlflowHostCreds, http_request

    creds = MlflowHostCreds(
        uri,
        ignore_tls_verification=MLFLOW_TRACKING_INSECURE_TLS.get(),
        server_cert_path=MLFLOW_TRACKING_SERVER_CERT_PATH.get(),
    )
    try:
        # asked once: no retries, whatever the environment says (a server that is down says so now)
        timeout = int(
            os.environ.get("MLFLOW_HTTP_REQUEST_TIMEOUT") or HTTP_SETTINGS["MLFLOW_HTTP_REQUEST_TIMEOUT"]
        )
        answer = http_request(
            creds, SERVER_INFO, "GET", max_retries=0, timeout=timeout, raise_on_status=False
        )
    except Exception as e:
        raise RegistryUnreachable(f"cannot reach the MLflow registry at {uri}: {_said(e)}") from e
    if answer.status_code >= 500 or answer.status_code in (401, 403):  # down, or a login in front of it
        login = (
            " (a login: set MLFLOW_TRACKING_USERNAME and MLFLOW_TRACKING_PASSWORD)"
            if answer.status_code < 500
            else ""
        )
        said = f"HTTP {answer.status_code} to GET {SERVER_INFO}{login}"
        raise RegistryUnreachable(f"cannot reach the MLflow registry at {uri}: {said}")
    try:
        info = answer.json() if answer.status_code == 200 else None
    except ValueError:
        info = None
    if not isinstance(info, dict) or not set(info) >= SERVER_INFO_KEYS:
        said = " ".join(answer.text.split())[:120]
        raise NotMlflow(
            f"{uri} answers, but not as an MLflow tracking server: HTTP {answer.status_code} to "
            f"GET {SERVER_INFO}, {said!r}. Is MLFLOW_TRACKING_URI the MLflow server's address (not "
            "another service's)?"
        )


def _is_mlflow_sqlite(db: Path, uri: str, must_exist: bool) -> None:
    """`NotMlflow` for a sqlite file that is there but is not an MLflow store (another program's
    database, or not a database), read-only and before MLflow would add its tables to it. An empty
    file is a store to be created, unless `must_exist`."""
    if not db.is_file():
        return
    try:
        with closing(sqlite3.connect(f"{db.resolve().as_uri()}?mode=ro", uri=True)) as con:
            tables = {row[0] for row in con.execute("SELECT name FROM sqlite_master WHERE type = 'table'")}
    except sqlite3.Error as e:
        raise NotMlflow(f"MLflow store {uri}: {db} is not an SQLite database ({e})") from e
    if not tables and not must_exist:
        return
    if not {"experiments", "alembic_version"} <= tables:
        found = ", ".join(sorted(tables)[:8]) or "none"
        raise NotMlflow(
            f"MLflow store {uri}: {db} is not an MLflow database (tables: {found}); left as it is"
        )


def _said(e: Exception) -> str:
    """The error's first line, its start and end when long (a connection error's cause comes last)."""
    line = (str(e).splitlines() or [""])[0]
    if len(line) > 400:
        line = f"{line[:200]} ... {line[-200:]}"
    return f"{type(e).__name__}: {line}"


def _takes_writes(client: MlflowClient, uri: str) -> None:
    """Write the tracking experiment's description back as it is (creating the experiment if needed, as a
    writer would anyway): a store that refuses is read-only, found before any run, version or alias."""
    # MLflow logs a refused SQL write with its whole traceback before raising: the error below says it
    db_log = logging.getLogger("mlflow.store.db.utils")
    quiet = db_log.disabled
    db_log.disabled = True
    try:
        exp_id = experiment_id(client)
        tags = client.get_experiment(exp_id).tags
        client.set_experiment_tag(exp_id, "mlflow.note.content", tags.get("mlflow.note.content", ABOUT))
        if OLD_WRITE_CHECK_TAG in tags:
            client.delete_experiment_tag(exp_id, OLD_WRITE_CHECK_TAG)
    except Exception as e:
        code = getattr(e, "error_code", "")
        text = str(e).lower()
        if code == "UNAUTHENTICATED":
            raise ReadOnlyStore(
                f"the MLflow server at {uri} takes writes only from a known user ({_said(e)}): set "
                "MLFLOW_TRACKING_USERNAME and MLFLOW_TRACKING_PASSWORD to a lab or admin user's."
            ) from e
        if code == "PERMISSION_DENIED" or "readonly" in text or "read-only" in text:
            raise ReadOnlyStore(
                f"the MLflow store at {uri} is read-only here ({_said(e)}): it can be read, not written. "
                "A read-only database, or read-only credentials (a simulator's): writing needs a lab or "
                "admin user."
            ) from e
        raise RegistryUnreachable(f"cannot write to the MLflow store at {uri}: {_said(e)}") from e
    finally:
        db_log.disabled = quiet


def versions(client: MlflowClient, name: str) -> list[Any]:
    """Every version of `name` ([] for an unknown name); any other registry error propagates, so a
    hiccup of the store is never read as "no versions"."""
    return list(client.search_model_versions(f"name = '{name}'"))


def finished_run(client: MlflowClient, exp_id: str, tag: str, value: str) -> Any | None:
    """The latest FINISHED run of the experiment tagged `tag` = `value`: what a registration reuses
    instead of logging the same thing again. A run still RUNNING, or FAILED or KILLED, was cut short
    (its artifacts may be partial) and is never reused."""
    runs = client.search_runs(
        [exp_id],
        filter_string=f"tags.`{tag}` = '{value}' and attributes.status = 'FINISHED'",
        max_results=1,
        order_by=["attributes.start_time DESC"],
    )
    return runs[0] if runs else None


def alias_version(client: MlflowClient, name: str, alias: str) -> Any | None:
    """The version `name@alias` points to; None only when the model or the alias does not exist
    (any other error, an unreachable store say, propagates)."""
    from mlflow.exceptions import MlflowException

    # A server with workspaces on answers 403, not 404, for a model that does not exist: ask first
    if not client.search_registered_models(filter_string=f"name = '{name}'", max_results=1):
        return None
    try:
        return client.get_model_version_by_alias(name, alias)
    except MlflowException as e:
        if e.error_code in ("RESOURCE_DOES_NOT_EXIST", "INVALID_PARAMETER_VALUE"):
            return None
        raise
