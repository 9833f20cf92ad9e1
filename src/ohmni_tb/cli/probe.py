"""``ohmni probe``: first contact with a real robot — what its boards really speak.

It opens the port itself with a bare bus (no Robot: nothing starts sending wheel commands)
and runs :func:`ohmni_tb.probe.probe_port`; this module parses, prints and writes.
"""

from __future__ import annotations

import os
import platform
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any

import typer

from ohmni_tb.cli import common
from ohmni_tb.cli.common import (
    JsonOption,
    PortOption,
    console,
    daemon_for,
    emit_json,
    error_line,
    parse_int,
    plain_table,
    resolve_port,
    run,
)

if TYPE_CHECKING:
    from ohmni_tb.config import RobotConfig
    from ohmni_tb.config_file import WriteOutcome
    from ohmni_tb.probe import Finding, ProbeReport

__all__ = ["probe"]

#: The ids a device may have: 0..253 (0xFE is broadcast).
_MAX_ID = 0xFD
#: ``--pwm``'s default and range: ohmni_tb.probe.findings.MOTION_PWM, session.MIN/MAX_PWM.
_PWM_DEFAULT, _PWM_MIN, _PWM_MAX = 80, 20, 300
#: Characters of reply bytes shown per finding in the table.
_RAW_CHARS = 80
#: The table's raw column, at most this wide.
_RAW_WIDTH = 26
_MOTION_WARNING = (
    "ohmni probe --allow-motion: the wheels will turn, one at a time, a few millimetres "
    "each (PWM {pwm} of 1000 for 0.3 s per try). The robot must be on a stand, or have "
    "room around it. Ctrl-C stops the wheels and ends the probe."
)


def probe(
    port: PortOption = None,
    ids: Annotated[
        str,
        typer.Option(
            "--ids",
            metavar="IDS",
            help="The ids to scan: a list of ids and ranges, e.g. 0..4,11..20 (decimal or "
            "0x..). Default all of 0..253: a silent id costs one bus timeout (25 ms with "
            "the default usb_latency_ms, so about 7 s for the whole scan).",
        ),
    ] = "0..253",
    allow_motion: Annotated[
        bool,
        typer.Option(
            "--allow-motion",
            help="Turn each wheel a little to find which wheel command moves it (the robot "
            "on a stand, or with room). Without it nothing moves: the probe only reads.",
        ),
    ] = False,
    pwm: Annotated[
        str,
        typer.Option(
            "--pwm",
            metavar="N",
            help=f"The PWM of a wheel try, {_PWM_MIN}..{_PWM_MAX} of 1000 (past the dead "
            "band; raise it if no form moves the wheels).",
        ),
    ] = str(_PWM_DEFAULT),
    as_json: JsonOption = False,
    write: Annotated[
        bool,
        typer.Option(
            "--write",
            help="Save the settings the probe measured into the config file (--config, "
            "else the file ohmni reads, else the user's ohmni.toml); the rest of the file "
            "stays as it is.",
        ),
    ] = False,
    config: Annotated[
        Path | None,
        typer.Option(
            "--config",
            metavar="FILE",
            help="The config file whose profile is compared with the robot and that "
            "--write writes (created if missing).",
            show_default=False,
        ),
    ] = None,
    share: Annotated[
        Path | None,
        typer.Option(
            "--share",
            metavar="FILE",
            help="Also write the report as JSON to FILE, to attach to a bug report: with the "
            "package version, Python and OS, without the adapter's serial number.",
            show_default=False,
        ),
    ] = None,
    share_serials: Annotated[
        bool,
        typer.Option("--share-serials", help="Keep the adapter's serial number in --share."),
    ] = False,
) -> None:
    """Find what the robot's boards really speak and compare it with the profile.

    Opens the port itself (while ohmni serve holds it, it says the port is busy) and only
    reads: every id that answers (firmware tag or servo model, reply latency), the USB
    adapter's latency timer, the battery block (searched for when it is not where
    assumed), the drive boards' torque register, the worm neck's registers, the external
    servos. With --allow-motion it also turns each wheel a little in each wheel-command
    form, confirming every stop by the wheel counts. Prints one row per finding
    (confirmed, differs, not found) and the settings that differ; --write saves them.
    Exit code 0 when the probe ran, 1 when a stop was not confirmed or the bus failed.

    Example: ohmni probe --port 'sim://?battery_addr=0xB0' --ids 0..20
    """
    scan = _parse_ids(ids)
    trial_pwm = parse_int(pwm, "--pwm", _PWM_MIN, _PWM_MAX)
    if share_serials and share is None:
        raise typer.BadParameter("--share-serials goes with --share FILE")
    if daemon_for(port, False) is not None:
        error_line(
            "ohmni serve holds the port: ohmni probe opens it itself (a bare bus, no "
            "Robot); stop the daemon, or name the port with --port"
        )
        raise typer.Exit(1)
    url = resolve_port(port)
    settings = _load(config)
    if allow_motion:
        typer.echo(_MOTION_WARNING.format(pwm=trial_pwm), err=as_json)

    async def main() -> ProbeReport:
        from ohmni_tb.errors import StopNotConfirmedError  # noqa: PLC0415
        from ohmni_tb.probe import probe_port  # noqa: PLC0415

        transport = await common.open_transport(url)
        try:
            report = await probe_port(
                transport,
                profile=settings.profile(),
                ids=scan,
                allow_motion=allow_motion,
                pwm=trial_pwm,
                bus_timeout_s=settings.bus_timeout_s(),
                usb_latency_ms=settings.usb_latency_ms,
                port_name=url,
            )
        except StopNotConfirmedError as exc:
            error_line(
                f"probe aborted: a wheel stop was not confirmed, the wheels may still be "
                f"moving ({exc.reason}); stops were sent in both command forms: check the "
                "robot, run ohmni stop or switch it off"
            )
            raise typer.Exit(1) from None
        return report

    report = run(main)
    data = report.to_json()
    written = _write(report, settings, config) if write else None
    data["written"] = written
    data["shared"] = None if share is None else str(share)
    if share is not None:
        _share(data, share, serials=share_serials)
    if as_json:
        emit_json(data)
        return
    _print(report, url)
    if written is not None:
        _print_written(written)
    if share is not None:
        console.print(f"report for sharing: {share}", highlight=False, markup=False)


# -- arguments -------------------------------------------------------------------------------


def _parse_ids(text: str) -> list[int]:
    """``--ids``: ids and ranges (``0..4``, ``11-20``), comma-separated.

    Raises:
        typer.BadParameter: A part is not an id 0..253, or a range runs backwards.
    """
    found: set[int] = set()
    for piece in text.split(","):
        part = piece.strip()
        if not part:
            raise typer.BadParameter(f"--ids={text!r} has an empty part: e.g. 0..4,11,20")
        low_text, dots, high_text = part.partition("..")
        if not dots and "-" in part[1:]:
            low_text, _, high_text = part.partition("-")
            dots = "-"
        low = parse_int(low_text.strip(), "--ids", 0, _MAX_ID)
        high = parse_int(high_text.strip(), "--ids", 0, _MAX_ID) if dots else low
        if high < low:
            raise typer.BadParameter(f"--ids: the range {part} runs backwards")
        found.update(range(low, high + 1))
    return sorted(found)


def _load(config: Path | None) -> RobotConfig:
    """The settings the probe compares with: ``--config`` FILE's (none when it does not
    exist yet), else ``$OHMNI_CONFIG``'s (likewise), else what ``RobotConfig.load()``
    reads. A bad file is exit 1, one line."""
    from ohmni_tb.config import CONFIG_ENV, RobotConfig  # noqa: PLC0415  # pydantic: when run

    named = config
    if named is None and os.environ.get(CONFIG_ENV):
        named = Path(os.environ[CONFIG_ENV]).expanduser()
    missing = named is not None and not named.exists()

    async def load() -> RobotConfig:
        if missing:
            return RobotConfig()  # the file --write creates; the environment still counts
        return RobotConfig.load(named)

    return run(load)


# -- output ----------------------------------------------------------------------------------


def _print(report: ProbeReport, url: str) -> None:
    from rich.markup import escape  # noqa: PLC0415

    console.print(
        f"[bold]probe of {escape(url)}[/bold]: ids {report.to_json()['scanned']} scanned in "
        f"{report.elapsed_s:.1f} s; {len(report.devices)} answered",
        highlight=False,
    )
    devices = plain_table()
    for column in ("sid", "name", "kind", "firmware / model", "latency ms", "status"):
        devices.add_column(column, justify="right" if column in ("sid", "latency ms") else "left")
    for d in report.devices:
        devices.add_row(
            str(d.sid),
            d.name,
            d.kind,
            escape(d.firmware or d.model or "-"),
            "-" if d.latency_s is None else f"{d.latency_s * 1e3:.2f}",
            f"{d.status_error:02X} {d.status_detail:02X}",
        )
    console.print(devices)
    table = plain_table("findings")
    for column in ("finding", "status", "assumed", "found"):
        table.add_column(column)
    # The reply bytes on one line, cut short: --json has them all.
    table.add_column("raw (replies)", no_wrap=True, overflow="ellipsis", max_width=_RAW_WIDTH)
    colour = {"confirmed": "green", "differs": "yellow", "not found": "red"}
    for f in report.findings:
        table.add_row(
            f.name,
            f"[{colour[f.status.value]}]{f.status.value}[/]",
            escape(_summary(f, f.assumed)),
            escape(_summary(f, f.found)),
            escape(_raw_text(f)),
        )
    for s in report.skipped:
        table.add_row(s.name, "[dim]skipped[/dim]", "", escape(s.why), "")
    console.print(table)
    for f in report.findings:
        if f.detail:
            console.print(f"{f.name}: {f.detail}", highlight=False, markup=False)
    _print_differs(report)


def _print_differs(report: ProbeReport) -> None:
    from ohmni_tb.probe.findings import setting_text  # noqa: PLC0415

    differing = report.differing()
    if not differing:
        measured = ", ".join(report.measured()) or "none"
        console.print(f"settings: every measured one as assumed ({measured})", highlight=False)
        return
    console.print("settings that differ (--write saves them):", highlight=False)
    for name, (old, new) in differing.items():
        console.print(
            f"  {name} = {setting_text(name, new)}   (assumed {setting_text(name, old)})",
            highlight=False,
            markup=False,
        )


def _summary(finding: Finding, value: Any) -> str:
    """A finding's assumed or found value in a few words."""
    from ohmni_tb.probe.findings import setting_text  # noqa: PLC0415

    if value is None:
        return "-"
    if finding.name == "devices" and isinstance(value, list):
        return ", ".join(map(str, value)) or "none"
    if not isinstance(value, dict):
        return setting_text(finding.name, value) if isinstance(value, list) else str(value)
    if finding.name == "devices":
        boards = ", ".join(map(str, value.get("boards", [])))
        necks = " or ".join(map(str, value.get("neck", [])))
        return f"boards {boards}" + (f"; a neck at {necks}" if necks else "")
    if finding.name == "battery":
        text = (
            f"{setting_text('battery_addr', value['battery_addr'])}, "
            f"{value['battery_length']} bytes, {value['battery_layout']}"
        )
        if "cell_mv" in value:
            text += " · " + "/".join(map(str, value["cell_mv"])) + " mV"
        return text
    if finding.name == "wheel_form":
        form = value.get("form")
        if form is None or "left_ticks" not in value:
            return str(form or "-") if "trials" not in value else "none moved"
        return f"{form} (left {value['left_ticks']:+d}, right {value['right_ticks']:+d} ticks)"
    if finding.name == "drive_torque" and "values" in value:
        values = "/".join(f"{v:02X}" for v in value["values"])
        return f"RAM {value['drive_torque_addr']} in {values}"
    parts = []
    for key, item in value.items():
        shown = "-" if item is None else setting_text(key, item)
        if isinstance(item, int) and not isinstance(item, bool) and key in ("left", "right"):
            shown = f"{item:02X}"
        parts.append(f"{key.removeprefix('worm_')} {shown}")
    return ", ".join(parts)


def _raw_text(finding: Finding) -> str:
    """The reply bytes a finding rests on, cut short (``--json`` has them all)."""
    replies = [r.reply.hex(" ").upper() for r in finding.raw if r.reply is not None]
    text = " | ".join(replies)
    return text if len(text) <= _RAW_CHARS else text[: _RAW_CHARS - 1] + "…"


# -- --write and --share ---------------------------------------------------------------------


def _write(report: ProbeReport, settings: RobotConfig, config: Path | None) -> dict[str, Any]:
    """Write the measured settings; what was written (for JSON and the lines printed)."""
    from ohmni_tb.config_file import (  # noqa: PLC0415  # pydantic: when run
        default_config_file,
        loaded_config_file,
        write_settings,
    )
    from ohmni_tb.errors import ConfigError  # noqa: PLC0415

    path = config if config is not None else default_config_file()
    values = report.measured()
    outcome: WriteOutcome | None = None
    if values:
        try:
            outcome = write_settings(
                path, values, comment="ohmni settings (ohmni probe wrote the bus profile)"
            )
        except ConfigError as exc:
            error_line(str(exc))
            raise typer.Exit(1) from None
    previous = {} if outcome is None else outcome.previous
    changes = {
        name: {"old": previous.get(name), "assumed": _plain(getattr(settings, name)), "new": new}
        for name, new in values.items()
    }
    read = loaded_config_file()
    environment = {key.upper() for key in os.environ}
    return {
        "file": str(path),
        "created": outcome is not None and outcome.created,
        "settings": changes,
        "read_by_commands": read is not None and read.resolve() == path.resolve(),
        "overridden_by": {
            name: f"OHMNI_{name.upper()}"
            for name in values
            if f"OHMNI_{name.upper()}" in environment
        },
    }


def _plain(value: Any) -> Any:
    return list(value) if isinstance(value, tuple) else value


def _print_written(written: dict[str, Any]) -> None:
    from ohmni_tb.probe.findings import setting_text  # noqa: PLC0415

    if not written["settings"]:
        console.print("nothing measured to write", highlight=False)
        return
    verb = "created" if written["created"] else "updated"
    console.print(f"{verb} {written['file']}:", highlight=False, markup=False)
    same: list[str] = []
    for name, change in written["settings"].items():
        old = change["old"]
        was = change["assumed"] if old is None else old
        if was == change["new"]:
            same.append(name)
            continue
        before = (
            f"{setting_text(name, old)} in the file"
            if old is not None
            else f"not set, {setting_text(name, was)}"
        )
        console.print(
            f"  {name}: {before} → {setting_text(name, change['new'])}",
            highlight=False,
            markup=False,
        )
    if same:
        console.print(f"  as before: {', '.join(same)}", highlight=False, markup=False)
    if not written["read_by_commands"]:
        console.print(
            f"note: the commands read another file (or none), not this one: set "
            f"OHMNI_CONFIG={written['file']} to use it",
            highlight=False,
            markup=False,
        )
    for name, variable in written["overridden_by"].items():
        console.print(
            f"note: ${variable} is set and overrides {name} from the file",
            highlight=False,
            markup=False,
        )


def _share(data: dict[str, Any], path: Path, *, serials: bool) -> None:
    """Write the report to share: no serial numbers unless asked, with the environment."""
    import json  # noqa: PLC0415

    from ohmni_tb._version import __version__  # noqa: PLC0415
    from ohmni_tb.probe import shareable  # noqa: PLC0415

    environment = {
        "ohmni_tb": __version__,
        "python": platform.python_version(),
        "implementation": sys.implementation.name,
        "os": platform.platform(),
    }
    shared = shareable(data, serials=serials, environment=environment)
    try:
        path.write_text(json.dumps(shared, indent=2) + "\n", encoding="utf-8")
    except OSError as exc:
        error_line(f"cannot write the report to {path}: {exc}")
        raise typer.Exit(1) from None
