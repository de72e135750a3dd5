"""The publisher (`pipeline.team.publisher`) as a server of the stack: on every alias change, MLflow's
webhook has it publish the new version to the simulators' bucket."""

from __future__ import annotations

import sys

from pipeline.team.servers.base import Launch, Server


class Publisher(Server):
    name = "publisher"

    @property
    def address(self) -> str:
        """Where MLflow's webhook reaches it."""
        return f"http://{self.stack.host}:{self.port}/mlflow"

    def launch(self) -> Launch:
        cmd = [sys.executable, "-m", "pipeline.team.publisher", str(self.stack.dir)]
        return Launch(cmd, {"PYTHONUNBUFFERED": "1"}, self.stack.dir)
