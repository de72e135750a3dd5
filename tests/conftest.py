"""Shared fixtures: MLflow in a temp folder, the hand-made rig-log/1 batch and a writable copy of it, and a
web server that answers everything alike (`not_mlflow`)."""

from __future__ import annotations

import http.server
import os
import shutil
import sys
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest
from filelock import FileLock

from tests.projects import (
    Registered,
    build_tiny_project,
    copy_project,
    make_empty_store,
    new_store,
    register_into,
)

LAB_BENCH_A = Path(__file__).parent / "fixtures" / "rig-log" / "lab-bench-a"


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """The long tests first: the groups that run on one worker (the team stack, the emulated board
    and live pages) and the end-to-end runs marked slow, then the rest in their order. The two
    workers then end on short tests together instead of one idling while the other finishes a long
    one (`make test` ended with one worker idle for 68 s before this)."""
    long = ("slow", "xdist_group")
    items.sort(key=lambda item: not any(item.get_closest_marker(m) for m in long))  # stable


TIMELINE = "NEEDLECUE_TEST_TIMELINE"  # a file: each test's worker, start and end appended (where time goes)


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_protocol(item: pytest.Item) -> Iterator[None]:
    """With NEEDLECUE_TEST_TIMELINE set, one line per test (setup to teardown): the suite's timeline."""
    path = os.environ.get(TIMELINE)
    start = time.time()
    yield
    if path:
        worker = os.environ.get("PYTEST_XDIST_WORKER", "master")
        with open(path, "a") as f:
            f.write(f"{worker}\t{start:.2f}\t{time.time():.2f}\t{item.nodeid}\n")


@pytest.fixture(autouse=True)
def mlflow_http_settings_restored() -> Iterator[None]:
    """MLflow reads its HTTP timeout and retries from the process's environment at every request, so
    a test must leave them as it found them: a poll still running in a thread after its test ends
    changes them under the tests that follow."""
    keys = ("MLFLOW_HTTP_REQUEST_TIMEOUT", "MLFLOW_HTTP_REQUEST_MAX_RETRIES")
    before = {k: os.environ.get(k) for k in keys}
    yield
    after = {k: os.environ.get(k) for k in keys}
    assert after == before, f"MLflow's HTTP settings changed by this test: {before} -> {after}"


@pytest.fixture
def lab_bench_a() -> Path:
    """The committed fixture folder (read it, never write it)."""
    return LAB_BENCH_A


@pytest.fixture
def raw_dir(tmp_path: Path) -> Path:
    """tmp_path/raw holding a copy of lab-bench-a that a test may break."""
    raw = tmp_path / "raw"
    shutil.copytree(LAB_BENCH_A, raw / "lab-bench-a")
    return raw


@pytest.fixture(autouse=True)
def mlflow_store(
    empty_store: Path, tmp_path_factory: pytest.TempPathFactory, monkeypatch: pytest.MonkeyPatch
) -> Iterator[str]:
    """Every test's MLflow store is a new, empty sqlite store in a temp folder (a copy of `empty_store`),
    never the project's mlflow.db. A copy the test left as it was is removed after it (the suite would
    keep about 1 MB per test)."""
    folder = tmp_path_factory.mktemp("mlflow")
    uri = new_store(empty_store, folder)
    made = _sqlite_version(folder / "mlflow.db")
    monkeypatch.setenv("MLFLOW_TRACKING_URI", uri)
    monkeypatch.setenv("MLFLOW_REGISTRY_URI", uri)
    yield uri
    if _sqlite_version(folder / "mlflow.db") == made and [p.name for p in folder.iterdir()] == ["mlflow.db"]:
        (folder / "mlflow.db").unlink()
    # registry.connect() sets MLflow's process-wide URIs, which win over the environment: forget them
    if "mlflow" in sys.modules:
        mlflow = sys.modules["mlflow"]
        mlflow.set_tracking_uri(None)
        mlflow.set_registry_uri(None)


def _sqlite_version(db: Path) -> tuple[int, bytes] | None:
    """A sqlite file's size and its header's change counter (bytes 24-27, which every committed write
    moves), None when it is gone: the same twice means nothing was written in between."""
    try:
        with db.open("rb") as f:
            return db.stat().st_size, f.read(28)[24:]
    except FileNotFoundError:
        return None


def _built_once(
    factory: pytest.TempPathFactory, worker_id: str, name: str, build: Callable[[Path], object]
) -> Path:
    """The folder `name` that `build` makes, made once per test session and shared by the xdist workers
    (the first makes it, the others wait for it)."""
    base = factory.getbasetemp()
    shared = base if worker_id == "master" else base.parent  # xdist: the folder every worker's temp is in
    root = shared / name
    with FileLock(shared / f"{name}.lock"):
        if not (shared / f"{name}.done").exists():
            shutil.rmtree(root, ignore_errors=True)  # what a failed worker left half done
            build(root)
            (shared / f"{name}.done").touch()
    return root


@pytest.fixture(scope="session")
def empty_store(tmp_path_factory: pytest.TempPathFactory, worker_id: str) -> Path:
    """A folder with an empty MLflow sqlite store, its tables made once per session: take a copy with
    `tests.projects.new_store` (every test's `mlflow_store` is one)."""
    return _built_once(tmp_path_factory, worker_id, "empty-store", make_empty_store)


@pytest.fixture(scope="session")
def tiny_built(tmp_path_factory: pytest.TempPathFactory, worker_id: str) -> Path:
    """The small simulated project reproduced through every stage but register, shared by the tests of
    a session; never write into it: take a copy with `tests.projects.copy_project`."""
    return _built_once(tmp_path_factory, worker_id, "tiny-built", build_tiny_project)


@pytest.fixture(scope="session")
def tiny_registered(tiny_built: Path, tmp_path_factory: pytest.TempPathFactory, worker_id: str) -> Registered:
    """`tiny_built` registered into a store of its own, shared by the tests of a session; never write
    into either."""

    def build(root: Path) -> None:
        root.mkdir()
        copy_project(tiny_built, root / "project")
        register_into(root / "project", root / "store")

    root = _built_once(tmp_path_factory, worker_id, "tiny-registered", build)
    return Registered(root / "project", root / "store")


class _Answers(http.server.BaseHTTPRequestHandler):
    """Answers every request with the same status and body, as a misconfigured proxy or web app might."""

    status = 200
    body = b"{}"
    seen: list[str]

    def _answer(self) -> None:
        self.seen.append(f"{self.command} {self.path.split('?')[0]}")
        length = int(self.headers.get("Content-Length") or 0)
        self.rfile.read(length)
        self.send_response(self.status)
        self.send_header("Content-Type", "application/json")
        self.send_header("Content-Length", str(len(self.body)))
        self.end_headers()
        self.wfile.write(self.body)

    do_GET = do_POST = do_PATCH = do_DELETE = _answer

    def log_message(self, *args: object) -> None:  # quiet
        pass


@pytest.fixture
def not_mlflow(request: pytest.FixtureRequest) -> Iterator[tuple[str, list[str]]]:
    """http://127.0.0.1:<port> of a server answering `request.param` (status, body; default 200 and
    `{}`) to everything, and the requests it saw."""
    seen: list[str] = []
    status, body = getattr(request, "param", (200, b"{}"))
    handler = type("H", (_Answers,), {"status": status, "body": body, "seen": seen})
    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), handler)
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    try:
        yield f"http://127.0.0.1:{server.server_address[1]}", seen
    finally:
        server.shutdown()
        server.server_close()
