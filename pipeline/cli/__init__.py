"""`needlecue`: the commands a person runs by hand (the stages themselves run under `dvc repro`)."""

from __future__ import annotations

import typer

from pipeline.cli import batches, calibrate, registry, replay, runs
from pipeline.live import commands as live_commands
from pipeline.team import commands as team_commands

app = typer.Typer(add_completion=False, no_args_is_help=True, help=__doc__)

# in this order: `needlecue --help` lists the commands as they are added
app.command()(batches.simulate)
app.command("simulate-batch")(batches.simulate_batch)
app.command()(runs.repro)
app.command()(runs.retrain)
app.command()(batches.check)
app.command()(calibrate.calibrate)
app.command()(replay.replay)
app.command()(registry.rollback)
app.command()(registry.ui)
app.command("data-of")(registry.data_of)
app.add_typer(team_commands.team, name="team")
app.command("live")(live_commands.live)
app.command("emulate-rig")(live_commands.emulate_rig)
app.command("emulate-board")(live_commands.emulate_board)
app.command("unit-id")(live_commands.unit_id)
