"""Stages in a warm interpreter (pipeline/execution/preload.py): what a stage process sees and does is what a
fresh `python -m` would see and do, and nothing outlives its caller."""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from pipeline.execution import preload
from pipeline.execution import run as launcher
from tests.projects import copy_project

PROBE = """
import json, os, sys, time
out = {"argv": sys.argv[1:], "cwd": os.getcwd(), "env": os.environ.get("NEEDLECUE_PROBE"),
       "pid": os.getpid(), "cpus": sorted(os.sched_getaffinity(0))}
print(json.dumps(out), flush=True)
print("to stderr", file=sys.stderr, flush=True)
if "--sleep" in sys.argv:
    open("sleeping", "w").write(str(os.getpid()))
    time.sleep(60)
if "--fail" in sys.argv:
    raise RuntimeError("the probe failed")
sys.exit(int(sys.argv[1]) if sys.argv[1:] and sys.argv[1].isdigit() else 0)
"""
CLIENT = """import os, sys
from pipeline.execution import preload
status = preload.run_stage(sys.argv[1:], dict(os.environ))
sys.exit(99 if status is None else status)  # 99: no server took it
"""


RIGHTS = """
import json, sys
out = {}
try:
    open(sys.argv[1]).read()
    out["read"] = "read"
except PermissionError:
    out["read"] = "refused"
try:
    open(sys.argv[2], "a").write("x")
    out["write"] = "written"
except PermissionError:
    out["write"] = "refused"
print(json.dumps(out), flush=True)
"""
LAUNCH = """import os, sys
from pipeline.execution import preload
if preload.run_stage(sys.argv[1:], dict(os.environ)) is None:  # as pipeline.execution.run: else fresh
    os.execv(sys.executable, [sys.executable, "-m", *sys.argv[1:]])
"""
ASK = """import json, os, sys
from pathlib import Path
from pipeline.execution import preload
print(json.dumps(preload.ask(Path(sys.argv[1]), sys.argv[2:], dict(os.environ))))
"""
WITHOUT_DAC = ["setpriv", "--bounding-set", "-dac_override,-dac_read_search", "--"]


def _has_dac_override() -> bool:
    """Whether this process may ignore file permissions (CAP_DAC_OVERRIDE, bit 1), as root does."""
    eff = preload.identity().get("CapEff")
    return eff is not None and bool(int(eff, 16) & 0b10)


@pytest.fixture
def sockets() -> Iterator[str]:
    """A private folder for the tests' servers, short enough for a Unix socket's address."""
    folder = tempfile.mkdtemp(prefix="nc-", dir="/tmp")
    yield folder
    shutil.rmtree(folder, ignore_errors=True)


def wait_ready(env: dict[str, str], seconds: float = 120) -> Path:
    """The socket of the server for `env`, once its log says it serves."""
    socket = preload.socket_path(env)
    assert socket is not None
    log = socket.with_suffix(".log")
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline and not (log.is_file() and "preload: ready" in log.read_text()):
        time.sleep(0.1)
    assert log.is_file() and "preload: ready" in log.read_text(), (
        log.read_text() if log.is_file() else "no log"
    )
    return socket


def server_log(env: dict[str, str]) -> str:
    """What the server for `env` logged (why it refused a caller, say)."""
    socket = preload.socket_path(env)
    log = None if socket is None else socket.with_suffix(".log")
    return log.read_text() if log is not None and log.is_file() else "no log"


@pytest.fixture
def warm(tmp_path: Path, sockets: str) -> dict[str, str]:
    """An environment with its own preload folder, and a server for it (light: json only) running."""
    env = dict(os.environ, NEEDLECUE_PRELOAD_DIR=sockets, NEEDLECUE_PRELOAD_MODULES="json")
    env["PYTHONPATH"] = str(
        Path(__file__).resolve().parents[1]
    )  # the clients import pipeline.execution.preload
    assert preload.run_stage(["json.tool", "--help"], env) is None  # none yet: one is started
    wait_ready(env)
    (tmp_path / "probe_stage.py").write_text(PROBE)
    return env


def _client(cwd: Path, env: dict[str, str], *argv: str, **kw) -> subprocess.Popen:
    cmd = [sys.executable, "-c", CLIENT, "probe_stage", *argv]
    pipes = {"stdout": subprocess.PIPE, "stderr": subprocess.PIPE}
    return subprocess.Popen(cmd, cwd=cwd, env=env, text=True, **pipes, **kw)


def test_a_stage_gets_the_callers_arguments_folder_environment_and_output_and_its_exit_status(
    warm: dict[str, str], tmp_path: Path
) -> None:
    # given: a warm server; when: a caller in its own folder, with its own value of a variable the
    # stages read as they run (not part of the server's key), runs the probe
    client = _client(tmp_path, {**warm, "NEEDLECUE_PROBE": "mine"}, "3", "b")
    out, err = client.communicate(timeout=60)
    assert client.returncode != 99, f"no server took the stage; its log:\n{server_log(warm)}\n{err}"
    # then: the probe ran in a process of the server's, saw what the caller has, wrote to the
    # caller's stdout and stderr, and its exit status is the caller's
    seen = json.loads(out)
    assert seen["argv"] == ["3", "b"] and seen["cwd"] == str(tmp_path) and seen["env"] == "mine"
    assert seen["pid"] != client.pid and seen["cpus"] == sorted(os.sched_getaffinity(0))
    assert "to stderr" in err
    assert client.returncode == 3


def test_copies_of_a_project_on_their_own_import_paths_share_a_server_and_each_runs_its_own_code(
    warm: dict[str, str], tmp_path: Path
) -> None:
    # given: a warm server, and two copies of a project, each with its own package `mine` on its
    # PYTHONPATH (as each copy of this project puts its own client/ there)
    (tmp_path / "who_stage.py").write_text("import mine\nprint(mine.WHO)\n")
    envs = {}
    for copy in ("a", "b"):
        (tmp_path / copy / "mine").mkdir(parents=True)
        (tmp_path / copy / "mine" / "__init__.py").write_text(f"WHO = {copy!r}\n")
        envs[copy] = {**warm, "PYTHONPATH": os.pathsep.join([str(tmp_path / copy), warm["PYTHONPATH"]])}
    # when: each runs the stage
    outs = {}
    for copy, env in envs.items():
        done = subprocess.run(
            [sys.executable, "-c", CLIENT, "who_stage"], cwd=tmp_path, env=env, capture_output=True, text=True
        )
        assert done.returncode == 0, f"{done.stderr}\n{server_log(warm)}"
        outs[copy] = done.stdout.strip()
    # then: the one server ran both, each with its own copy's code
    assert preload.socket_path(envs["a"]) == preload.socket_path(envs["b"]) == preload.socket_path(warm)
    assert outs == {"a": "a", "b": "b"}
    assert server_log(warm).count("who_stage") == 2


def test_a_caller_whose_path_finds_a_preloaded_library_elsewhere_is_refused(tmp_path: Path) -> None:
    # given: a server that preloaded colorsys, and a caller whose PYTHONPATH has a colorsys of its own
    sockets = tempfile.mkdtemp(prefix="nc-", dir="/tmp")
    repo = str(Path(__file__).resolve().parents[1])
    env = dict(
        os.environ, NEEDLECUE_PRELOAD_DIR=sockets, NEEDLECUE_PRELOAD_MODULES="colorsys", PYTHONPATH=repo
    )
    try:
        client = [sys.executable, "-c", CLIENT, "json.tool", "--help"]
        assert subprocess.run(client, env=env, capture_output=True).returncode == 99  # starts the server
        wait_ready(env)
        (tmp_path / "shadow").mkdir()
        (tmp_path / "shadow" / "colorsys.py").write_text("")
        shadowed = {**env, "PYTHONPATH": os.pathsep.join([str(tmp_path / "shadow"), repo])}
        # when: each asks the server
        served = subprocess.run(client, env=env, capture_output=True, text=True)
        refused = subprocess.run(client, env=shadowed, capture_output=True, text=True)
        # then: the first is served; the second is refused (a fresh interpreter would load its own
        # colorsys), and the server says why
        assert served.returncode == 0, served.stderr
        assert refused.returncode == 99, refused.stderr
        assert "its import path finds colorsys elsewhere" in server_log(env)
    finally:
        shutil.rmtree(sockets, ignore_errors=True)


def test_a_stage_that_raises_prints_its_traceback_and_fails(warm: dict[str, str], tmp_path: Path) -> None:
    client = _client(tmp_path, warm, "--fail")
    _, err = client.communicate(timeout=60)
    assert client.returncode == 1
    assert "RuntimeError: the probe failed" in err


def test_ctrl_c_reaches_the_stage_and_a_killed_caller_takes_its_stage_along(
    warm: dict[str, str], tmp_path: Path
) -> None:
    # given: a stage that sleeps, started through the server
    client = _client(tmp_path, warm, "--sleep")
    pidfile = tmp_path / "sleeping"
    deadline = time.monotonic() + 30
    while not pidfile.exists() and time.monotonic() < deadline:
        time.sleep(0.05)
    # when: Ctrl-C reaches the caller
    client.send_signal(signal.SIGINT)
    client.communicate(timeout=30)
    # then: the stage got it and ended as Python does on Ctrl-C
    assert client.returncode == 128 + signal.SIGINT
    # given: another sleeping stage; when: its caller is killed outright
    pidfile.unlink()
    client = _client(tmp_path, warm, "--sleep")
    deadline = time.monotonic() + 30
    while not pidfile.exists() and time.monotonic() < deadline:
        time.sleep(0.05)
    stage = int(pidfile.read_text())
    client.kill()
    client.wait(timeout=10)
    # then: the stage is stopped too
    deadline = time.monotonic() + 15
    while Path(f"/proc/{stage}").exists() and time.monotonic() < deadline:
        time.sleep(0.1)
    assert not Path(f"/proc/{stage}").exists()


@pytest.mark.skipif(not (_has_dac_override() and shutil.which("setpriv")), reason="needs root and setpriv")
def test_a_caller_without_a_capability_of_the_server_gets_what_a_fresh_interpreter_gives(
    warm: dict[str, str], tmp_path: Path
) -> None:
    # given: a warm server of a root caller, a file nobody may read (000), a read-only store (0444)
    (tmp_path / "rights_stage.py").write_text(RIGHTS)
    secret, store = tmp_path / "secret", tmp_path / "mlflow.db"
    secret.write_text("s")
    store.write_text("")
    secret.chmod(0o000)
    store.chmod(0o444)
    launch = [sys.executable, "-c", LAUNCH, "rights_stage", str(secret), str(store)]

    def run(prefix: list[str], env: dict[str, str]) -> dict[str, str]:
        done = subprocess.run([*prefix, *launch], cwd=tmp_path, env=env, capture_output=True, text=True)
        assert done.returncode == 0, done.stderr
        return json.loads(done.stdout)

    # when: a caller that has given up overriding file permissions runs the stage, preload on and off
    warm_run = run(WITHOUT_DAC, warm)
    fresh_run = run(WITHOUT_DAC, {**warm, "NEEDLECUE_PRELOAD": "0"})
    # then: the same: refused both, as the caller's own rights say; while the server's own kind of
    # caller (root) reads and writes both through it
    assert warm_run == fresh_run == {"read": "refused", "write": "refused"}
    assert run([], warm) == {"read": "read", "write": "written"}
    # and the server itself refuses such a caller that knocks on its socket, in one line of its log
    socket = preload.socket_path(warm)
    assert socket is not None
    asked = subprocess.run(
        [*WITHOUT_DAC, sys.executable, "-c", ASK, str(socket), "rights_stage", str(secret), str(store)],
        cwd=tmp_path,
        env=warm,
        capture_output=True,
        text=True,
    )
    assert json.loads(asked.stdout) == "refused", asked.stderr
    assert "refused caller" in socket.with_suffix(".log").read_text()


def test_the_key_follows_the_callers_umask() -> None:
    env = launcher.pinned_env({"PATH": "/usr/bin"})
    before = preload.key(env)
    old = os.umask(0o077)
    try:
        changed = preload.key(env)
    finally:
        os.umask(old)
    assert changed != before == preload.key(env)
    assert {"Uid", "Gid", "Groups", "CapEff", "CapBnd", "Umask", "limits"} <= set(preload.identity())


def test_a_socket_path_too_long_for_unix_means_no_server(tmp_path: Path) -> None:
    # given: a preload folder whose socket address would not fit
    env = dict(os.environ, NEEDLECUE_PRELOAD_DIR=str(tmp_path / ("x" * 120)))
    # then: the caller runs its stage itself, and starts no server that could not bind
    assert preload.socket_path(env) is None
    assert preload.run_stage(["probe_stage"], env) is None
    assert not list((tmp_path / ("x" * 120)).iterdir())


def test_without_a_server_the_caller_runs_the_stage_itself(tmp_path: Path) -> None:
    # given: preloading turned off
    env = dict(os.environ, NEEDLECUE_PRELOAD="0", NEEDLECUE_PRELOAD_DIR=str(tmp_path / "sockets"))
    # then: no server is asked or started
    assert preload.run_stage(["probe_stage"], env) is None
    assert not (tmp_path / "sockets").exists()


def test_a_shared_folder_is_refused(tmp_path: Path) -> None:
    folder = tmp_path / "open"
    folder.mkdir(mode=0o777)
    folder.chmod(0o777)
    with pytest.raises(PermissionError, match="not a private folder"):
        preload.socket_dir({"NEEDLECUE_PRELOAD_DIR": str(folder)})


def test_the_key_ignores_what_stages_read_when_they_run_and_not_what_libraries_read_as_they_load() -> None:
    base = launcher.pinned_env({"PATH": "/usr/bin", "HOME": "/root"})
    runtime = {**base, "MLFLOW_TRACKING_URI": "sqlite:///x.db", "DVC_STAGE": "train@15-ls", "PWD": "/x"}
    loading = {**base, "ATEN_CPU_CAPABILITY": "avx2"}
    assert preload.key(runtime) == preload.key(base) != preload.key(loading)


@pytest.mark.slow
def test_a_stage_writes_the_same_bytes_warm_and_fresh(tiny_built: Path, tmp_path: Path, sockets: str) -> None:
    # given: a copy of the small project and a server with the real preload list
    root, _ = copy_project(tiny_built, tmp_path / "project")
    env = launcher.pinned_env(dict(os.environ, NEEDLECUE_PRELOAD_DIR=sockets))
    cmd = [sys.executable, "-m", "pipeline.execution.run", "train", "fnn", "data/processed/15"]
    choice = ["--choice", "data/choices/fnn.json"]
    subprocess.run([*cmd, "fresh", *choice], cwd=root, env={**env, "NEEDLECUE_PRELOAD": "0"}, check=True)
    subprocess.run([*cmd, "first", *choice], cwd=root, env=env, check=True)  # starts the server
    socket = wait_ready(env)
    # when: the same stage runs in a warm process
    done = subprocess.run([*cmd, "warm", *choice], cwd=root, env=env, capture_output=True, text=True)
    # then: the server ran it, and it wrote the fresh run's bytes
    assert done.returncode == 0, done.stderr
    assert "pipeline.stages.train fnn data/processed/15 warm" in socket.with_suffix(".log").read_text()
    assert (root / "warm" / "model.pt").read_bytes() == (root / "fresh" / "model.pt").read_bytes()
    assert (root / "first" / "model.pt").read_bytes() == (root / "fresh" / "model.pt").read_bytes()
