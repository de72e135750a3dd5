"""One server's lifecycle (`pipeline.team.servers.base.Server`): spawned, waited for until it answers,
found again by its pid, stopped; a server that exits while starting is reported with its log. On a
small HTTP server, not the stack's: the protocol is what every server of the stack shares."""

from __future__ import annotations

import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pytest

from pipeline.team.servers.base import Launch, Ports, Server, StackError
from pipeline.team.stack import free_base_port

pytestmark = [pytest.mark.team, pytest.mark.xdist_group("team")]


@dataclass
class View:
    """The least of a stack a server reads."""

    dir: Path
    ports: Ports
    host: str = "127.0.0.1"
    settings: dict[str, Any] = field(default_factory=dict)
    tracking_uri: str = ""
    s3_endpoint: str = ""

    def database_uri(self, database: str) -> str:
        return ""


class Http(Server):
    """Python's own HTTP server, or with `fails` a command that prints a complaint and exits."""

    name = "http"
    fails = False

    @property
    def port(self) -> int:
        return self.stack.ports.base

    def launch(self) -> Launch:
        if self.fails:
            cmd = [sys.executable, "-c", "print('bad config: no such bucket'); raise SystemExit(3)"]
        else:
            cmd = [sys.executable, "-m", "http.server", str(self.port), "--bind", self.stack.host]
        return Launch(cmd, {}, self.stack.dir)


def test_a_server_is_started_found_by_its_pid_and_stopped(tmp_path: Path) -> None:
    # given: a server not started
    server = Http(View(tmp_path, Ports(free_base_port())))
    assert not server.running() and server.pid() is None
    try:
        # when: it starts
        server.start()
        # then: it answers, its pid is recorded and alive, its output goes to its log
        assert server.running() and server.pid() == int(server.pid_file.read_text())
        assert server.log == tmp_path / "logs" / "http.log" and server.log.is_file()
        with pytest.raises(StackError, match=r"http: port\(s\) \[\d+\] on 127.0.0.1 are taken"):
            Http(server.stack).check_ports_free()
    finally:
        # when: it is stopped; then: it was running, and is no longer
        assert server.stop()
    assert not server.running() and server.pid() is None
    assert not server.stop()  # nothing left to stop


def test_a_server_that_exits_while_starting_is_reported_with_its_log(tmp_path: Path) -> None:
    # given: a server whose command exits at once, saying why
    server = Http(View(tmp_path, Ports(free_base_port())))
    server.fails = True
    # when / then: starting it fails naming the server, its log and the log's last lines
    reported = r"(?s)http: exited while starting; its log: .*http\.log\n.*bad config"
    with pytest.raises(StackError, match=reported):
        server.start()
