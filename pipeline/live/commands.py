"""The live commands of `needlecue` (`pipeline.cli` registers them): `live`, `emulate-rig`,
`emulate-board`, `unit-id`, and the
client every command that runs the champion builds (`load_client`). Heavy imports stay inside the
functions, so `needlecue --help` stays quick."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Annotated, Any

import typer

from pipeline.exits import fail


def load_client(
    angle: float | None,
    alias: str,
    model_dir: Path | None,
    unit_id: str | None,
    cues_uncalibrated: bool = False,
    unverified: bool = False,
) -> Any:
    """The champion (or `model_dir`) with unit `unit_id`'s registered calibration, as the simulator
    loads it; `unverified` runs a `model_dir` that fails its check, after a loud warning. Raises what
    the client raises (RegistryUnreachable, ValueError incl. ModelRefused, LookupError, ...)."""
    from needlecue_client import ForceClient

    if model_dir is None:
        if angle is None:
            raise ValueError("give --angle (the preset angle whose model to fetch) or --model-dir")
        if unverified:
            raise ValueError("--unverified is for --model-dir only: a fetched champion is always checked")
        return ForceClient.from_registry(angle, alias, unit_id=unit_id, cues_uncalibrated=cues_uncalibrated)
    calibration = None
    if unit_id is not None:  # the unit's registered calibration, if there is one
        from needlecue_client import ModelNotFound, fetch_unit
        from needlecue_runtime.registry.store import RegistryUnreachable
        from needlecue_runtime.unit_calibration import FILE

        try:
            calibration = fetch_unit(unit_id) / FILE
        except (ModelNotFound, RegistryUnreachable) as e:
            typer.echo(f"warning: no calibration of unit {unit_id}: {e}", err=True)
    client = ForceClient.from_dir(
        model_dir,
        calibration=calibration,
        unit_id=unit_id,
        cues_uncalibrated=cues_uncalibrated,
        unverified=unverified,
    )
    if unverified:
        typer.echo(
            f"WARNING: {model_dir} runs UNVERIFIED (--unverified): its forces and cues may be wrong", err=True
        )
    if angle is not None and client.angle_deg != angle:
        raise ValueError(f"--angle {angle:g} but the model in {model_dir} is for {client.angle_deg:g}°")
    return client


AngleOption = Annotated[
    float | None, typer.Option("--angle", help="preset insertion angle (deg) whose champion is fetched")
]
AliasOption = Annotated[str, typer.Option("--alias", help="registry alias of the model")]
ModelDirOption = Annotated[
    Path | None, typer.Option("--model-dir", help="an already-fetched model folder (skips the registry)")
]
UnverifiedOption = Annotated[
    bool,
    typer.Option(
        "--unverified",
        help="run a --model-dir whose graph or description is not what was registered (loudly)",
    ),
]


def live(
    port: Annotated[str, typer.Option("--port", help="the estimator's serial port, e.g. /dev/ttyACM0")],
    angle: AngleOption = None,
    unit: Annotated[
        str | None, typer.Option("--unit", help="the estimator unit: its registered calibration is applied")
    ] = None,
    alias: AliasOption = "champion",
    model_dir: ModelDirOption = None,
    baud: Annotated[int, typer.Option(help="the port's baud rate (the firmware sends at 115200)")] = 115200,
    adc_bits: Annotated[
        int | None, typer.Option(help="ADC resolution (default: the firmware's banner, else 10)")
    ] = None,
    vref: Annotated[
        float | None, typer.Option("--vref", help="ADC full scale, V (default: the banner's, else 5.0)")
    ] = None,
    record: Annotated[
        Path | None, typer.Option("--record", help="the session folder (default recordings/live-DATE-TIME)")
    ] = None,
    http_port: Annotated[int, typer.Option(help="the trainee page's port on 127.0.0.1 (0: any free)")] = 8770,
    reset_wait: Annotated[float, typer.Option(help="seconds to wait out the board's reset on connect")] = 2.0,
    insertions: Annotated[
        int | None, typer.Option(help="stop after this many insertions (default: run until Ctrl-C)")
    ] = None,
    duration: Annotated[float | None, typer.Option(help="stop after this many seconds")] = None,
    give_up: Annotated[
        float | None, typer.Option(help="stop when the port has been gone this many seconds")
    ] = None,
    cues_uncalibrated: Annotated[
        bool, typer.Option(help="show angle cues even for an uncalibrated unit (not advised)")
    ] = False,
    unverified: UnverifiedOption = False,
) -> None:
    """Run the champion and the cue tracker live on the estimator's serial stream: the trainee's page
    (http://127.0.0.1:8770/), a terminal line, and a recording `needlecue replay` plays back.

    Exit 1 on a bad model or unit, 2 if the registry is unreachable and nothing is cached."""
    from needlecue_runtime.registry.store import RegistryUnreachable
    from pipeline.live.app import LiveOptions, run_live

    try:
        client = load_client(angle, alias, model_dir, unit, cues_uncalibrated, unverified)
    except RegistryUnreachable as e:
        raise fail(str(e), 2) from e
    except (FileNotFoundError, ValueError, LookupError) as e:
        raise fail(str(e)) from e
    options = LiveOptions(
        port=port,
        baud=baud,
        adc_bits=adc_bits,
        vref_v=vref,
        session_dir=record,
        http_port=http_port,
        reset_wait_s=reset_wait,
        insertions=insertions,
        duration_s=duration,
        give_up_s=give_up,
    )
    try:
        summary = run_live(client, options, say=typer.echo, cues_uncalibrated=cues_uncalibrated)
    except (FileExistsError, OSError, ValueError) as e:
        raise fail(str(e)) from e
    typer.echo("")
    for ins in summary["insertions"]:
        typer.echo(
            f"insertion {ins['number']} ({ins['trial_id']}): {' -> '.join(ins['cues'])} [{ins['ended']}]"
        )
    typer.echo(f"stream: {json.dumps(summary['counts'], sort_keys=True)}")
    typer.echo(f"recorded {summary['recording']} ({summary['stopped']})")


def emulate_rig(
    trials: Annotated[
        list[Path],
        typer.Argument(help="rig-log/1 estimator files (<batch>/<trial>.fsr.csv), played in order"),
    ],
    link: Annotated[
        Path | None, typer.Option(help="a symlink to the pseudo-terminal, for `needlecue live --port`")
    ] = None,
    pause: Annotated[float, typer.Option(help="seconds at rest before, between and after the trials")] = 3.0,
    speed: Annotated[float, typer.Option(help="playback speed (1: the real rate)")] = 1.0,
    baud: Annotated[int, typer.Option(help="the baud rate the emulated firmware sends at")] = 115200,
    pull_at: Annotated[float | None, typer.Option(help="pull the cable at this second")] = None,
    replug_after: Annotated[
        float | None, typer.Option(help="plug it in again after this many seconds")
    ] = None,
    garbage_at: Annotated[list[float] | None, typer.Option(help="send garbage bytes at this second")] = None,
    stall_at: Annotated[float | None, typer.Option(help="stall the USB link at this second")] = None,
    stall: Annotated[
        float, typer.Option(help="how long the stall lasts (then a burst of late samples)")
    ] = 0.5,
    wait_reader: Annotated[float, typer.Option(help="seconds to wait for a reader to open the port")] = 60.0,
) -> None:
    """Play recorded or simulated trials over a pseudo-terminal at the real rate, in the firmware's wire
    format (docs/live.md), optionally with faults. Prints the pseudo-terminal's path."""
    from pipeline.live.emulate import Faults, load_trial, play

    try:
        loaded = [load_trial(t) for t in trials]
    except ValueError as e:
        raise fail(str(e)) from e
    faults = Faults(pull_at, replug_after, tuple(garbage_at or ()), stall_at, stall, baud)
    sent = play(
        loaded,
        link=link,
        pause_s=pause,
        speed=speed,
        faults=faults,
        wait_reader_s=wait_reader,
        say=lambda m: typer.echo(m),
    )
    typer.echo(f"emulate-rig: done: {json.dumps(sent, sort_keys=True)}")


def emulate_board(
    trials: Annotated[
        list[Path],
        typer.Argument(help="rig-log/1 estimator files (<batch>/<trial>.fsr.csv), played in order"),
    ],
    link: Annotated[Path, typer.Option(help="a symlink to the pseudo-terminal, for `needlecue live --port`")],
    pause: Annotated[float, typer.Option(help="seconds at rest before, between and after the trials")] = 3.0,
    seconds: Annotated[
        float | None, typer.Option(help="board seconds to run (default: 1 s after the last rest)")
    ] = None,
    reset_at: Annotated[list[float] | None, typer.Option(help="reset the board at this second")] = None,
    stuck: Annotated[
        list[str] | None, typer.Option(help="PIN:FROM_S:TO_S:MV: an analog pin stuck at MV millivolts")
    ] = None,
    crystal_hz: Annotated[
        int, typer.Option(help="the board's crystal (the firmware assumes 16000000; 15920000 is 0.5 % slow)")
    ] = 16_000_000,
    dev_buf: Annotated[
        int,
        typer.Option(
            help="bytes (64..4095) the USB link holds for a host that stops reading; the rest is lost"
        ),
    ] = 4000,
    eeprom: Annotated[
        Path | None, typer.Option(help="a file that keeps the board's EEPROM (its unit id) between runs")
    ] = None,
    elf: Annotated[Path, typer.Option(help="the firmware, built by `make firmware`")] = Path(
        "firmware/build/needlecue.elf"
    ),
    board: Annotated[Path, typer.Option(help="the simavr harness, built by `make firmware`")] = Path(
        "firmware/build/board"
    ),
    wait_reader: Annotated[float, typer.Option(help="seconds to wait for a reader to open the port")] = 60.0,
) -> None:
    """Run the shipped firmware on an emulated ATmega328P (simavr), its analog pins driven by recorded
    or simulated trials, its serial port on a pseudo-terminal (docs/live.md, "The emulated board")."""
    import signal
    import tempfile

    from pipeline.live import board as bd
    from pipeline.live.emulate import load_trial

    try:
        loaded = [load_trial(t) for t in trials]
        faults = bd.BoardFaults(
            tuple(reset_at or ()), tuple(bd.Stuck.parse(s) for s in stuck or ()), crystal_hz, dev_buf
        )
    except ValueError as e:
        raise fail(str(e)) from e
    with tempfile.TemporaryDirectory(prefix="needlecue-board-") as folder:
        try:
            proc = bd.emulate(
                loaded,
                link,
                Path(folder) / "pins.csv",
                elf=elf,
                board=board,
                pause_s=pause,
                seconds=seconds,
                faults=faults,
                eeprom=eeprom,
                wait_reader_s=wait_reader,
            )
        except FileNotFoundError as e:
            raise fail(str(e)) from e
        signal.signal(signal.SIGTERM, lambda *_: proc.terminate())
        assert proc.stdout is not None
        try:
            for line in proc.stdout:
                typer.echo(line.rstrip("\n"))
        except KeyboardInterrupt:
            proc.terminate()
        code = proc.wait()
    if code != 0:
        raise fail(f"the emulated board exited {code}", code)


def unit_id(
    port: Annotated[str, typer.Option(help="the estimator's serial port, e.g. /dev/ttyACM0")],
    unit: Annotated[
        str | None, typer.Argument(help="the id to keep in the board's EEPROM (none: just show it)")
    ] = None,
    clear: Annotated[bool, typer.Option(help="clear the id: the banner then names no unit")] = False,
    reset_wait: Annotated[
        float, typer.Option(help="seconds to wait out the board's reset after the port opens")
    ] = 2.0,
    baud: Annotated[int, typer.Option(help="the port's baud rate")] = 115200,
) -> None:
    """Show or set the unit id an estimator running needlecue's firmware keeps in its EEPROM and sends in
    its banner (docs/live.md, "The firmware"). Exit 1 if the board refuses or does not answer."""
    from pipeline.live.port import open_serial
    from pipeline.live.unit_id import read_banner, set_unit_id, wait_for_banner

    if unit is not None and clear:
        raise fail("give a unit id or --clear, not both")
    try:
        ser = open_serial(port, baud)
    except OSError as e:  # serial.SerialException is an OSError
        raise fail(f"cannot open {port}: {e}") from e
    try:
        wait_for_banner(ser, reset_wait)  # an Uno resets when the port opens; its bootloader ignores input
        banner = set_unit_id(ser, unit) if unit is not None or clear else read_banner(ser)
    except (ValueError, TimeoutError, OSError) as e:  # OSError: serial.SerialException, a pulled cable
        raise fail(f"{port}: {e}") from e
    finally:
        ser.close()
    rate = f"{banner.rate_hz:g} Hz" if banner.rate_hz else "no rate given"
    channels = ",".join(banner.channels or ()) or "not given"
    typer.echo(f"{port}: unit {banner.unit_id or '(none)'}; channels {channels}; {rate}")
