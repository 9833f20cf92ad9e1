"""``ohmni neck``: move the neck (HerkuleX or worm gear) and read it back.

Which neck is fitted is found when the port opens (the Robot's discovery, or ``neck`` in
the config). The named positions, per kind (from the config's ranges):

* HerkuleX (sid 3): ``up`` = ``neck_max_raw`` (650), ``down`` = ``neck_min_raw`` (280),
  ``center`` = the middle of the two (465, also the default rest position). Which end is
  up is **assumed**: 512 is the level head (0°), and the safe range reaches 45° one way
  and 75° the other; the longer side is taken as down, as the rest position leans there.
* Worm gear (sid 4): ``up`` = ``worm_min_raw`` (−127000), ``down`` = ``worm_max_raw``
  (120000), ``center`` = their middle (−3500); 0 is the documented neutral (``--raw 0``).

A move waits for the neck to read back at its target with the handle's own
``move(..., wait=True)`` (:mod:`ohmni_tb.robot.devices`).
"""

from __future__ import annotations

import asyncio
import math
from collections.abc import AsyncIterator
from dataclasses import dataclass
from typing import TYPE_CHECKING, Annotated, Any, TypeVar, cast

import typer
from rich.markup import escape

from ohmni_tb.cli.common import (
    DirectOption,
    JsonOption,
    PortOption,
    YesOption,
    confirm_motion,
    console,
    daemon_for,
    emit_json,
    load_config,
    open_robot,
    parse_int,
    resolve_port,
    run,
)
from ohmni_tb.errors import InvalidArgumentError, OhmniError
from ohmni_tb.herkulex.units import MAX_PLAYTIME_S, check_playtime_s

if TYPE_CHECKING:
    from ohmni_tb.config import RobotConfig
    from ohmni_tb.robot import (
        Robot,
        ServoHandle,
        ServoSample,
        WormNeckHandle,
        WormNeckSample,
    )

__all__ = ["neck"]

T = TypeVar("T", "ServoSample", "WormNeckSample")

#: The named positions a move takes; ``rest`` and ``free`` are not moves to a position.
NAMED = ("up", "down", "center")
ACTIONS = (*NAMED, "rest", "free")
DEFAULT_PLAYTIME_S = 1.0
#: How long the worm gear may take to get there (the handle's default, WORM_TIMEOUT_S of
#: ohmni_tb.robot.devices).
WORM_TIMEOUT_S = 15.0
#: How long to wait for a feedback sample.
SAMPLE_TIMEOUT_S = 1.0


class NeckError(OhmniError):
    """The neck did not get there, or cannot do what was asked (exit code 1)."""


@dataclass(frozen=True)
class _Ask:
    """What the command line asked for, checked before the port opens."""

    action: str  # up, down, center, rest, free, raw, deg or read
    raw: int | None = None
    deg: float | None = None
    playtime_s: float | None = None


def neck(
    position: Annotated[
        str | None,
        typer.Argument(
            metavar="POSITION",
            help="up, down or center (per neck kind, see above), rest (move to the rest "
            "position, then torque free) or free (torque off). With no POSITION, --raw or "
            "--deg: print where the neck is.",
            show_default=False,
        ),
    ] = None,
    raw: Annotated[
        str | None,
        typer.Option(
            "--raw",
            metavar="N",
            help="Target in raw counts (0x.. accepted): HerkuleX 280..650, worm gear "
            "-127000..120000 (the config's neck_min_raw.. / worm_min_raw.. ranges).",
            show_default=False,
        ),
    ] = None,
    deg: Annotated[
        float | None,
        typer.Option(
            "--deg",
            metavar="X",
            help="Target in degrees, HerkuleX only: 0 = level head (512 + "
            "neck_zero_offset_raw), -75.4..+44.85 with the default range.",
            show_default=False,
        ),
    ] = None,
    playtime: Annotated[
        float | None,
        typer.Option(
            "--playtime",
            metavar="S",
            help=f"Seconds the HerkuleX move takes, 0..{MAX_PLAYTIME_S} (default "
            f"{DEFAULT_PLAYTIME_S:g} s). Ignored by the worm gear: it has its own speed.",
            show_default=False,
        ),
    ] = None,
    as_json: JsonOption = False,
    port: PortOption = None,
    direct: DirectOption = False,
    yes: YesOption = False,
) -> None:
    """Move the neck and print the target and where it read back (raw and degrees).

    The neck kind is found when the port opens: HerkuleX (sid 3) or worm gear (sid 4).
    HerkuleX: up = 650 (neck_max_raw), down = 280 (neck_min_raw), center = 465 (the
    middle, also the rest position); which end is up is assumed. Worm gear: up = -127000,
    down = 120000, center = -3500 (the middle; --raw 0 is its neutral).

    The command waits until the position reads back within 5 counts (HerkuleX; playtime
    + 1.5 s at most) or 1000 counts (worm gear; 15 s at most), else exit 1. A target
    outside both necks' ranges is refused before the port opens (exit 2); one outside
    the range of the neck that answered, or --deg on a worm gear, is refused after
    discovery with exit 1 and nothing sent to the neck.

    The neck stays where it was sent: the command leaves the neck as it is on exit
    (on_exit_neck=keep), so a HerkuleX neck keeps its torque on. Run `ohmni neck rest` or
    `ohmni neck free` when done: holding torque for long heats the servo.

    On a real port, motion asks first (--yes skips); sim:// never asks, nor a daemon
    serving it.

    Examples: ohmni neck up --port sim:// ; ohmni neck --raw 400 --playtime 0.5 ;
    ohmni neck --deg -10 --json ; ohmni neck rest ; ohmni neck --json (where it is).
    """
    ask = _check_arguments(position, raw, deg, playtime)
    config = load_config()
    _check_against_config(ask, config)
    via = daemon_for(port, direct)
    where = via or resolve_port(port)
    if ask.action != "read":
        confirm_motion(where, _describe(ask), yes=yes)
    result = run(lambda: _run(where, via, ask))
    if as_json:
        emit_json(result)
    else:
        _print(result)


# -- arguments, before the port opens -------------------------------------------------------


def _check_arguments(
    position: str | None, raw: str | None, deg: float | None, playtime: float | None
) -> _Ask:
    """The request, every argument checked that can be without the config.

    Raises:
        typer.BadParameter: Several targets, an unknown position, a number that is not
            one, or a playtime outside 0..2.8448 s.
    """
    given = []
    if position is not None:
        given.append(f"POSITION {position!r}"[:60])
    if raw is not None:
        given.append(f"--raw={raw}"[:60])
    if deg is not None:
        given.append(f"--deg={deg!r}")
    if len(given) > 1:
        raise typer.BadParameter(
            f"give one target, not {len(given)}: {', '.join(given)} (POSITION, --raw or --deg)"
        )
    if position is not None and position not in ACTIONS:
        shown = repr(position) if len(position) <= 40 else f"{position[:20]!r}…"
        raise typer.BadParameter(f"POSITION must be up, down, center, rest or free, not {shown}")
    if playtime is not None:
        # The handle's own range and rounding (ohmni_tb.herkulex.units), checked here
        # so that a bad one is refused before the port opens.
        try:
            check_playtime_s(playtime)
        except InvalidArgumentError:
            raise typer.BadParameter(
                f"--playtime={playtime!r} is out of range: allowed 0..{MAX_PLAYTIME_S:g} s "
                f"(sent in whole 11.2 ms ticks)"
            ) from None
        if position in ("rest", "free") or (position is None and raw is None and deg is None):
            what = position or "reading the position"
            raise typer.BadParameter(
                f"--playtime is for moves (up, down, center, --raw, --deg), not {what}"
            )
    if deg is not None and not math.isfinite(deg):
        raise typer.BadParameter(f"--deg={deg!r} is not a finite number of degrees")
    if raw is not None:
        return _Ask("raw", raw=parse_int(raw, "--raw"), playtime_s=playtime)
    if deg is not None:
        return _Ask("deg", deg=deg, playtime_s=playtime)
    return _Ask(position or "read", playtime_s=playtime)


def _herkulex_range(config: RobotConfig) -> tuple[int, int]:
    return config.neck_min_raw, config.neck_max_raw


def _worm_range(config: RobotConfig) -> tuple[int, int]:
    return config.worm_min_raw, config.worm_max_raw


def _degrees(raw: float, zero_offset_raw: int) -> float:
    from ohmni_tb.herkulex.units import angle_deg_from_raw  # noqa: PLC0415

    return angle_deg_from_raw(raw, zero_offset_raw=zero_offset_raw)


def _deg_range(config: RobotConfig) -> str:
    low, high = _herkulex_range(config)
    offset = config.neck_zero_offset_raw
    return f"{_degrees(low, offset):+.2f}..{_degrees(high, offset):+.2f}° (raw {low}..{high})"


def _check_against_config(ask: _Ask, config: RobotConfig) -> None:
    """Refuse what no neck the config allows could take (exit 2, before the port opens).

    Raises:
        typer.BadParameter: --raw outside every allowed neck's range, --deg outside the
            HerkuleX range or with a worm-gear neck configured.
    """
    kinds = ("herkulex", "worm") if config.neck == "auto" else (config.neck,)
    if ask.raw is not None:
        ranges = {"herkulex": _herkulex_range(config), "worm": _worm_range(config)}
        allowed = [ranges[kind] for kind in kinds if kind in ranges]
        if not any(low <= ask.raw <= high for low, high in allowed):
            names = {"herkulex": "HerkuleX neck", "worm": "worm-gear neck"}
            text = " or ".join(
                f"{ranges[kind][0]}..{ranges[kind][1]} ({names[kind]})"
                for kind in kinds
                if kind in ranges
            )
            shown = str(ask.raw) if ask.raw.bit_length() <= 64 else "a huge number"
            raise typer.BadParameter(
                f"--raw={shown} is out of range: allowed {text or 'nothing (neck=none)'}"
            )
    if ask.deg is not None:
        if "herkulex" not in kinds:
            raise typer.BadParameter(
                f"--deg is for the HerkuleX neck; the config says neck={config.neck}: "
                "use --raw or up/down/center"
            )
        _deg_to_raw(ask.deg, config)


def _deg_to_raw(deg: float, config: RobotConfig) -> int:
    """``--deg`` as the HerkuleX raw target.

    Raises:
        typer.BadParameter: Outside the HerkuleX neck's range; the message gives it.
    """
    from ohmni_tb.herkulex.units import pos_raw_from_deg  # noqa: PLC0415

    low, high = _herkulex_range(config)
    try:
        return pos_raw_from_deg(
            deg, zero_offset_raw=config.neck_zero_offset_raw, min_raw=low, max_raw=high
        )
    except InvalidArgumentError:  # OutOfRangeError too
        raise typer.BadParameter(
            f"--deg={deg!r} is out of range: allowed {_deg_range(config)}"
        ) from None


def _describe(ask: _Ask) -> str:
    if ask.action == "raw":
        return f"ohmni neck --raw {ask.raw}"
    if ask.action == "deg":
        return f"ohmni neck --deg {ask.deg:g}"
    return f"ohmni neck {ask.action}"


# -- on the robot ----------------------------------------------------------------------------


def _named(robot: Robot) -> dict[str, int]:
    """up, down and center for the neck that answered."""
    config = robot.config
    if robot.neck_kind == "worm":
        low, high = _worm_range(config)
        return {"up": low, "down": high, "center": (low + high) // 2}
    low, high = _herkulex_range(config)
    return {"up": high, "down": low, "center": (low + high) // 2}


async def _run(port: str, via: str | None, ask: _Ask) -> dict[str, Any]:
    # keep: the neck stays where this command sent it (or rested, or freed) on exit.
    control = ask.action != "read"
    async with open_robot(port, via=via, control=control, on_exit_neck="keep") as robot:
        handle = robot.neck  # StateError (exit 1) when no neck answered
        # The Robot's handle, or through the daemon one with the same attributes.
        if robot.neck_kind == "herkulex":
            return await _herkulex(robot, cast("ServoHandle", handle), ask)
        return await _worm(robot, cast("WormNeckHandle", handle), ask)


def _base(robot: Robot, sid: int, ask: _Ask) -> dict[str, Any]:
    config = robot.config
    low, high = _worm_range(config) if robot.neck_kind == "worm" else _herkulex_range(config)
    return {
        "neck": robot.neck_kind,
        "sid": sid,
        "action": ask.action,
        "target_raw": None,
        "target_deg": None,
        "playtime_s": None,
        "position_raw": None,
        "position_deg": None,
        "torque": None,
        "moving": None,
        "stalled": None,
        "elapsed_s": None,
        "range_raw": [low, high],
        "positions_raw": _named(robot),
        "notes": [],
    }


async def _herkulex(robot: Robot, handle: ServoHandle, ask: _Ask) -> dict[str, Any]:
    from ohmni_tb.herkulex.units import playtime_sent_s  # noqa: PLC0415

    loop = asyncio.get_running_loop()
    out = _base(robot, handle.sid, ask)
    offset = handle.zero_offset_raw
    if robot.config.servo_hz <= 0:
        raise NeckError("the neck reads back from the servo_neck stream: servo_hz is 0")
    target: int | None = None
    if ask.action in NAMED:
        target = _named(robot)[ask.action]
    elif ask.action == "raw":
        target = ask.raw
    elif ask.action == "deg":
        assert ask.deg is not None
        target = _deg_to_raw_checked(ask.deg, robot.config)
    if target is not None:
        low, high = handle.min_raw, handle.max_raw
        if not low <= target <= high:
            raise NeckError(
                f"{_label(ask, target)} is out of range for the HerkuleX neck (sid "
                f"{handle.sid}): allowed {low}..{high}; nothing was sent to the neck"
            )
        playtime = DEFAULT_PLAYTIME_S if ask.playtime_s is None else ask.playtime_s
        out.update(
            target_raw=target,
            target_deg=round(_degrees(target, offset), 2),
            playtime_s=round(playtime_sent_s(playtime), 4),
        )
        sent = loop.time()
        # Back within 5 counts and done moving, by the playtime + 1.5 s.
        arrived = await handle.move(target, playtime_s=playtime, wait=True)
        assert arrived is not None  # wait=True
        sample = arrived
        out["elapsed_s"] = round(max(sample.stamp_s - sent, 0.0), 3)
    else:
        async with robot.subscribe("servo_neck", maxlen=8) as samples:
            sent = loop.time()
            if ask.action == "rest":
                out.update(
                    target_raw=handle.rest_raw,
                    target_deg=round(_degrees(handle.rest_raw, offset), 2),
                )
                await handle.rest()  # over 1 s, then torque free
                sent = loop.time()
            elif ask.action == "free":
                await handle.free()
                sent = loop.time()
            sample = await _next(samples, sent, "servo_neck")
    out.update(
        position_raw=sample.position_raw,
        position_deg=round(_degrees(sample.position_raw, offset), 2),
        torque=sample.torque.name.lower(),
        moving=sample.moving,
    )
    return out


def _label(ask: _Ask, target: int) -> str:
    """How an error names the target: as typed, or the named position's value."""
    return f"--raw={target}" if ask.action == "raw" else f"{ask.action} ({target} raw)"


def _deg_to_raw_checked(deg: float, config: RobotConfig) -> int:
    try:
        return _deg_to_raw(deg, config)
    except typer.BadParameter as exc:  # checked before the port opened: not expected
        raise NeckError(str(exc)) from None


async def _worm(robot: Robot, handle: WormNeckHandle, ask: _Ask) -> dict[str, Any]:
    loop = asyncio.get_running_loop()
    out = _base(robot, handle.sid, ask)
    notes: list[str] = out["notes"]
    if robot.config.new_neck_hz <= 0:
        raise NeckError("the neck reads back from the new_neck stream: new_neck_hz is 0")
    if ask.action == "deg":
        raise NeckError(
            "--deg is for the HerkuleX neck, and the worm-gear neck answered: use --raw "
            "or up/down/center; nothing was sent to the neck"
        )
    target: int | None = None
    if ask.action in NAMED:
        target = _named(robot)[ask.action]
    elif ask.action == "raw":
        target = ask.raw
    elif ask.action == "rest":
        notes.append("the worm gear holds its position without power: nothing to rest")
    elif ask.action == "free":
        notes.append("the worm gear has no torque to release: nothing to free")
    if target is not None:
        if not handle.min_raw <= target <= handle.max_raw:
            raise NeckError(
                f"{_label(ask, target)} is out of range for the worm-gear neck (sid 4): "
                f"allowed {handle.min_raw}..{handle.max_raw}; nothing was sent to the neck"
            )
        if ask.playtime_s is not None:
            notes.append("--playtime ignored: the worm gear moves at its own speed")
        out["target_raw"] = target
        sent = loop.time()
        # Back within 1000 counts and at rest; a stall is an error (PositionError).
        arrived = await handle.move(target, wait=True, timeout_s=WORM_TIMEOUT_S)
        assert arrived is not None  # wait=True
        sample = arrived
        out["elapsed_s"] = round(max(sample.stamp_s - sent, 0.0), 3)
    else:
        async with robot.subscribe("new_neck", maxlen=8) as samples:
            sample = await _next(samples, loop.time(), "new_neck")
    if sample.stalled:
        raise NeckError(
            f"the worm-gear neck stalled at {sample.position_raw}: only a power cycle clears it"
        )
    out.update(position_raw=sample.position_raw, moving=sample.moving, stalled=sample.stalled)
    return out


async def _next(
    samples: AsyncIterator[T],
    after_s: float,
    stream: str,
    *,
    deadline: float | None = None,
    default: T | None = None,
) -> T:
    """The next sample of ``samples`` read at or after ``after_s``.

    At ``deadline`` (loop time) ``default`` is returned if it is not ``None``.

    Raises:
        NeckError: No sample came within :data:`SAMPLE_TIMEOUT_S` (or by the deadline,
            with no ``default``).
    """
    loop = asyncio.get_running_loop()
    started = loop.time()
    until = started + SAMPLE_TIMEOUT_S if deadline is None else deadline
    while True:
        try:
            async with asyncio.timeout_at(until):
                sample = await anext(samples)
        except TimeoutError:
            if default is not None:
                return default
            raise NeckError(
                f"no {stream} sample came within {until - started:.1f} s: is the neck still "
                "answering?"
            ) from None
        except StopAsyncIteration:
            raise NeckError(f"the {stream} stream ended (the robot closed)") from None
        if sample.stamp_s >= after_s:
            return sample


# -- output ----------------------------------------------------------------------------------


def _print(result: dict[str, Any]) -> None:
    kind = "HerkuleX" if result["neck"] == "herkulex" else "worm-gear"
    head = f"neck: {kind} (sid {result['sid']})"
    action = result["action"]
    if action in NAMED or action == "rest":
        head += f", {action}"
    if result["target_raw"] is not None:
        line = f"{head} → {_where(result['target_raw'], result['target_deg'])}"
        if action == "rest":
            line += ", then torque free"
        elif result["playtime_s"] is not None:
            line += f" over {result['playtime_s']:g} s"
        console.print(line, highlight=False)
    elif action == "free":
        console.print(f"{head}: torque free", highlight=False)
    else:
        console.print(head, highlight=False)
    sent = result["target_raw"] is not None or (action == "free" and kind == "HerkuleX")
    label = "read back" if sent else "position"
    back = f"{label}: {_where(result['position_raw'], result['position_deg'])}"
    if result["torque"] is not None:
        back += f", torque {result['torque']}"
    if result["moving"]:
        back += ", moving"
    if result["elapsed_s"] is not None:
        back += f" ({result['elapsed_s']:.2f} s after the command)"
    console.print(back, highlight=False)
    if action == "read":
        named = ", ".join(f"{name} {raw}" for name, raw in result["positions_raw"].items())
        low, high = result["range_raw"]
        console.print(f"range {low}..{high} raw; {named}", highlight=False)
    for note in result["notes"]:
        console.print(f"[dim]{escape(note)}[/dim]")


def _where(raw: int, deg: float | None) -> str:
    return f"{raw} raw" if deg is None else f"{raw} raw ({deg:+.2f}°)"
