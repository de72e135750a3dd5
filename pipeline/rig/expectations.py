"""Great Expectations 1.x checks of freshly read rig-log/1 data, mapped back to `Problem`s.

`pipeline.rig.reader` parses each batch into plain frames and hands them here. Per batch it
validates four frames, one validation each (never one per file, which would be slow):

- ``trials``: the trials.csv table (``trial_id``, ``angle_deg``, ``tissue_point``, ``line``);
- ``fsr``: all estimator rows of the batch (``trial_id``, ``line``, ``t_ms``, channels, ``dt``);
- ``ref``: all reference rows (``trial_id``, ``line``, ``t_s``, forces [, torques], ``dt``);
- ``streams``: one row per stream file (``trial_id``, ``file``, ``time_column``, ``n_samples``,
  ``rate_hz``): enough samples at a plausible rate (``ingest`` params).

``line`` is the 1-based line in the source file (header = line 1) and ``dt`` the step from
the previous sample of the same trial (NaN on a trial's first row, which GX skips as
missing). Results are requested in COMPLETE format with ``unexpected_index_column_names``
so every failing row maps back to trial, file, line and column. Each expectation carries
``meta.reason``, the text of the `Problem` it raises (``{value}`` is the offending value).
The rules are those of `docs/rig-log-format.md`, "Invalid input and what happens to it".

GX is imported lazily: importing this module (e.g. for ``needlecue --help``) stays fast.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
import pandas as pd

from pipeline.config import IngestParams
from pipeline.rig.format import ID_PATTERN, TRIAL_COLUMNS, Problem

if TYPE_CHECKING:
    from great_expectations.data_context import AbstractDataContext
    from great_expectations.expectations import Expectation

INDEX_COLUMNS = {
    "trials": ["trial_id", "line"],
    "fsr": ["trial_id", "line"],
    "ref": ["trial_id", "line"],
    "streams": ["trial_id", "file", "time_column"],
}
# Stored result JSON keeps at most this many failing rows per expectation; Problems get all.
MAX_STORED_ROWS = 100
_DROP_META = ("run_id", "validation_time", "validation_id", "checkpoint_id", "batch_markers")


@dataclass(frozen=True)
class Check:
    """One validated frame: scrubbed GX result JSON and the Problems it raised."""

    kind: str
    result: dict[str, Any]
    problems: list[Problem]
    # A failure that names no row (missing column, GX error): the whole batch is suspect.
    batch_failed: bool


def _fmt(value: Any) -> str:
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return "NaN"
    if isinstance(value, bool | np.bool_):
        return str(bool(value))
    if isinstance(value, int | np.integer):
        return str(int(value))
    if isinstance(value, float | np.floating):
        return f"{float(value):.10g}"
    return repr(str(value))


def _e(cls_name: str, reason: str, *, meta: dict[str, Any] | None = None, **kwargs: Any) -> Expectation:
    """An expectation whose meta says in words what a failure means.

    meta may also say which column to blame: ``column`` (a name, or None for no column) or
    ``column_from`` (the index column of the failing row that holds the name).
    """
    import great_expectations.expectations as gxe

    return getattr(gxe, cls_name)(meta={"reason": reason, **(meta or {})}, **kwargs)


def _not_null(cols: Sequence[str]) -> list[Expectation]:
    return [_e("ExpectColumnValuesToNotBeNull", "missing value (empty cell or NaN)", column=c) for c in cols]


def _schema(cols: Sequence[str]) -> list[Expectation]:
    return [_e("ExpectColumnToExist", f"column {c!r} is missing", column=c) for c in cols]


def trial_expectations() -> list[Expectation]:
    """trials.csv: id pattern, unique ids, a numeric plausible angle, a non-empty tissue_point."""
    return [
        *_schema([*TRIAL_COLUMNS, "line"]),
        _e(
            "ExpectColumnValuesToMatchRegex",
            f"trial_id {{value}} does not match {ID_PATTERN.pattern}",
            column="trial_id",
            regex=rf"\A(?:{ID_PATTERN.pattern})\Z",
        ),
        _e("ExpectColumnValuesToBeUnique", "trial_id {value} is listed more than once", column="trial_id"),
        *_not_null(["angle_deg"]),
        # Catches inf too; any real insertion angle in degrees lies well inside.
        _e(
            "ExpectColumnValuesToBeBetween",
            "angle_deg {value} is not an angle in degrees",
            column="angle_deg",
            min_value=-360,
            max_value=360,
        ),
        _e("ExpectColumnValuesToMatchRegex", "tissue_point is empty", column="tissue_point", regex=r"\S"),
    ]


def stream_expectations(
    time_col: str,
    value_cols: Sequence[str],
    adc_max: int | None = None,
) -> list[Expectation]:
    """One stream kind: columns exist, no missing values, ADC range, strictly increasing time."""
    unit = "ms" if time_col.endswith("_ms") else "s"
    exps = [*_schema(["trial_id", "line", time_col, *value_cols, "dt"]), *_not_null([time_col, *value_cols])]
    if adc_max is not None:
        exps += [
            _e(
                "ExpectColumnValuesToBeBetween",
                f"count {{value}} outside the ADC range [0, {adc_max}]",
                column=c,
                min_value=0,
                max_value=adc_max,
            )
            for c in value_cols
        ]
    # dt failures are about the time column; blame it in the Problem.
    exps.append(
        _e(
            "ExpectColumnValuesToBeBetween",
            f"time does not increase: step of {{value}} {unit} from the previous sample",
            meta={"column": time_col},
            column="dt",
            min_value=0,
            strict_min=True,
        )
    )
    return exps


def streams_expectations(params: IngestParams) -> list[Expectation]:
    """Per stream file: enough samples at a plausible rate."""
    return [
        *_schema(["trial_id", "file", "time_column", "n_samples", "rate_hz"]),
        _e(
            "ExpectColumnValuesToBeBetween",
            f"only {{value}} samples (ingest.min_samples = {params.min_samples})",
            meta={"column": None},
            column="n_samples",
            min_value=params.min_samples,
        ),
        _e(
            "ExpectColumnValuesToBeBetween",
            f"sample rate {{value}} Hz outside [{params.min_rate_hz:g}, {params.max_rate_hz:g}] Hz "
            "(ingest.min_rate_hz, ingest.max_rate_hz)",
            meta={"column_from": "time_column"},
            column="rate_hz",
            min_value=params.min_rate_hz,
            max_value=params.max_rate_hz,
        ),
    ]


def _jsonable(obj: Any) -> Any:
    """Plain JSON values; non-finite floats become strings so the file stays strict JSON."""
    if isinstance(obj, dict):
        return {str(k): _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [_jsonable(v) for v in obj]
    if isinstance(obj, np.generic):
        obj = obj.item()
    if isinstance(obj, float) and not math.isfinite(obj):
        return None if math.isnan(obj) else str(obj)
    return obj


def scrub_result(result: Mapping[str, Any]) -> dict[str, Any]:
    """GX result JSON without run times, random ids or huge lists: same input, same bytes."""
    out = _jsonable(dict(result))
    out.pop("id", None)
    meta = out.get("meta") or {}
    for key in _DROP_META:
        meta.pop(key, None)
    for r in out.get("results", []):
        r.get("expectation_config", {}).pop("id", None)
        res = r.get("result") or {}
        res.pop("unexpected_index_query", None)
        for key in ("unexpected_list", "unexpected_index_list", "partial_unexpected_list"):
            if isinstance(res.get(key), list) and len(res[key]) > MAX_STORED_ROWS:
                res[key] = res[key][:MAX_STORED_ROWS]
                res[f"{key}_truncated"] = True
    return out


def problems_from_result(
    result: Mapping[str, Any], batch_id: str, default_file: str, file_of: Callable[[str], str]
) -> tuple[list[Problem], bool]:
    """Every failing row of a (raw, unscrubbed) result dict as a Problem; True if one names no row."""
    problems: list[Problem] = []
    batch_failed = False
    for r in result.get("results", []):
        if r.get("success"):
            continue
        cfg = r.get("expectation_config") or {}
        meta = cfg.get("meta") or {}
        kw = cfg.get("kwargs") or {}
        col = kw.get("column")
        blame = meta.get("column", col)
        reason = str(meta.get("reason", cfg.get("type", "expectation failed")))
        exc = r.get("exception_info") or {}
        rows = (r.get("result") or {}).get("unexpected_index_list")
        if exc.get("raised_exception") or not rows:
            if exc.get("raised_exception"):
                reason = f"validation of {cfg.get('type')} failed: {exc.get('exception_message')}"
            problems.append(Problem(batch_id, default_file, reason.replace("{value}", "?"), column=blame))
            batch_failed = True
            continue
        for row in rows:
            tid = row.get("trial_id")
            file = row.get("file")
            if "column_from" in meta:
                blame = row.get(meta["column_from"])
            problems.append(
                Problem(
                    batch_id,
                    str(file_of(str(file))) if file is not None else file_of(str(tid)),
                    reason.replace("{value}", _fmt(row.get(col))),
                    trial_id=None if tid is None else str(tid),
                    line=None if row.get("line") is None else int(row["line"]),
                    column=blame,
                )
            )
    return problems, batch_failed


class Validator:
    """One ephemeral GX context for a run; validates frames of many batches in it."""

    def __init__(self, params: IngestParams) -> None:
        self.params = params
        self._context: AbstractDataContext | None = None
        self._names: set[str] = set()

    @property
    def context(self) -> AbstractDataContext:
        if self._context is None:
            self._context = ephemeral_context()
            self._context.data_sources.add_pandas("rig-log")
        return self._context

    def _unique(self, name: str) -> str:
        # The same batch_id can be validated twice in one context (e.g. `check` given a folder twice).
        base, n = name, 1
        while name in self._names:
            n += 1
            name = f"{base}.{n}"
        self._names.add(name)
        return name

    def run(
        self,
        batch_id: str,
        kind: str,
        frame: pd.DataFrame,
        expectations: list[Expectation],
        default_file: str,
        file_of: Callable[[str], str],
    ) -> Check:
        """Validate one frame with one suite; failing rows become Problems."""
        import great_expectations as gx

        ctx = self.context
        name = self._unique(f"{batch_id}.{kind}")
        source = ctx.data_sources.get("rig-log")
        batch_def = source.add_dataframe_asset(name).add_batch_definition_whole_dataframe("all")
        suite = ctx.suites.add(gx.ExpectationSuite(name=name, expectations=expectations))
        vd = ctx.validation_definitions.add(gx.ValidationDefinition(name=name, data=batch_def, suite=suite))
        res = vd.run(
            batch_parameters={"dataframe": frame},
            result_format={
                "result_format": "COMPLETE",
                "unexpected_index_column_names": INDEX_COLUMNS[kind],
                "partial_unexpected_count": 0,
                "return_unexpected_index_query": False,
            },
        )
        raw = res.to_json_dict()
        problems, failed = problems_from_result(raw, batch_id, default_file, file_of)
        return Check(kind, scrub_result(raw), problems, failed)

    def trials(self, batch_id: str, frame: pd.DataFrame, file: str) -> Check:
        return self.run(batch_id, "trials", frame, trial_expectations(), file, lambda _: file)

    def stream(
        self,
        batch_id: str,
        kind: str,
        frame: pd.DataFrame,
        time_col: str,
        value_cols: Sequence[str],
        adc_max: int | None,
        default_file: str,
        file_of: Callable[[str], str],
    ) -> Check:
        return self.run(
            batch_id, kind, frame, stream_expectations(time_col, value_cols, adc_max), default_file, file_of
        )

    def streams(
        self, batch_id: str, frame: pd.DataFrame, default_file: str, file_of: Callable[[str], str]
    ) -> Check:
        return self.run(batch_id, "streams", frame, streams_expectations(self.params), default_file, file_of)


def ephemeral_context() -> AbstractDataContext:
    """An in-memory GX context: nothing written to disk, no usage statistics, no progress bars."""
    import great_expectations as gx
    from great_expectations.data_context.types.base import (
        DataContextConfig,
        InMemoryStoreBackendDefaults,
        ProgressBarsConfig,
    )

    # No usage statistics (no network in CI) and no tqdm bars cluttering `dvc repro` output.
    config = DataContextConfig(
        store_backend_defaults=InMemoryStoreBackendDefaults(),
        analytics_enabled=False,
        progress_bars=ProgressBarsConfig(globally=False),
    )
    return gx.get_context(mode="ephemeral", project_config=config)


def frame_dt(frame: pd.DataFrame, time_col: str) -> pd.Series:
    """Step from the previous sample of the same trial (NaN on each trial's first row)."""
    return frame.groupby("trial_id", sort=False)[time_col].diff()
