"""Rendering stored Great Expectations results as a GX Data Docs site, byte-identical for the
same results (the ingest report's `data_docs/index.html`).
"""

from __future__ import annotations

import datetime as dt
import json
import re
import shutil
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from pipeline.rig.expectations import ephemeral_context

FIXED_RUN_TIME = dt.datetime(2000, 1, 1, tzinfo=dt.UTC)
_CACHE_BUSTER = re.compile(r"\?d=\d{8}T\d{6}\.\d+Z")
_UUID = re.compile(r"[0-9a-f]{8}-[0-9a-f]{4}-[0-9a-f]{4}-[0-9a-f]{4}-[0-9a-f]{12}")


def _deterministic_html(text: str) -> str:
    """Drop GX's render-time cache-buster and number its random element ids in page order."""
    ids: dict[str, str] = {}
    text = _CACHE_BUSTER.sub("", text)
    return _UUID.sub(lambda m: ids.setdefault(m.group(0), f"el{len(ids) + 1}"), text)


def write_data_docs(
    results: Mapping[str, Mapping[str, Mapping[str, Any]]],
    site_dir: Path,
    run_time: dt.datetime | None = None,
) -> Path:
    """Render stored (scrubbed) GX results {batch_id: {kind: result}} as a GX Data Docs site.

    A fresh ephemeral context gets each result back in its validation-results store (with a
    run id, which the renderer needs) and its suite, then `build_data_docs` writes the HTML
    through a TupleFilesystemStoreBackend rooted at `site_dir`. Reused batches were not
    validated in this run, so this is the only way their results reach the site.
    Returns the path of index.html.
    """
    import great_expectations as gx
    from great_expectations.core.expectation_validation_result import (
        expectationSuiteValidationResultSchema,
    )
    from great_expectations.core.run_identifier import RunIdentifier
    from great_expectations.data_context.types.resource_identifiers import (
        ExpectationSuiteIdentifier,
        ValidationResultIdentifier,
    )
    from great_expectations.expectations.expectation_configuration import ExpectationConfiguration

    if site_dir.exists():
        shutil.rmtree(site_dir)
    site_dir.mkdir(parents=True)
    ctx = ephemeral_context()
    ctx.add_data_docs_site(
        "local_site",
        {
            "class_name": "SiteBuilder",
            # GX wants an absolute base_directory; dvc.yaml passes relative paths.
            "store_backend": {
                "class_name": "TupleFilesystemStoreBackend",
                "base_directory": str(site_dir.resolve()),
            },
            "site_index_builder": {"class_name": "DefaultSiteIndexBuilder"},
        },
    )
    # GX needs a run time; a fixed one keeps the site byte-identical for the same data, so
    # reports/ingest (a DVC output) does not change between identical runs.
    run_id = RunIdentifier(run_name="ingest", run_time=run_time or FIXED_RUN_TIME)
    for batch_id in sorted(results):
        for kind, stored in sorted(results[batch_id].items()):
            data = json.loads(json.dumps(stored))
            data.setdefault("meta", {})["run_id"] = run_id
            suite = gx.ExpectationSuite(name=data["suite_name"])
            for r in data.get("results", []):
                cfg = dict(r["expectation_config"])
                cfg["kwargs"] = {k: v for k, v in cfg.get("kwargs", {}).items() if k != "batch_id"}
                suite.add_expectation_configuration(ExpectationConfiguration(**cfg))
            if data["suite_name"] not in {s.name for s in ctx.suites.all()}:
                ctx.suites.add(suite)
            key = ValidationResultIdentifier(
                expectation_suite_identifier=ExpectationSuiteIdentifier(name=data["suite_name"]),
                run_id=run_id,
                batch_identifier=f"{batch_id}-{kind}",
            )
            ctx.validation_results_store.set(key, expectationSuiteValidationResultSchema.load(data))
    ctx.build_data_docs()
    for page in site_dir.rglob("*.html"):
        page.write_text(_deterministic_html(page.read_text()))
    index = site_dir / "index.html"
    if not index.exists():  # pragma: no cover - GX behaviour changed; keep the report usable
        index.write_text(_fallback_html(results))
    return index


def _fallback_html(results: Mapping[str, Mapping[str, Mapping[str, Any]]]) -> str:
    rows = "".join(
        f"<tr><td>{b}</td><td>{k}</td><td>{'pass' if r.get('success') else 'FAIL'}</td></tr>"
        for b in sorted(results)
        for k, r in sorted(results[b].items())
    )
    return f"<html><body><h1>Ingest validation</h1><table>{rows}</table></body></html>"
