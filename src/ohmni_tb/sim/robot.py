"""The simulated Ohmni: every device of the bus map on one simulated line.

``open_transport("sim://")`` builds one from the URL's options; the table of every
option (the robot's and the line's) is in :mod:`ohmni_tb.sim.url`. The robot's own are
``neck`` (``0101``, ``0201`` or ``worm``), ``ext_servos`` (external servo ids), ``soc``,
``docked``, ``count_offset`` and the bus profile's settings (``wheel_form``,
``battery_addr`` ...: :data:`~ohmni_tb.protocol.profile.PROFILE_SETTINGS`), so the
simulator can play any profile ``ohmni probe`` may meet.

The :class:`SimRobot` is reachable from the transport (``transport.robot``) for tests
and tools: its ground-truth pose, the dock, the power switch, obstacles against the
wheels (:meth:`SimRobot.block_wheels`), wheels that lose their traction
(:meth:`SimRobot.slip_wheels`). The URL options ``stall`` and ``slip`` (drive board ids)
start it so, and ``ohmni sim``'s console sets them by board id (:meth:`SimRobot.stall`,
:meth:`SimRobot.slip`).
"""

from __future__ import annotations

from collections.abc import Callable

from ohmni_tb.errors import ConfigError, InvalidArgumentError
from ohmni_tb.herkulex import Model
from ohmni_tb.protocol.devices import DeviceId
from ohmni_tb.protocol.profile import DEFAULT_PROFILE, PROFILE_SETTINGS, BusProfile
from ohmni_tb.sim.core import BatteryPack, SimCoreBoard
from ohmni_tb.sim.device import SimDevice
from ohmni_tb.sim.drive import DriveTrain, MotorModel, Pose, SimDriveBoard
from ohmni_tb.sim.servo import SimServo
from ohmni_tb.sim.worm_neck import SimWormNeck
from ohmni_tb.transport import option_bool

__all__ = ["NECK_CHOICES", "SimRobot"]

NECK_CHOICES = ("0101", "0201", "worm")


class SimRobot:
    """Every simulated device of one robot.

    Args:
        neck: ``"0101"``, ``"0201"`` (HerkuleX neck at sid 3) or ``"worm"`` (sid 4).
        ext_servo_ids: Ids of the external HerkuleX servos (default the profile's).
        profile: What the boards speak: the wheel command's form, the right motor's
            mounting, the torque register, the battery block's address, length and
            layout, the worm neck's registers, the external servo ids.
        soc_percent: Battery state of charge at start.
        docked: Start on the dock.
        count_offset: Initial accumulated count of both drive boards.
        motor: Motor and wheel parameters.
        wheel_separation_m: True wheel separation.
    """

    def __init__(
        self,
        *,
        neck: str = "0101",
        ext_servo_ids: tuple[int, ...] | None = None,
        soc_percent: float = 80.0,
        docked: bool = False,
        count_offset: int = 0,
        motor: MotorModel | None = None,
        wheel_separation_m: float = 0.330,
        profile: BusProfile = DEFAULT_PROFILE,
    ) -> None:
        if ext_servo_ids is None:
            ext_servo_ids = profile.ext_servo_ids
        self.profile = profile
        if neck not in NECK_CHOICES:
            raise ConfigError(f"neck={neck!r} is not one of {', '.join(NECK_CHOICES)}")
        if not 0 <= soc_percent <= 100:
            raise ConfigError(f"soc={soc_percent} is out of range: allowed 0..100 %")
        reserved = {int(d) for d in DeviceId}
        if len(set(ext_servo_ids)) != len(ext_servo_ids):
            raise ConfigError(
                f"external servo ids {ext_servo_ids} repeat an id; they would collide"
            )
        if not -(2**31) <= count_offset < 2**31:
            raise ConfigError(
                f"count_offset={count_offset} is out of range: allowed -2**31..2**31-1"
            )
        for sid in ext_servo_ids:
            if sid in reserved or not 0 <= sid <= 0xFD:
                raise ConfigError(f"external servo id {sid} clashes with a board or is not 0..253")
        self.train = DriveTrain(
            motor,
            wheel_separation_m=wheel_separation_m,
            count_offsets=(count_offset,) * 2,
            profile=profile.drive,
        )
        self.left = SimDriveBoard(DeviceId.LEFT_DRIVE, self.train)
        self.right = SimDriveBoard(DeviceId.RIGHT_DRIVE, self.train)
        self.core = SimCoreBoard(BatteryPack(soc=soc_percent / 100.0), profile=profile.core)
        self.core.pack.extra_load = self.train.motor_current_a
        self.core.load_sync = self.train.advance
        self.core.set_docked(docked)
        self.neck: SimServo | SimWormNeck
        if neck == "worm":
            self.neck = SimWormNeck(profile=profile.worm)
        else:
            model = Model.DRS_0101 if neck == "0101" else Model.DRS_0201
            self.neck = SimServo(DeviceId.HERKULEX_NECK, model=model)
        self.ext_servos = [SimServo(sid) for sid in ext_servo_ids]
        self._clock: Callable[[], float] | None = None

    def attach_clock(self, clock: Callable[[], float]) -> None:
        """Give the robot its line's clock, so readings are taken at the present time."""
        self._clock = clock

    def sync(self) -> float:
        """Advance every device to the line's present time and return that time."""
        if self._clock is None:
            return 0.0
        now = self._clock()
        for device in self.devices:
            device.advance(now)
        return now

    @property
    def devices(self) -> list[SimDevice]:
        """Every device on the line."""
        return [self.left, self.right, self.core, self.neck, *self.ext_servos]

    @property
    def pose(self) -> Pose:
        """The true pose of the robot now (metres, radians; yaw unwrapped)."""
        self.sync()
        return self.train.pose

    def wheel_speeds_mps(self) -> tuple[float, float]:
        """The true forward speed of the left and right wheel now."""
        self.sync()
        return self.train.wheel_speeds_mps()

    def set_docked(self, docked: bool) -> None:
        """Put the robot on its dock or take it off (from now on)."""
        self.sync()
        self.core.set_docked(docked)

    def block_wheels(self, *, left: bool, right: bool) -> None:
        """Put an obstacle against the left and/or right wheel, or take it away (from now on).

        A blocked wheel does not turn whatever its board's PWM (its count holds, its speed
        reads 0) and its motor draws the stall current of its duty from the pack; one
        turning is stopped dead. ``block_wheels(left=False, right=False)`` frees both.
        """
        self.sync()
        self.train.block(0, left)
        self.train.block(1, right)

    def unblock_wheels(self) -> None:
        """Take every obstacle away from the wheels (from now on)."""
        self.block_wheels(left=False, right=False)

    @property
    def blocked_wheels(self) -> tuple[bool, bool]:
        """Whether the left and the right wheel are blocked."""
        return self.train.blocked()

    def slip_wheels(self, *, left: bool, right: bool) -> None:
        """Take the left and/or right wheel's traction away, or give it back (from now on).

        A wheel without traction (a slippery patch, or lifted) still turns and counts,
        free of the robot's load, so it runs faster at the same PWM than on the ground;
        the robot moves as if that wheel stood (:mod:`ohmni_tb.sim.drive`).
        ``slip_wheels(left=False, right=False)`` gives both their grip back.
        """
        self.sync()
        self.train.slip(0, left)
        self.train.slip(1, right)

    @property
    def slipping_wheels(self) -> tuple[bool, bool]:
        """Whether the left and the right wheel have lost their traction."""
        return self.train.slipping()

    def stall(self, sid: int, on: bool = True) -> None:
        """Block the wheel of drive board ``sid`` (the id it answers to now), or free it
        (``on=False``): :meth:`block_wheels` for one board.

        Raises:
            InvalidArgumentError: No drive board answers to ``sid``.
        """
        side = self._side(sid)
        self.sync()
        self.train.block(side, on)

    def slip(self, sid: int, on: bool = True) -> None:
        """Take the traction of drive board ``sid``'s wheel away, or give it back
        (``on=False``): :meth:`slip_wheels` for one board.

        Raises:
            InvalidArgumentError: No drive board answers to ``sid``.
        """
        side = self._side(sid)
        self.sync()
        self.train.slip(side, on)

    def _side(self, sid: int) -> int:
        for board in (self.left, self.right):
            if board.sid == sid:
                return board.side
        raise InvalidArgumentError(
            f"no drive board answers to id {sid}: the drive boards answer to "
            f"{self.left.sid} (left) and {self.right.sid} (right)"
        )

    @classmethod
    def from_options(cls, options: dict[str, str]) -> SimRobot:
        """Build from ``sim://`` URL options, consuming the ones it knows.

        Raises:
            ConfigError: An option's value is invalid; the message names it.
        """
        neck = options.pop("neck", "0101")
        profile = _profile_from_options(options)
        ext_ids = profile.ext_servo_ids
        for key in ("ext", "ext_servos"):
            ext_text = options.pop(key, None)
            if ext_text is not None:
                ext_ids = parse_ids(key, ext_text)
        try:
            soc = float(options.pop("soc", "80"))
        except ValueError:
            raise ConfigError("option soc must be a number of percent") from None
        docked = option_bool(options, "docked", False)
        try:
            count_offset = int(options.pop("count_offset", "0"), 0)
        except ValueError:
            raise ConfigError("option count_offset must be an integer") from None
        stalled = _board_ids("stall", options.pop("stall", ""))
        slipping = _board_ids("slip", options.pop("slip", ""))
        robot = cls(
            neck=neck,
            ext_servo_ids=ext_ids,
            soc_percent=soc,
            docked=docked,
            count_offset=count_offset,
            profile=profile,
        )
        for sid in stalled:
            robot.stall(sid)
        for sid in slipping:
            robot.slip(sid)
        return robot


def _board_ids(name: str, text: str) -> tuple[int, ...]:
    """The drive board ids of option ``name`` (``"0,1"``; ``""`` or ``none``: none).

    Raises:
        ConfigError: An id is not a drive board's (0 left, 1 right).
    """
    ids = parse_ids(name, text)
    drives = (int(DeviceId.LEFT_DRIVE), int(DeviceId.RIGHT_DRIVE))
    for sid in ids:
        if sid not in drives:
            raise ConfigError(
                f"option {name}: id {sid} is not a drive board's: allowed 0 (left), 1 (right)"
            )
    return ids


def _profile_from_options(options: dict[str, str]) -> BusProfile:
    """The profile the URL's options give (the assumed one for the rest), consuming them.

    Raises:
        ConfigError: An option's value is invalid; the message names it.
    """
    given = {key: options.pop(key) for key in PROFILE_SETTINGS if key in options}
    try:
        return BusProfile.from_settings(given)
    except InvalidArgumentError as exc:
        raise ConfigError(f"sim:// option {exc}") from None


def parse_ids(name: str, text: str) -> tuple[int, ...]:
    """Parse ``"11,12"`` (or ``"none"``) into device ids.

    Raises:
        ConfigError: An id is not an integer in 0..253.
    """
    if text.strip().lower() in {"", "none"}:
        return ()
    ids = []
    for part in text.split(","):
        try:
            sid = int(part.strip(), 0)
        except ValueError:
            raise ConfigError(f"option {name}: {part!r} is not a device id") from None
        if not 0 <= sid <= 0xFD:
            raise ConfigError(f"option {name}: id {sid} is out of range: allowed 0..253")
        ids.append(sid)
    return tuple(ids)
