"""``ohmni drive``: drive for a time, a distance or a turn and print the odometry; --teleop.

Three ways to move, one at a time:

- ``--linear/--angular [--duration S]``: the velocity command for a time (1 s by
  default), held by re-sending ``robot.drive()`` faster than the motion watchdog.
- ``--distance M`` or ``--turn DEG``: by odometry to the goal, slowing down near it so
  it does not overshoot; bounded by a timeout from the speed: the Robot's own motion
  goals, ``robot.drive_distance`` and ``robot.rotate`` (:mod:`ohmni_tb.robot.motion`).
- ``--teleop``: the keyboard in the terminal; each key press sends one ``drive()``, and
  the watchdog stops the robot when no key repeats.
- ``--pwm L R`` or ``--wheels L R [--duration S]``: open-loop PWM (``robot.drive_pwm``)
  or each wheel's speed (``robot.drive_wheels``) for a time, held as ``--linear`` is.

Every timed or goal drive ends with the stop confirmed by the wheel counts standing still
(the rule of :mod:`ohmni_tb.safety`), then prints what the odometry measured. Every
argument is checked against the Robot's limits before the port is opened.

A person drives: the commands go as the command source ``local`` on the robot's own
computer (the port opened here, or a daemon on loopback) and ``remote`` from elsewhere
(``--source`` names another), so ``ohmni drive`` at the robot overrides a remote script
for a while (:mod:`ohmni_tb.control.sources`).
"""

from __future__ import annotations

import asyncio
import dataclasses
import logging
import math
import os
import sys
from collections.abc import Awaitable, Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from typing import TYPE_CHECKING, Annotated, Any, TypeVar

import typer
from rich.console import Console
from rich.markup import escape

from ohmni_tb.cli import common
from ohmni_tb.cli.common import (
    DirectOption,
    JsonOption,
    PortOption,
    RobotWarnings,
    YesOption,
    confirm_motion,
    console,
    daemon_for,
    drive_source,
    emit_json,
    error_line,
    resolve_port,
    run,
)
from ohmni_tb.errors import (
    MotionError,
    OhmniError,
    SourceOverriddenError,
    StateError,
    StopNotConfirmedError,
)

if TYPE_CHECKING:
    from ohmni_tb.config import RobotConfig
    from ohmni_tb.robot import Robot, RobotStats, WheelEncoderSample, WheelOdomSample
    from ohmni_tb.robot.teleop import KeyTeleop

__all__ = ["drive"]

T = TypeVar("T")

#: --duration when none is given, s.
DEFAULT_DURATION_S = 1.0
#: The longest --duration, s: a longer drive is a job for --teleop or a program.
MAX_DURATION_S = 600.0
#: The farthest --distance either way, m.
MAX_DISTANCE_M = 100.0
#: The largest --turn either way, degrees (ten turns).
MAX_TURN_DEG = 3600.0
#: Speeds of --distance and --turn (and of a --teleop key) when --linear/--angular are
#: not given; the Robot's limits cap them. The goals' own (ohmni_tb.robot.motion's),
#: restated so that the arguments are checked before the Robot is imported.
DEFAULT_LINEAR_MPS = 0.3
DEFAULT_ANGULAR_RADPS = 1.0
#: The slowest speed a goal creeps at near its goal, and the least it accepts (as above).
MIN_GOAL_LINEAR_MPS = 0.03
MIN_GOAL_ANGULAR_RADPS = 0.2
#: drive() is re-sent at least this often while a command is held (and at least three
#: times per watchdog period).
COMMAND_PERIOD_S = 0.1
#: Time allowed to confirm the stop by the wheel counts, the ramp down included.
STOP_CONFIRM_TIMEOUT_S = 2.0
#: Time allowed for the first wheel counts after the Robot opens.
_FIRST_SAMPLE_S = 1.0
#: --teleop: the display is redrawn this often, s.
_REDRAW_S = 0.1

_err = Console(stderr=True)
_LOGGER = "ohmni_tb"


# -- arguments ------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class _Plan:
    """What to do, checked: one of the modes with its numbers."""

    mode: str  # "duration", "distance", "turn", "teleop", "pwm" or "wheels"
    linear_mps: float = 0.0
    angular_radps: float = 0.0
    duration_s: float = 0.0
    goal: float = 0.0  # metres for "distance", degrees for "turn"
    left: float = 0.0  # "pwm": PWM; "wheels": m/s
    right: float = 0.0
    ramped: bool = True  # "duration": through the acceleration limits (robot.drive's ramped)

    @property
    def timed(self) -> bool:
        """Held for a time, then stopped (not a goal, not the keyboard)."""
        return self.mode in ("duration", "pwm", "wheels")


def _fmt(value: float) -> str:
    return f"{value:g}"


def _finite(name: str, value: float | None) -> None:
    if value is not None and not math.isfinite(value):
        raise typer.BadParameter(f"{name}={_fmt(value)} is not a finite number")


def _within(name: str, value: float, low: float, high: float, unit: str, why: str = "") -> None:
    if not low <= value <= high:
        raise typer.BadParameter(
            f"{name}={_fmt(value)} is out of range: allowed {_fmt(low)}..{_fmt(high)} {unit}{why}"
        )


def _check_speed(config: RobotConfig, linear: float | None, angular: float | None) -> None:
    """Refuse a speed past the Robot's limits (the Robot would scale it down quietly)."""
    if linear is not None:
        top = config.max_linear_mps
        _within("--linear", linear, -top, top, "m/s", " (max_linear_mps)")
    if angular is not None:
        top = config.max_angular_radps
        _within("--angular", angular, -top, top, "rad/s", " (max_angular_radps)")
    wheel = abs(linear or 0.0) + abs(angular or 0.0) * config.wheel_separation_m / 2
    if wheel > config.max_wheel_mps:
        asked = " with ".join(
            f"{name}={_fmt(value)}"
            for name, value in (("--linear", linear), ("--angular", angular))
            if value is not None
        )
        raise typer.BadParameter(
            f"{asked} asks a wheel for {wheel:.3g} m/s: allowed up to "
            f"{_fmt(config.max_wheel_mps)} m/s (max_wheel_mps)"
        )


def _plan(
    config: RobotConfig,
    *,
    linear: float | None,
    angular: float | None,
    duration: float | None,
    distance: float | None,
    turn: float | None,
    teleop: bool,
    as_json: bool,
) -> _Plan:
    """Check the arguments together and against the limits; nothing is opened yet.

    Raises:
        typer.BadParameter: Names the option, its value and what is allowed.
    """
    for name, value in (
        ("--linear", linear),
        ("--angular", angular),
        ("--duration", duration),
        ("--distance", distance),
        ("--turn", turn),
    ):
        _finite(name, value)
    given = [
        name
        for name, value in (
            ("--duration", duration),
            ("--distance", distance),
            ("--turn", turn),
            ("--teleop", teleop or None),
        )
        if value is not None
    ]
    if len(given) > 1:
        raise typer.BadParameter(f"{given[0]} and {given[1]} do not combine: give one of them")
    _check_speed(config, linear, angular)
    if teleop:
        if as_json:
            raise typer.BadParameter("--json does not combine with --teleop (a live screen)")
        for name, value in (("--linear", linear), ("--angular", angular)):
            if value == 0:
                raise typer.BadParameter(f"{name}=0 gives a --teleop key no speed: give > 0")
        return _Plan("teleop", _linear_speed(config, linear), _angular_speed(config, angular))
    if distance is not None:
        if angular is not None:
            raise typer.BadParameter(
                "--angular does not combine with --distance (a straight drive): for an arc, "
                "give --linear, --angular and --duration"
            )
        if distance == 0:
            raise typer.BadParameter("--distance=0 goes nowhere: give a non-zero distance")
        _within("--distance", distance, -MAX_DISTANCE_M, MAX_DISTANCE_M, "m")
        speed = _linear_speed(config, linear)
        if speed < MIN_GOAL_LINEAR_MPS:
            top = _fmt(config.top_linear_mps())
            raise typer.BadParameter(
                f"--linear={_fmt(linear or 0.0)} is too slow for --distance: allowed "
                f"{MIN_GOAL_LINEAR_MPS:g}..{top} m/s either way (the sign comes from the distance)"
            )
        return _Plan("distance", linear_mps=speed, goal=distance)
    if turn is not None:
        if linear is not None:
            raise typer.BadParameter(
                "--linear does not combine with --turn (a turn on the spot): for an arc, "
                "give --linear, --angular and --duration"
            )
        if turn == 0:
            raise typer.BadParameter("--turn=0 turns nothing: give a non-zero angle in degrees")
        _within("--turn", turn, -MAX_TURN_DEG, MAX_TURN_DEG, "degrees")
        speed = _angular_speed(config, angular)
        if speed < MIN_GOAL_ANGULAR_RADPS:
            top = _fmt(config.top_angular_radps())
            raise typer.BadParameter(
                f"--angular={_fmt(angular or 0.0)} is too slow for --turn: allowed "
                f"{MIN_GOAL_ANGULAR_RADPS:g}..{top} rad/s either way (the sign comes from the turn)"
            )
        return _Plan("turn", angular_radps=speed, goal=turn)
    if linear is None and angular is None:
        raise typer.BadParameter(
            "nothing to drive: give --linear and/or --angular (with --duration), or "
            "--distance, --turn or --teleop"
        )
    if not linear and not angular:
        raise typer.BadParameter("--linear=0 with --angular=0 drives nowhere: give a speed")
    seconds = DEFAULT_DURATION_S if duration is None else duration
    if not 0 < seconds <= MAX_DURATION_S:
        raise typer.BadParameter(
            f"--duration={_fmt(seconds)} is out of range: allowed >0..{MAX_DURATION_S:g} s"
        )
    return _Plan("duration", linear or 0.0, angular or 0.0, duration_s=seconds)


def _wheel_plan(
    config: RobotConfig,
    *,
    pwm: tuple[float, float] | None,
    wheels: tuple[float, float] | None,
    others: dict[str, object],
    duration: float | None,
) -> _Plan:
    """``--pwm L R`` or ``--wheels L R``, with ``--duration`` alone, checked.

    Raises:
        typer.BadParameter: Names the option, its value and what is allowed.
    """
    from ohmni_tb.protocol.drive import PWM_LIMIT  # noqa: PLC0415

    name, values = ("--pwm", pwm) if pwm is not None else ("--wheels", wheels)
    assert values is not None
    if pwm is not None and wheels is not None:
        raise typer.BadParameter("--pwm and --wheels do not combine: give one of them")
    extra = [option for option, value in others.items() if value]
    if extra:
        raise typer.BadParameter(
            f"{name} does not combine with {extra[0]}: give {name} with --duration only"
        )
    for side, value in zip(("L", "R"), values, strict=True):
        _finite(f"{name} {side}", value)
        if pwm is not None:
            _within(f"{name} {side}", value, -PWM_LIMIT, PWM_LIMIT, "PWM")
        else:
            top = config.max_wheel_mps
            _within(f"{name} {side}", value, -top, top, "m/s", " (max_wheel_mps)")
    if not any(values):
        raise typer.BadParameter(f"{name} 0 0 drives nowhere: give a non-zero value")
    seconds = DEFAULT_DURATION_S if duration is None else duration
    _finite("--duration", seconds)
    if not 0 < seconds <= MAX_DURATION_S:
        raise typer.BadParameter(
            f"--duration={_fmt(seconds)} is out of range: allowed >0..{MAX_DURATION_S:g} s"
        )
    return _Plan(
        "pwm" if pwm is not None else "wheels",
        duration_s=seconds,
        left=float(values[0]),
        right=float(values[1]),
    )


def _unramped(plan: _Plan, no_ramp: bool, *, pwm: bool, wheels: bool) -> _Plan:
    """``plan`` with ``--no-ramp`` applied: a timed --linear/--angular drive only.

    Raises:
        typer.BadParameter: ``--no-ramp`` with another mode, naming it.
    """
    if not no_ramp:
        return plan
    if plan.mode != "duration":
        other = "--pwm" if pwm else "--wheels" if wheels else f"--{plan.mode}"
        why = "(no ramp there either)" if pwm or wheels else "(it ramps to stop where it should)"
        raise typer.BadParameter(
            f"--no-ramp does not combine with {other} {why}: give it with --linear/--angular "
            "and --duration"
        )
    return dataclasses.replace(plan, ramped=False)


def _linear_speed(config: RobotConfig, linear: float | None) -> float:
    """The speed a goal or teleop drive uses: ``--linear``'s size, else the default
    within the config's limit."""
    return abs(linear) if linear is not None else min(DEFAULT_LINEAR_MPS, config.top_linear_mps())


def _angular_speed(config: RobotConfig, angular: float | None) -> float:
    """The same for turning: ``--angular``'s size, else the default within the limit."""
    if angular is not None:
        return abs(angular)
    return min(DEFAULT_ANGULAR_RADPS, config.top_angular_radps())


# -- the command ----------------------------------------------------------------------------


def drive(
    linear: Annotated[
        float | None,
        typer.Option(
            "--linear",
            help="Forward speed, m/s (negative: backward). With --distance or --teleop: "
            f"the speed, its sign ignored (default {DEFAULT_LINEAR_MPS:g}).",
            show_default=False,
        ),
    ] = None,
    angular: Annotated[
        float | None,
        typer.Option(
            "--angular",
            help="Yaw rate, rad/s counter-clockwise (negative: clockwise). With --turn or "
            f"--teleop: the rate, its sign ignored (default {DEFAULT_ANGULAR_RADPS:g}).",
            show_default=False,
        ),
    ] = None,
    duration: Annotated[
        float | None,
        typer.Option(
            "--duration",
            help=f"How long to hold --linear/--angular, s (default {DEFAULT_DURATION_S:g}, "
            f"at most {MAX_DURATION_S:g}).",
            show_default=False,
        ),
    ] = None,
    distance: Annotated[
        float | None,
        typer.Option(
            "--distance",
            help="Drive this far straight by odometry, m (negative: backward), and stop there.",
            show_default=False,
        ),
    ] = None,
    turn: Annotated[
        float | None,
        typer.Option(
            "--turn",
            help="Turn on the spot this far by odometry, degrees (positive: "
            "counter-clockwise), and stop there.",
            show_default=False,
        ),
    ] = None,
    teleop: Annotated[
        bool,
        typer.Option(
            "--teleop",
            help="Drive with the keyboard: arrows or WASD, space stops, + and - change the "
            "speed, q quits.",
        ),
    ] = False,
    pwm: Annotated[
        tuple[float, float] | None,
        typer.Option(
            "--pwm",
            help="Open loop: the left and right wheel's PWM, -1000..1000 each, forward "
            "positive (robot.drive_pwm; fractions are rounded to whole steps), held for "
            "--duration. The wheel PIDs step aside; the watchdog still applies.",
            show_default=False,
        ),
    ] = None,
    wheels: Annotated[
        tuple[float, float] | None,
        typer.Option(
            "--wheels",
            help="Each wheel's speed, m/s, forward positive (robot.drive_wheels: no ramp, "
            "within max_wheel_mps), held for --duration.",
            show_default=False,
        ),
    ] = None,
    no_ramp: Annotated[
        bool,
        typer.Option(
            "--no-ramp",
            help="With --linear/--angular for --duration: the pure velocity command "
            "(robot.drive(..., ramped=False), tb_control's /tb_cmd_vel): the wheel setpoints "
            "jump to the target instead of ramping; still within the speed limits and the "
            "watchdog, and the stop still ramps down.",
        ),
    ] = False,
    source: Annotated[
        str | None,
        typer.Option(
            "--source",
            help="The command source the commands go as (command_sources): default local on "
            "the robot's own computer (the port opened here, or a daemon on loopback), remote "
            "from elsewhere. A higher source that drives refuses them meanwhile.",
            show_default=False,
        ),
    ] = None,
    port: PortOption = None,
    direct: DirectOption = False,
    yes: YesOption = False,
    as_json: JsonOption = False,
) -> None:
    """Drive for a time, a distance or a turn, stop, and print what the odometry measured.

    --linear/--angular are held for --duration (re-sent faster than the motion watchdog),
    then the robot stops and the stop is confirmed by the wheel counts. --distance and
    --turn drive by odometry, slow down near the goal and fail (exit 1) if it is not
    reached in time or a wheel does not turn. --teleop drives from the keyboard: each key
    press drives for the watchdog time, so releasing the key stops the robot. Speeds past
    the Robot's limits are refused. On a real robot it asks first (--yes skips that); on
    sim:// it does not, nor through a daemon serving sim://. The commands go as the
    command source local on the robot's computer and remote elsewhere (--source): a
    higher source that drives refuses them meanwhile.

    Examples:

    ohmni drive --linear 0.3 --duration 2 --port sim://

    ohmni drive --distance 0.5 --json --port sim://

    ohmni drive --turn -90 --angular 0.5 --port /dev/ttyUSB0 --yes

    ohmni drive --teleop --port sim://

    ohmni drive --pwm 250 250 --duration 0.5 --port sim://

    ohmni drive --wheels 0.2 0.1 --duration 2 --port sim://

    ohmni drive --linear 0.3 --no-ramp --duration 1 --port sim://
    """
    from ohmni_tb.config import RobotConfig  # noqa: PLC0415  # pydantic: only when run

    try:
        config = RobotConfig.load()
    except OhmniError as exc:
        error_line(str(exc))
        raise typer.Exit(1) from exc
    if pwm is not None or wheels is not None:
        plan = _wheel_plan(
            config,
            pwm=pwm,
            wheels=wheels,
            others={
                "--linear": linear is not None,
                "--angular": angular is not None,
                "--distance": distance is not None,
                "--turn": turn is not None,
                "--teleop": teleop,
            },
            duration=duration,
        )
    else:
        plan = _plan(
            config,
            linear=linear,
            angular=angular,
            duration=duration,
            distance=distance,
            turn=turn,
            teleop=teleop,
            as_json=as_json,
        )
    plan = _unramped(plan, no_ramp, pwm=pwm is not None, wheels=wheels is not None)
    stdin_fd: int | None = None
    if plan.mode == "teleop":
        stdin_fd = _terminal_fd()
    via = daemon_for(port, direct)
    try:
        url = via or resolve_port(port)
    except OhmniError as exc:
        error_line(str(exc))
        raise typer.Exit(1) from exc
    sources = [row.name for row in config.source_table()]
    if source is not None and via is None and source not in sources:
        raise typer.BadParameter(
            f"--source={source!r} is not a command source: allowed {', '.join(sources)} "
            "(command_sources)"
        )
    source = source if source is not None else drive_source(via)
    what = {
        "duration": "ohmni drive",
        "distance": "ohmni drive --distance",
        "turn": "ohmni drive --turn",
        "teleop": "ohmni drive --teleop",
        "pwm": "ohmni drive --pwm",
        "wheels": "ohmni drive --wheels",
    }[plan.mode]
    confirm_motion(url, what, yes=yes)
    watch = RobotWarnings()

    def interrupted() -> None:
        if not watch.opened:
            _err.print("interrupted while the robot was opening: nothing was driven")
        elif watch.stop is None and not watch.unconfirmed:
            _err.print("interrupted: the wheel stop was confirmed on the way out")

    if stdin_fd is not None:
        fd = stdin_fd
        with _raw_terminal(fd):
            summary = run(
                lambda: _with_robot(
                    url,
                    via,
                    watch,
                    lambda robot, watch: _teleop(robot, watch, plan, fd, url),
                    source,
                ),
                on_interrupt=interrupted,
            )
        _print_result(summary, teleop=True)
        return
    result = run(
        lambda: _with_robot(
            url, via, watch, lambda robot, _watch: _timed_or_goal(robot, plan, as_json), source
        ),
        on_interrupt=interrupted,
    )
    if as_json:
        emit_json({"port": url, "source": source, **result})
    else:
        _print_result(result, teleop=False)


def _terminal_fd() -> int:
    """stdin's descriptor for --teleop.

    Raises:
        typer.BadParameter: stdin is not a terminal, or there are no POSIX terminals.
    """
    try:
        import termios  # noqa: F401, PLC0415  # POSIX only
    except ImportError:
        raise typer.BadParameter("--teleop needs a POSIX terminal (termios)") from None
    try:
        fd = sys.stdin.fileno()
        tty = os.isatty(fd)
    except (AttributeError, OSError, ValueError):
        tty = False
    if not tty:
        raise typer.BadParameter(
            "--teleop reads keys from a terminal, and stdin is not one: run it in a terminal"
        )
    return fd


@contextmanager
def _raw_terminal(fd: int) -> Iterator[None]:
    """Keys one at a time, unechoed, Ctrl-C as a key; the output processing stays on (so
    a newline still returns the carriage). Restored on any exit."""
    import termios  # noqa: PLC0415  # POSIX only, checked by _terminal_fd

    saved = termios.tcgetattr(fd)
    mode = termios.tcgetattr(fd)
    mode[0] &= ~(termios.BRKINT | termios.ICRNL | termios.INPCK | termios.ISTRIP | termios.IXON)
    mode[3] &= ~(termios.ECHO | termios.ICANON | termios.IEXTEN | termios.ISIG)
    mode[6][termios.VMIN] = 1
    mode[6][termios.VTIME] = 0
    termios.tcsetattr(fd, termios.TCSAFLUSH, mode)
    try:
        yield
    finally:
        # TCSAFLUSH: the key repeats still queued do not spill into the shell.
        termios.tcsetattr(fd, termios.TCSAFLUSH, saved)


# -- the Robot ------------------------------------------------------------------------------


async def _with_robot(
    port: str,
    via: str | None,
    watch: RobotWarnings,
    body: Callable[[Robot, RobotWarnings], Awaitable[T]],
    source: str,
) -> T:
    """Open the Robot, check it can drive, run ``body``; the Robot stops on the way out.

    Raises:
        OhmniError: What went wrong; a stop not confirmed on the way out after another
            error is printed first (the robot may be moving).
    """
    logger = logging.getLogger(_LOGGER)
    logger.addHandler(watch)
    try:
        async with common.open_robot(port, via=via, control=True, source=source) as robot:
            watch.opened = True
            await _ready(robot)
            return await body(robot, watch)
    except OhmniError as exc:
        if watch.stop is not None and watch.stop is not exc:
            if not isinstance(exc, StopNotConfirmedError):  # else the same news, twice
                error_line(str(exc))
            raise watch.stop from exc
        raise
    except BaseException:
        # Ctrl-C or a cancellation: still say it if the stop could not be confirmed.
        if watch.stop is not None:
            _err.print(f"[bold red]{escape(str(watch.stop))}[/bold red]", soft_wrap=True)
        raise
    finally:
        logger.removeHandler(watch)


async def _ready(robot: Robot) -> None:
    """Both drive boards answer and their counts come in.

    Raises:
        StateError: A drive board is silent, or no wheel counts arrive.
    """
    from ohmni_tb.protocol.devices import DeviceId  # noqa: PLC0415

    present = robot.state.present
    silent = [int(sid) for sid in (DeviceId.LEFT_DRIVE, DeviceId.RIGHT_DRIVE) if sid not in present]
    if silent:
        if len(silent) == 1:
            which = f"drive board {silent[0]} does not answer"
        else:
            which = f"drive boards {' and '.join(map(str, silent))} do not answer"
        raise StateError(f"{which}: the robot cannot drive")
    if robot.latest("wheel_odom") is not None:
        return
    try:
        async with asyncio.timeout(_FIRST_SAMPLE_S), robot.subscribe("wheel_odom") as odom:
            async for _ in odom:
                return
    except TimeoutError:
        pass
    raise StateError(f"no wheel counts within {_FIRST_SAMPLE_S:g} s: the robot cannot drive")


def _command_period(robot: Robot) -> float:
    watchdog = robot.config.watchdog_s
    return COMMAND_PERIOD_S if watchdog <= 0 else min(COMMAND_PERIOD_S, watchdog / 3)


@dataclass(frozen=True, slots=True)
class _Snapshot:
    """Odometry and wheel travel at one control tick, and the truth on sim://."""

    stamp_s: float
    x_m: float
    y_m: float
    heading_rad: float
    travel_m: float  # the mean of both wheels' travel since open, forward positive
    truth: tuple[float, float, float] | None

    @staticmethod
    def take(robot: Robot) -> _Snapshot:
        odom = robot.latest("wheel_odom")
        enc = robot.latest("wheel_encoder")
        if odom is None or enc is None:
            raise StateError("no odometry yet")
        return _Snapshot.of(robot, odom, enc)

    @staticmethod
    def of(robot: Robot, odom: WheelOdomSample, enc: WheelEncoderSample) -> _Snapshot:
        truth = None
        if robot.sim is not None:
            pose = robot.sim.pose
            truth = (float(pose.x), float(pose.y), float(pose.yaw))
        return _Snapshot(
            odom.stamp_s,
            odom.x_m,
            odom.y_m,
            odom.heading_rad,
            (enc.left_m + enc.right_m) / 2,
            truth,
        )


def _relative(
    start: tuple[float, float, float], end: tuple[float, float, float]
) -> dict[str, float]:
    """``end`` in the frame of ``start``: x forward, y left, yaw the heading change wrapped."""
    x0, y0, h0 = start
    dx, dy = end[0] - x0, end[1] - y0
    turned = end[2] - h0
    return {
        "x_m": round(math.cos(h0) * dx + math.sin(h0) * dy, 4),
        "y_m": round(-math.sin(h0) * dx + math.cos(h0) * dy, 4),
        "yaw_deg": round(math.degrees(math.atan2(math.sin(turned), math.cos(turned))), 2),
    }


def _measured(start: _Snapshot, end: _Snapshot, first_command_s: float) -> dict[str, Any]:
    """What the odometry measured between two snapshots, for the report."""
    turned = end.heading_rad - start.heading_rad
    travelled = end.travel_m - start.travel_m
    elapsed = max(end.stamp_s - first_command_s, 1e-9)
    truth = None
    if start.truth is not None and end.truth is not None:
        truth = _relative(start.truth, end.truth)
        truth["heading_change_deg"] = round(math.degrees(end.truth[2] - start.truth[2]), 2)
    return {
        "distance_m": round(travelled, 4),
        "heading_change_deg": round(math.degrees(turned), 2),
        "heading_change_rad": round(turned, 5),
        "pose": _relative(
            (start.x_m, start.y_m, start.heading_rad), (end.x_m, end.y_m, end.heading_rad)
        ),
        "elapsed_s": round(elapsed, 3),
        "average_linear_mps": round(travelled / elapsed, 4),
        "average_angular_radps": round(turned / elapsed, 4),
        "truth": truth,
    }


async def _stopped(robot: Robot) -> dict[str, Any]:
    """Stop, confirm it, and say how long it took."""
    robot.stop()
    report = await common.confirm_stop(robot, STOP_CONFIRM_TIMEOUT_S)
    return {"confirmed": True, "after_s": round(report.elapsed_s, 3), "samples": report.reads}


# -- timed and goal drives ------------------------------------------------------------------


async def _timed_or_goal(robot: Robot, plan: _Plan, quiet: bool) -> dict[str, Any]:
    before = robot.stats()
    if plan.timed:
        result = await _timed(robot, plan, quiet)
    else:
        result = await _to_goal(robot, plan, quiet)
    return {**result, **_losses(before, robot)}


def _losses(before: RobotStats, robot: Robot) -> dict[str, int]:
    """Feedback lost and regained during a drive (a cable, a silent board): the boards
    kept their last command meanwhile, and the odometry missed that motion."""
    after = robot.stats()
    return {
        "link_losses": after.bus.link_losses - before.bus.link_losses,
        "missed_counts": after.streams["wheel_encoder"].missed
        - before.streams["wheel_encoder"].missed,
    }


async def _timed(robot: Robot, plan: _Plan, quiet: bool) -> dict[str, Any]:
    loop = asyncio.get_running_loop()
    period = _command_period(robot)
    command, call = _timed_command(plan)
    if not quiet:
        console.print(
            f"drive: {command} for {plan.duration_s:g} s ({call}() re-sent every "
            f"{period:g} s), then stop",
            highlight=False,
            soft_wrap=True,
        )
    start = _Snapshot.take(robot)
    first = loop.time()
    try:
        end = first + plan.duration_s
        while True:
            _send(robot, plan)
            left = end - loop.time()
            if left <= 0:
                break
            await asyncio.sleep(min(period, left))
    finally:
        # Whatever happened above, Ctrl-C included: the target goes to zero now.
        robot.stop()
    stop = await _stopped(robot)
    if plan.mode == "pwm":
        sent: dict[str, Any] = {"left_pwm": plan.left, "right_pwm": plan.right}
    elif plan.mode == "wheels":
        sent = {"left_mps": plan.left, "right_mps": plan.right}
    else:
        sent = {
            "linear_mps": plan.linear_mps,
            "angular_radps": plan.angular_radps,
            "ramped": plan.ramped,
        }
    return {
        "mode": plan.mode,
        "command": {**sent, "duration_s": plan.duration_s},
        "goal": None,
        **_measured(start, _Snapshot.take(robot), first),
        "stop": stop,
    }


def _timed_command(plan: _Plan) -> tuple[str, str]:
    """What a timed drive sends, for people, and the Robot call that sends it."""
    if plan.mode == "pwm":
        return f"PWM left {plan.left:+g}, right {plan.right:+g} (open loop)", "drive_pwm"
    if plan.mode == "wheels":
        return f"left wheel {plan.left:+.2f} m/s, right {plan.right:+.2f} m/s", "drive_wheels"
    speeds = f"{plan.linear_mps:+.2f} m/s, {plan.angular_radps:+.2f} rad/s"
    if not plan.ramped:
        return f"{speeds} (no ramp)", "drive"
    return speeds, "drive"


def _send(robot: Robot, plan: _Plan) -> None:
    """One command of a timed drive."""
    if plan.mode == "pwm":
        robot.drive_pwm(plan.left, plan.right)
    elif plan.mode == "wheels":
        robot.drive_wheels(plan.left, plan.right)
    else:
        robot.drive(plan.linear_mps, plan.angular_radps, ramped=plan.ramped)


def _goal_timeout(goal: float, speed: float, accel: float, decel: float) -> float:
    """Time a goal drive may take: the Robot's default for it."""
    from ohmni_tb.robot.motion import goal_timeout_s  # noqa: PLC0415  # the Robot is open

    return goal_timeout_s(goal, speed, accel, decel)


async def _to_goal(robot: Robot, plan: _Plan, quiet: bool) -> dict[str, Any]:
    """Drive to ``plan.goal`` with the Robot's motion goal (``drive_distance`` or
    ``rotate``), then confirm the stop by the wheel counts.

    Raises:
        MotionError: Not there: out of time, a wheel stalled, the counts stopped (the
            robot is stopped, and the stop confirmed, first).
    """
    config = robot.config
    loop = asyncio.get_running_loop()
    linear = plan.mode == "distance"
    sign = 1.0 if plan.goal > 0 else -1.0
    if linear:
        top = plan.linear_mps
        timeout_s = _goal_timeout(
            abs(plan.goal), top, config.linear_accel_mps2, config.linear_decel_mps2
        )
        goal_text = f"{plan.goal:+.3f} m at up to {top:.3g} m/s"
    else:
        top = plan.angular_radps
        timeout_s = _goal_timeout(
            math.radians(abs(plan.goal)),
            top,
            config.angular_accel_radps2,
            config.angular_decel_radps2,
        )
        goal_text = f"{plan.goal:+.1f}° at up to {top:.3g} rad/s"
    if not quiet:
        console.print(
            f"drive: {'straight' if linear else 'turn on the spot'} {goal_text} by odometry, "
            f"slowing down near the goal (timeout {timeout_s:.1f} s)",
            highlight=False,
            soft_wrap=True,
        )
    start = _Snapshot.take(robot)
    first = loop.time()
    failure: MotionError | None = None
    try:
        if linear:
            await robot.drive_distance(plan.goal, speed_mps=top, timeout_s=timeout_s)
        else:
            await robot.rotate(math.radians(plan.goal), speed_radps=top, timeout_s=timeout_s)
    except MotionError as exc:
        failure = exc
    finally:
        # Whatever happened above, Ctrl-C included: the target is zero.
        robot.stop()
    stop = await _stopped(robot)
    end = _Snapshot.take(robot)
    measured = _measured(start, end, first)
    if failure is not None:
        raise failure
    if linear:
        goal: dict[str, float] = {"distance_m": plan.goal}
        error = {"error_m": round(measured["distance_m"] - plan.goal, 4)}
    else:
        goal = {"turn_deg": plan.goal}
        error = {"error_deg": round(measured["heading_change_deg"] - plan.goal, 2)}
    return {
        "mode": plan.mode,
        "command": {
            "linear_mps": sign * top if linear else 0.0,
            "angular_radps": 0.0 if linear else sign * top,
            "timeout_s": round(timeout_s, 2),
        },
        "goal": {**goal, **error},
        **measured,
        "stop": stop,
    }


def _print_result(result: dict[str, Any], *, teleop: bool) -> None:
    stop = result["stop"]
    pose = result["pose"]
    keys = result["keys"] if teleop else 0
    lines = [f"teleop: {keys} key press{'' if keys == 1 else 'es'}"] if teleop else []
    if result.get("link_losses") or result.get("missed_counts"):
        lines.append(
            f"[yellow]warning: during the drive the link was lost {result['link_losses']} "
            f"time(s) and {result['missed_counts']} control cycles brought no wheel counts: "
            "the odometry below may have missed motion[/yellow]"
        )
    lines += [
        f"stop confirmed {stop['after_s']:.3f} s after the stop (both wheel counts held still, "
        f"{stop['samples']} wheel_encoder samples)",
    ]
    goal = result.get("goal")
    if goal is not None and "distance_m" in goal:
        lines.append(
            f"goal      {goal['distance_m']:+.3f} m, went {result['distance_m']:+.3f} m "
            f"({goal['error_m'] * 1000:+.1f} mm)"
        )
    elif goal is not None:
        lines.append(
            f"goal      {goal['turn_deg']:+.1f}°, turned {result['heading_change_deg']:+.1f}° "
            f"({goal['error_deg']:+.2f}°)"
        )
    lines += [
        f"distance  {result['distance_m']:+.3f} m (mean wheel travel, forward positive)",
        f"heading   {result['heading_change_deg']:+.1f}° ({result['heading_change_rad']:+.4f} rad)",
        f"pose      x={pose['x_m']:+.3f} m  y={pose['y_m']:+.3f} m  yaw={pose['yaw_deg']:+.1f}° "
        "(from the start)",
        f"average   {result['average_linear_mps']:+.3f} m/s, "
        f"{result['average_angular_radps']:+.3f} rad/s over {result['elapsed_s']:.2f} s "
        f"({'from the first key' if teleop else 'from the first command'} to the stop)",
    ]
    truth = result.get("truth")
    if truth is not None:
        off_mm = math.hypot(truth["x_m"] - pose["x_m"], truth["y_m"] - pose["y_m"]) * 1000
        lines.append(
            f"truth     x={truth['x_m']:+.3f} m  y={truth['y_m']:+.3f} m  "
            f"yaw={truth['yaw_deg']:+.1f}° (the simulator's; odometry {off_mm:.1f} mm off)"
        )
    for line in lines:
        console.print(line, highlight=False, soft_wrap=True)


# -- teleop ---------------------------------------------------------------------------------


def _teleop_screen(robot: Robot, state: KeyTeleop, start: _Snapshot, port: str, note: str) -> Any:
    from rich.table import Table  # noqa: PLC0415

    table = Table.grid(padding=(0, 2))
    table.add_column(style="bold")
    table.add_column()
    table.add_row("drive", "w/↑ forward  s/↓ back  a/← left  d/→ right  (hold the key)")
    table.add_row("keys", "space stop  + faster  - slower  q or Ctrl-C quit")
    table.add_row(
        "speed", f"{state.linear_mps:.2f} m/s, {state.angular_radps:.2f} rad/s a key press"
    )
    linear, angular = state.command
    table.add_row("command", f"{state.action}: {linear:+.2f} m/s, {angular:+.2f} rad/s")
    odom = robot.latest("wheel_odom")
    if odom is not None:
        pose = _relative(
            (start.x_m, start.y_m, start.heading_rad), (odom.x_m, odom.y_m, odom.heading_rad)
        )
        table.add_row(
            "odometry",
            f"x={pose['x_m']:+.3f} m  y={pose['y_m']:+.3f} m  yaw={pose['yaw_deg']:+.1f}°  "
            f"{odom.linear_mps:+.2f} m/s  {odom.angular_radps:+.2f} rad/s",
        )
    state_sample = robot.state
    flags = [
        *state_sample.faults,
        *(["watchdog tripped"] if state_sample.watchdog_tripped else []),
    ]
    robot_line = f"{port}, link {state_sample.link}" + (f", {', '.join(flags)}" if flags else "")
    active = state_sample.active_source
    table.add_row(
        "source",
        escape(
            f"{robot.source}"
            + ("" if active in (None, robot.source) else f" (overridden: {active} drives)")
        ),
    )
    table.add_row("robot", escape(robot_line))
    if note:
        table.add_row("note", escape(note))
    return table


async def _teleop(
    robot: Robot, watch: RobotWarnings, plan: _Plan, fd: int, port: str
) -> dict[str, Any]:
    from rich.live import Live  # noqa: PLC0415

    from ohmni_tb.robot.teleop import KeyParser, KeyTeleop  # noqa: PLC0415

    loop = asyncio.get_running_loop()
    state = KeyTeleop(
        robot, linear_mps=plan.linear_mps or None, angular_radps=plan.angular_radps or None
    )
    notes = [""]  # the newest warning, shown under the keys
    parser = KeyParser()
    failure: list[BaseException] = []
    wake = asyncio.Event()

    def readable() -> None:
        try:
            data = os.read(fd, 256)
        except (BlockingIOError, InterruptedError):
            return
        except OSError:
            data = b""
        if not data:  # the terminal went away
            state.quit = True
        try:
            for action in parser.feed(data):
                state.press(action, loop.time())
        except SourceOverriddenError as exc:  # a higher source drives: told, not fatal
            notes[0] = str(exc)
        except OhmniError as exc:  # an emergency stop latched, the robot closed
            failure.append(exc)
            state.quit = True
        if state.quit:
            wake.set()

    def note(text: str) -> None:
        notes[0] = text

    shown = watch.show
    watch.show = note
    start = _Snapshot.take(robot)
    before = robot.stats()
    loop.add_reader(fd, readable)
    try:
        with Live(
            _teleop_screen(robot, state, start, port, notes[0]),
            console=console,
            auto_refresh=False,
            redirect_stdout=False,
            redirect_stderr=False,
        ) as live:
            while not state.quit:
                try:
                    async with asyncio.timeout(_REDRAW_S):
                        await wake.wait()
                except TimeoutError:
                    parser.flush()
                state.decay(loop.time())
                live.update(_teleop_screen(robot, state, start, port, notes[0]), refresh=True)
    finally:
        loop.remove_reader(fd)
        robot.stop()
        watch.show = shown
    if failure:
        raise failure[0]
    stop = await _stopped(robot)
    first = state.first_key_s if state.first_key_s is not None else start.stamp_s
    return {
        "mode": "teleop",
        "keys": state.keys,
        "goal": None,
        **_measured(start, _Snapshot.take(robot), first),
        "stop": stop,
        **_losses(before, robot),
    }
