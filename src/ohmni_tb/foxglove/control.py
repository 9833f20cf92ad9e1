"""Foxglove services and parameters of a Robot: what the app's panels may read and change.

Parameters (the app's Parameters panel), named after tb_control's node:

- ``/tb_control/pid_kp`` … ``pid_ff_offset``: the wheel PIDs' gains (:class:`PidGains`),
  changed bumplessly for both wheels;
- ``/tb_control/rate/<stream>``: a polled stream's rate in Hz (``wheel_encoder`` is the
  control tick, ``servo_neck`` …);
- ``/tb_control/max_linear_mps``, ``max_angular_radps``, ``max_wheel_mps``,
  ``watchdog_s``: the limits, read only (they are the Robot's configuration: a client on
  an unauthenticated port does not raise them).

Services (JSON requests and responses, schemas advertised):

- ``/tb_control/reset_odom``: ``{"x_m": 0, "y_m": 0, "yaw_rad": 0}`` (each optional) →
  the pose odometry now starts from;
- ``/tb_control/set_odometry``: ``{"x_m": 1.5, "y_m": -0.5, "yaw_rad": 1.57}`` (each
  required: diff_drive_controller's ``~/set_odometry``) → the pose set;
- ``/tb_control/neck_move``: ``{"raw": 400}`` or ``{"rad": 0.1}``, with ``playtime_s``
  (HerkuleX neck; a worm-gear neck takes ``raw`` alone) → ``{"moved": true}``.

Reading is always allowed; changing only through a :class:`RobotControl` made with
``writable=True`` (``FoxgloveBridge(..., control=..., token=...)``, ``ohmni serve
--foxglove-control``), by a client that unlocked control. The ranges are the Robot's own
(``Robot.set_pid``, ``Robot.set_rate``): this module keeps none. A refused change names
the value and the allowed range, as every command does, and reaches the client at once
(through the daemon too: each change is confirmed before the answer); nothing reaches
the wire.
"""

from __future__ import annotations

import dataclasses
import json
from collections.abc import Awaitable, Callable
from typing import TYPE_CHECKING, Any, Final

from ohmni_tb._checks import number
from ohmni_tb.errors import InvalidArgumentError, StateError
from ohmni_tb.robot.samples import STREAMS

if TYPE_CHECKING:
    from ohmni_tb.robot import Robot

__all__ = [
    "LIMIT_PARAMETERS",
    "NECK_MOVE_SERVICE",
    "PARAMETER_PREFIX",
    "PID_PARAMETERS",
    "RATE_STREAMS",
    "RESET_ODOM_SERVICE",
    "SERVICE_SCHEMAS",
    "SET_ODOMETRY_SERVICE",
    "RobotControl",
]

#: Every parameter's name starts with this (tb_control's node).
PARAMETER_PREFIX: Final = "/tb_control/"
#: ``/tb_control/pid_<gain>``: the PidGains field each one is.
PID_PARAMETERS: Final = {
    "pid_kp": "kp",
    "pid_ki": "ki",
    "pid_kd": "kd",
    "pid_kff": "kff",
    "pid_ff_offset": "ff_offset",
}
#: ``/tb_control/rate/<stream>``: the polled streams whose rate can be read and set.
RATE_STREAMS: Final = tuple(name for name, spec in STREAMS.items() if spec.polled)
#: Read-only limits: the RobotConfig fields shown.
LIMIT_PARAMETERS: Final = ("max_linear_mps", "max_angular_radps", "max_wheel_mps", "watchdog_s")

RESET_ODOM_SERVICE: Final = "/tb_control/reset_odom"
SET_ODOMETRY_SERVICE: Final = "/tb_control/set_odometry"
NECK_MOVE_SERVICE: Final = "/tb_control/neck_move"


def _object(properties: dict[str, Any], **extra: Any) -> dict[str, Any]:
    return {"type": "object", "properties": properties, "additionalProperties": False, **extra}


_NUMBER: Final = {"type": "number"}
_POSE: Final = _object({"x_m": _NUMBER, "y_m": _NUMBER, "yaw_rad": _NUMBER})
#: Each service's (request, response) JSON Schema.
SERVICE_SCHEMAS: Final[dict[str, tuple[dict[str, Any], dict[str, Any]]]] = {
    RESET_ODOM_SERVICE: (_POSE, _POSE),
    SET_ODOMETRY_SERVICE: ({**_POSE, "required": ["x_m", "y_m", "yaw_rad"]}, _POSE),
    NECK_MOVE_SERVICE: (
        _object({"raw": {"type": "integer"}, "rad": _NUMBER, "playtime_s": _NUMBER}),
        _object({"moved": {"type": "boolean"}}),
    ),
}


class RobotControl:
    """The parameters and services of ``robot`` (module docstring).

    Args:
        robot: An open :class:`~ohmni_tb.Robot`, on a port or a daemon's (``ohmni
            serve`` gives the Foxglove clients a :class:`~ohmni_tb.client.RobotClient`,
            whose changes go through the daemon's control lease).
        writable: Whether parameters may be set and services called.
        before_change: Awaited before each change (``ohmni serve`` takes the daemon's
            control lease there, and raises when another client holds it).
    """

    def __init__(
        self,
        robot: Robot,
        *,
        writable: bool = False,
        before_change: Callable[[], Awaitable[None]] | None = None,
    ) -> None:
        self._robot = robot
        self.writable = writable
        self._before_change = before_change

    @property
    def services(self) -> tuple[str, ...]:
        """The services offered: none unless writable."""
        return tuple(SERVICE_SCHEMAS) if self.writable else ()

    async def parameters(self) -> dict[str, float]:
        """Every parameter's value now, by full name (a stream the robot does not poll is
        left out)."""
        robot = self._robot
        gains = robot.get_pid()
        stats = robot.stats()
        config = robot.config
        values: dict[str, float] = {}
        for name, field in PID_PARAMETERS.items():
            values[PARAMETER_PREFIX + name] = float(getattr(gains, field))
        for stream in RATE_STREAMS:
            figures = stats.streams.get(stream)
            if figures is not None and figures.requested_hz > 0:
                values[f"{PARAMETER_PREFIX}rate/{stream}"] = float(figures.requested_hz)
        for name in LIMIT_PARAMETERS:
            values[PARAMETER_PREFIX + name] = float(getattr(config, name))
        return values

    async def set_parameters(self, values: dict[str, Any]) -> None:
        """Set parameters by full name; the PID gains in one bumpless change.

        Raises:
            StateError: Not writable, or a read-only limit.
            InvalidArgumentError: An unknown name, or a value that is not a finite number.
            OutOfRangeError: A value outside its range (the Robot's own check, through the
                daemon too); the changes before it in ``values`` stay made.
        """
        self._check_writable()
        gains: dict[str, float] = {}
        rates: dict[str, float] = {}
        for full, value in values.items():
            name = full.removeprefix(PARAMETER_PREFIX)
            if name in PID_PARAMETERS:
                gains[PID_PARAMETERS[name]] = number(full, value)
            elif name.startswith("rate/") and name[5:] in RATE_STREAMS:
                rates[name[5:]] = number(full, value)
            elif name in LIMIT_PARAMETERS:
                raise StateError(f"{full} is read only: set it in the Robot's configuration")
            else:
                raise InvalidArgumentError(f"no parameter {full!r}")
        await self._change()
        if gains:
            current = self._robot.get_pid()
            self._robot.set_pid(dataclasses.replace(current, **gains))
            await self._confirm()
        for stream, hz in rates.items():
            self._robot.set_rate(stream, hz)
            await self._confirm()

    async def call(self, service: str, request: bytes) -> bytes:
        """Answer a service call (JSON in, JSON out).

        Raises:
            StateError: Not writable.
            InvalidArgumentError: Unknown service, not a JSON object, or unknown fields.
            OhmniError: What the Robot refused (a value out of range …); nothing sent.
        """
        self._check_writable()
        try:
            args = json.loads(request or b"{}")
        except ValueError as exc:
            raise InvalidArgumentError(f"{service}: the request is not JSON: {exc}") from exc
        schema = SERVICE_SCHEMAS.get(service)
        if schema is None:
            raise InvalidArgumentError(f"no service {service!r}")
        allowed = schema[0]["properties"]
        if not isinstance(args, dict) or set(args) - set(allowed):
            raise InvalidArgumentError(
                f"{service} takes a JSON object with {', '.join(allowed)}, not {request[:80]!r}"
            )
        if service in (RESET_ODOM_SERVICE, SET_ODOMETRY_SERVICE):
            if service == SET_ODOMETRY_SERVICE and set(allowed) - set(args):
                raise InvalidArgumentError(
                    f"{service} takes x_m, y_m and yaw_rad, all three; missing "
                    f"{', '.join(sorted(set(allowed) - set(args)))}"
                )
            pose = {key: number(key, args.get(key, 0.0)) for key in allowed}
            await self._change()
            if service == SET_ODOMETRY_SERVICE:
                self._robot.set_odometry(**pose)
            else:
                self._robot.reset_odometry(**pose)
            await self._confirm()
            return json.dumps(pose).encode()
        raw, rad = args.get("raw"), args.get("rad")
        if (raw is None) == (rad is None):
            raise InvalidArgumentError(f"{service} takes raw or rad, one of them")
        options: dict[str, Any] = {}
        if rad is not None:
            options["rad"] = number("rad", rad)
        if "playtime_s" in args:
            options["playtime_s"] = number("playtime_s", args["playtime_s"])
        await self._change()
        await self._robot.neck.move(raw, **options)
        return json.dumps({"moved": True}).encode()

    async def _change(self) -> None:
        """Just before a change reaches the Robot (the daemon's lease is taken here)."""
        if self._before_change is not None:
            await self._before_change()

    async def _confirm(self) -> None:
        """Wait for the daemon's answer to the commands sent (a remote robot's plain
        commands are not awaited): its refusal is this change's, told now, and not left
        to fail the next command (a Teleop Twist). A local robot refuses as it is called."""
        await self._robot.confirm()

    def _check_writable(self) -> None:
        if not self.writable:
            raise StateError(
                "this Foxglove server is read only: start it with control "
                "(ohmni serve --foxglove-control)"
            )
