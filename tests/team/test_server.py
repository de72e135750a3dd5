"""The team's MLflow server on a loaded machine: a worker that cannot answer for a while (no CPU for it:
the pipeline and the tests share 2 cores) is waited for, instead of being killed with the requests it
holds; and the server runs nothing a registry does not need."""

from __future__ import annotations

import contextlib
import os
import signal
import time
from concurrent.futures import ThreadPoolExecutor

import pytest
import requests

from tests.helpers import descendants

# the real servers, on one xdist worker (their tests share one stack), in file order
pytestmark = [pytest.mark.team, pytest.mark.xdist_group("team")]
SEARCH = "/api/2.0/mlflow/registered-models/search"
STALL_S = 8  # longer than uvicorn's default worker health check (5 s)


def _server_pid(team) -> int:
    pid = team.status()["mlflow"]["pid"]
    assert pid is not None, "the team's MLflow server is not running"
    return pid


def _workers(team) -> set[int]:
    """The pids of the uvicorn worker processes serving the team's MLflow."""
    # multiprocessing's spawned children (uvicorn's resource tracker is started another way)
    return {child for child, line in descendants(_server_pid(team)).items() if "spawn_main" in line}


def _resume(workers: set[int]) -> None:
    for pid in workers:
        with contextlib.suppress(ProcessLookupError):  # killed meanwhile: the test's assertions say so
            os.kill(pid, signal.SIGCONT)


def test_a_worker_that_stalls_longer_than_uvicorns_health_check_is_not_replaced(team):
    # Given the server's workers, answering
    auth = ("lab", team.settings["passwords"]["lab"])
    requests.get(team.tracking_uri + SEARCH, auth=auth, timeout=20).raise_for_status()
    workers = _workers(team)
    assert workers, "no uvicorn workers found under the MLflow server"
    # When every worker stalls for 8 s (stopped, as a process given no CPU is) while a request waits.
    # (A new connection: one kept alive is closed by uvicorn's own 5-s idle timeout as a worker resumes.)
    try:
        for pid in workers:
            os.kill(pid, signal.SIGSTOP)
        with ThreadPoolExecutor(max_workers=1) as pool:
            answer = pool.submit(requests.get, team.tracking_uri + SEARCH, auth=auth, timeout=60)
            time.sleep(STALL_S)
            _resume(workers)
            # Then the request is answered, and every worker is the one it was: none was killed (with
            # the requests it held) and replaced
            assert answer.result(timeout=60).status_code == 200
    finally:
        _resume(workers)
    assert _workers(team) == workers


def test_the_server_runs_its_workers_and_no_job_runner(team):
    # Given the team's MLflow server, answering
    # When its processes are listed
    running = list(descendants(_server_pid(team)).values())
    # Then its uvicorn workers are there, and none of MLflow's job runner (huey consumers for GenAI jobs:
    # eight processes, 1.9 GB, that a model registry never uses)
    assert _workers(team) and any("uvicorn" in line for line in running), running
    assert not [line for line in running if "huey" in line], running
