"""The DRS-0101 / DRS-0201 register maps, as one data table (sans-IO).

Both models share one map. EEP holds the power-up settings; on power-up and REBOOT the
servo copies EEP 6..53 to RAM 0..47 (RAM address = EEP address - 6), so the settings
present in both memories come from a single row of :data:`_TABLE` that yields an EEP and
a RAM :class:`Register`. EEP 0..5 exist only in EEP; RAM 48..73 only in RAM::

    EEP  0 model no1  1 model no2  2-3 firmware  4 baud  5 reserved
    EEP  6 ........................................... 53   settings
           \\ copied on power-up / REBOOT
    RAM  0 ........................................... 47   settings (act at once)
    RAM 48 status error  49 status detail  52 torque  53 LED  54.. feedback (read-only)

Multi-byte values are little-endian; the rows marked signed are two's complement. Every
write is checked here (read-only, range, allowed values) before any packet exists.

Where the reference gives no range, the register's natural byte range is used. The
feedback registers 68/70/72 are listed read-only as in the manual's RAM table.
"""

from __future__ import annotations

import enum
from collections.abc import Iterator, Mapping
from dataclasses import dataclass
from typing import Final

from ohmni_tb._checks import show
from ohmni_tb.errors import InvalidArgumentError, MalformedReplyError, OutOfRangeError
from ohmni_tb.protocol import Memory, StatusDetail, StatusError
from ohmni_tb.protocol.messages import STATUS_DETAILS, STATUS_ERRORS

__all__ = [
    "EEP",
    "EEP_SIZE",
    "FEEDBACK_ADDR",
    "FEEDBACK_SIZE",
    "RAM",
    "RAM_SIZE",
    "BaudRate",
    "Led",
    "Model",
    "Register",
    "RegisterMap",
    "ServoFeedback",
    "TorqueControl",
    "decode_feedback",
    "memory_of",
    "model_from_bytes",
    "resolve",
    "write_targets",
]

#: EEP 0..53: the last EEP register is the calibration difference at 53.
EEP_SIZE: Final = 54
#: RAM 0..73: the last RAM register is the desired velocity at 72..73.
RAM_SIZE: Final = 74
#: RAM address = EEP address - this, for the settings both memories hold (EEP 6..53).
EEP_TO_RAM_OFFSET: Final = 6


class Model(enum.IntEnum):
    """The servo model, as EEP 0 (model no1) reports it."""

    DRS_0101 = 0x01
    DRS_0201 = 0x02


class Led(enum.IntFlag):
    """LED bits of RAM 53. A JOG's SET byte carries the same bits shifted left by 2."""

    NONE = 0
    GREEN = 0x01
    BLUE = 0x02
    RED = 0x04


class TorqueControl(enum.IntEnum):
    """RAM 52 values."""

    FREE = 0x00
    #: Holds by braking the motor; JOGs are ignored.
    BRAKE = 0x40
    ON = 0x60


class BaudRate(enum.IntEnum):
    """EEP 4 baud codes (they act after REBOOT)."""

    B57600 = 0x22
    B115200 = 0x10
    B200000 = 0x09
    B250000 = 0x07
    B400000 = 0x04
    B500000 = 0x03
    B666666 = 0x02

    @property
    def bps(self) -> int:
        """The line speed in bits per second."""
        return _BAUD_BPS[self]


_BAUD_BPS: Final[Mapping[BaudRate, int]] = {
    BaudRate.B57600: 57_600,
    BaudRate.B115200: 115_200,
    BaudRate.B200000: 200_000,
    BaudRate.B250000: 250_000,
    BaudRate.B400000: 400_000,
    BaudRate.B500000: 500_000,
    BaudRate.B666666: 666_666,
}


@dataclass(frozen=True, slots=True)
class Register:
    """One register of one memory.

    Attributes:
        name: The register's name, shared by its EEP and RAM copies (``"ack_policy"``).
        memory: RAM or EEP.
        addr: The address of its first byte.
        size: 1 or 2 bytes (little-endian).
        default: The factory value, or ``None`` where it depends on the unit (model,
            firmware) or is measured at run time (feedback).
        low: The smallest value a write accepts.
        high: The largest value a write accepts.
        signed: Whether the bytes are two's complement.
        read_only: Whether a write is refused.
        unit: The unit of one count (``"count"``, ``"tick"`` = 11.2 ms, ``"%"``…), or ``""``.
        choices: The only values a write accepts, where the register is an enumeration.
    """

    name: str
    memory: Memory
    addr: int
    size: int
    default: int | None
    low: int
    high: int
    signed: bool = False
    read_only: bool = False
    unit: str = ""
    choices: frozenset[int] | None = None

    @property
    def end(self) -> int:
        """The address just after the register's last byte."""
        return self.addr + self.size

    def check(self, value: int) -> int:
        """Return ``value`` as a plain int if a write of it is allowed.

        Raises:
            InvalidArgumentError: The register is read-only, ``value`` is not an int, or
                it is not one of ``choices``.
            OutOfRangeError: ``value`` is outside ``low..high``.
        """
        if self.read_only:
            raise InvalidArgumentError(
                f"{self.memory.name} {self.addr} ({self.name}) is read-only; nothing was sent"
            )
        if isinstance(value, bool) or not isinstance(value, int):
            raise InvalidArgumentError(
                f"{self.name} takes an int, not {type(value).__name__} {value!r}"
            )
        if not self.low <= value <= self.high:
            raise OutOfRangeError(self.name, value, self.low, self.high, self.unit)
        if self.choices is not None and value not in self.choices:
            allowed = ", ".join(f"0x{c:02X}" for c in sorted(self.choices))
            raise InvalidArgumentError(f"{self.name}={value!r} is not one of {allowed}")
        return int(value)

    def encode(self, value: int) -> bytes:
        """Check ``value`` (see :meth:`check`) and return its bytes, little-endian.

        Raises:
            InvalidArgumentError: The register is read-only, ``value`` is not an int, or
                it is not one of ``choices``.
            OutOfRangeError: ``value`` is out of range.
        """
        return self.check(value).to_bytes(self.size, "little", signed=self.signed)

    def decode(self, data: bytes | bytearray) -> int:
        """Decode the register's bytes (little-endian, signed where the register is).

        Values the device reports are not range-checked: a reading is a fact.

        Raises:
            InvalidArgumentError: ``data`` is not exactly ``size`` bytes long.
        """
        if len(data) != self.size:
            raise InvalidArgumentError(
                f"{self.name} is {self.size} byte(s), got {len(data)}: {bytes(data).hex(' ')}"
            )
        return int.from_bytes(data, "little", signed=self.signed)


class RegisterMap:
    """The registers of one memory, looked up by name or by address.

    ``RAM["torque_control"]`` and ``RAM.by_addr(52)`` give the same register; iterating
    yields the registers in address order.
    """

    __slots__ = ("_by_addr", "_by_name", "memory", "size")

    def __init__(self, memory: Memory, size: int, registers: tuple[Register, ...]) -> None:
        self.memory = memory
        self.size = size
        self._by_name = {r.name: r for r in sorted(registers, key=lambda r: r.addr)}
        self._by_addr = {r.addr: r for r in registers}

    def __getitem__(self, name: str) -> Register:
        return self.by_name(name)

    def __contains__(self, name: object) -> bool:
        return name in self._by_name

    def __iter__(self) -> Iterator[Register]:
        return iter(self._by_name.values())

    def __len__(self) -> int:
        return len(self._by_name)

    def __repr__(self) -> str:
        return f"RegisterMap({self.memory.name}, {len(self)} registers)"

    def by_name(self, name: str) -> Register:
        """The register called ``name``.

        Raises:
            InvalidArgumentError: No register of this memory has that name.
        """
        try:
            return self._by_name[name]
        except KeyError:
            raise InvalidArgumentError(
                f"no {self.memory.name} register named {name!r}; known: {', '.join(self._by_name)}"
            ) from None

    def by_addr(self, addr: int) -> Register:
        """The register whose first byte is at ``addr``.

        Raises:
            InvalidArgumentError: ``addr`` is not an int, or no register starts there
                (reserved, the second byte of a 2-byte register, or past the end of the
                memory); the message says which.
        """
        if isinstance(addr, bool) or not isinstance(addr, int):
            raise InvalidArgumentError(
                f"a {self.memory.name} address must be an int, not {type(addr).__name__} "
                f"{show(addr)}"
            )
        found = self._by_addr.get(addr)
        if found is None:
            raise InvalidArgumentError(
                f"no {self.memory.name} register starts at address {show(addr)}"
                f"{self._why_none_at(addr)}"
            )
        return found

    def _why_none_at(self, addr: int) -> str:
        """Why no register starts at ``addr``, for the error: inside one, reserved, or out."""
        if not 0 <= addr < self.size:
            return f" (the {self.memory.name} addresses are 0..{self.size - 1})"
        for reg in self:
            if reg.addr < addr < reg.end:
                return (
                    f" (it is byte {addr - reg.addr + 1} of {reg.name}, "
                    f"{self.memory.name} {reg.addr}..{reg.end - 1})"
                )
        return " (reserved on these models)"

    def writable(self, addr: int, length: int) -> bool:
        """Whether every byte of ``addr..addr+length-1`` exists and may be written.

        Reserved bytes inside the memory are writable (the firmware stores them); bytes
        of read-only registers and bytes past the end are not.

        Raises:
            InvalidArgumentError: ``addr`` or ``length`` is not an int.
        """
        for name, value in (("addr", addr), ("length", length)):
            if isinstance(value, bool) or not isinstance(value, int):
                raise InvalidArgumentError(f"{name} must be an int, not {show(value)}")
        if addr < 0 or length < 0 or addr + length > self.size:
            return False
        return not any(r.read_only and r.addr < addr + length and addr < r.end for r in self)


def memory_of(memory: Memory | str) -> Memory:
    """``memory`` as a :class:`~ohmni_tb.protocol.Memory`: the enum, or ``"ram"``/``"eep"``.

    Raises:
        InvalidArgumentError: Anything else.
    """
    if isinstance(memory, Memory):
        return memory
    if isinstance(memory, str) and memory.lower() in ("ram", "eep"):
        return Memory(memory.lower())
    raise InvalidArgumentError(f"memory must be RAM or EEP ('ram', 'eep'), not {show(memory)}")


def write_targets(
    register: Register | str | int,
    value: int,
    *,
    persist: bool = False,
    memory: Memory | str = Memory.RAM,
) -> list[Register]:
    """The registers a servo write goes to, in the order to write them, each checked: the
    EEP register alone (``memory`` EEP), or the RAM one, after its EEP copy with
    ``persist``.

    Raises:
        InvalidArgumentError: Unknown register or memory, no register at that address, a
            read-only one, a bad value, ``persist`` with an EEP write, or ``persist`` of a
            register with no EEP copy.
        OutOfRangeError: The value is out of the register's range.
    """
    memory = memory_of(memory)
    if memory is Memory.EEP:
        if persist:
            raise InvalidArgumentError(
                "persist=True also writes the EEP copy of a RAM register; an EEP write is "
                "persistent already: give one of them"
            )
        targets = [resolve(register, Memory.EEP)]
    else:
        reg = resolve(register, Memory.RAM)
        targets = [reg]
        if persist:
            if reg.name not in EEP:
                raise InvalidArgumentError(f"{reg.name} has no EEP copy to persist")
            targets.insert(0, EEP[reg.name])
    for target in targets:
        target.check(value)
    return targets


def resolve(register: Register | str | int, memory: Memory) -> Register:
    """Return the ``memory`` register named by ``register``: an object, a name, or the
    address of its first byte (``resolve(30, Memory.EEP)`` is the EEP ``position_kp``,
    as tb_control's ``servo_write_eep`` names it).

    Raises:
        InvalidArgumentError: Unknown name, no register at that address (the message
            says why: reserved, inside a 2-byte register, out of the memory), or a
            register object of the other memory.
    """
    table = RAM if memory is Memory.RAM else EEP
    if isinstance(register, str):
        return table.by_name(register)
    if isinstance(register, int) and not isinstance(register, bool):
        return table.by_addr(register)
    if not isinstance(register, Register):
        raise InvalidArgumentError(
            f"register must be a Register, a name or an address, not {type(register).__name__}"
        )
    if register.memory is not memory:
        raise InvalidArgumentError(
            f"{register.name} at {register.memory.name} {register.addr} is not a "
            f"{memory.name} register; use the {memory.name} map"
        )
    return register


def model_from_bytes(data: bytes | bytearray) -> Model:
    """Detect the model from the two bytes of EEP 0..1 (a read of addr 0, length 2).

    The first byte (EEP 0, model no1) is the model; the second (model no2) is 0x01 on
    both, so a driver that reads them in the wrong order takes every DRS-0201 for a
    DRS-0101.

    Raises:
        InvalidArgumentError: ``data`` is not two bytes, or names an unknown model.
    """
    if len(data) != 2:
        raise InvalidArgumentError(f"model detection needs EEP 0..1 (2 bytes), got {len(data)}")
    try:
        return Model(data[0])
    except ValueError:
        raise InvalidArgumentError(
            f"unknown HerkuleX model no1 0x{data[0]:02X} (0x01 = DRS-0101, 0x02 = DRS-0201)"
        ) from None


# -- the table ------------------------------------------------------------------------

_U8: Final = 0xFF
_TICKS: Final = "tick"  # 11.2 ms


@dataclass(frozen=True, slots=True)
class _Row:
    """One line of the map: an EEP address, a RAM address, or both (EEP 6..53)."""

    name: str
    eep: int | None
    ram: int | None
    size: int = 1
    default: int | None = None
    low: int | None = None
    high: int | None = None
    signed: bool = False
    read_only: bool = False
    unit: str = ""
    choices: frozenset[int] | None = None


# The columns follow the reference's table: name, EEP address, RAM address. Ranges left
# out are the natural range of the bytes.
# fmt: off
_TABLE: Final[tuple[_Row, ...]] = (
    # EEP only: identity and link. Model no1 and the firmware differ per unit.
    _Row("model_no1", 0, None, read_only=True),
    _Row("model_no2", 1, None, default=0x01, read_only=True),
    _Row("firmware_version", 2, None, size=2, read_only=True),
    _Row("baud_rate", 4, None, default=BaudRate.B115200, choices=frozenset(BaudRate)),
    # Settings in both memories. 0xFE is broadcast, so no servo may take it as its id.
    _Row("id", 6, 0, default=0xFD, high=0xFD),
    _Row("ack_policy", 7, 1, default=1, high=2),
    _Row("alarm_led_policy", 8, 2, default=0x7F, high=0x7F, unit="mask"),
    _Row("torque_policy", 9, 3, default=0x35, high=0x7F, unit="mask"),
    _Row("max_temperature", 11, 5, default=0xDE, unit="raw"),
    _Row("min_voltage", 12, 6, default=0x5B, unit="0.074 V"),
    _Row("max_voltage", 13, 7, default=0x89, unit="0.074 V"),
    _Row("acceleration_ratio", 14, 8, default=25, high=50, unit="%"),
    _Row("max_acceleration_time", 15, 9, default=0x2D, high=0xFE, unit=_TICKS),
    _Row("dead_zone", 16, 10, default=0, unit="count"),
    _Row("saturator_offset", 17, 11, default=0),
    _Row("saturator_slope", 18, 12, size=2, default=0, high=0x7FFF),
    _Row("pwm_offset", 20, 14, default=0, signed=True),
    _Row("min_pwm", 21, 15, default=0),
    _Row("max_pwm", 22, 16, size=2, default=1023, high=1023),
    _Row("overload_pwm_threshold", 24, 18, size=2, default=1022, high=0x7FFE),
    _Row("min_position", 26, 20, size=2, default=21, high=1023, unit="count"),
    _Row("max_position", 28, 22, size=2, default=1002, high=1023, unit="count"),
    _Row("position_kp", 30, 24, size=2, default=440, high=0x7FFF),
    _Row("position_kd", 32, 26, size=2, default=8000, high=0x7FFF),
    _Row("position_ki", 34, 28, size=2, default=0, high=0x7FFF),
    _Row("position_feedforward_gain1", 36, 30, size=2, default=0, high=0x7FFF),
    _Row("position_feedforward_gain2", 38, 32, size=2, default=0, high=0x7FFF),
    _Row("led_blink_period", 44, 38, default=0x2D, unit=_TICKS),
    _Row("adc_fault_check_period", 45, 39, default=0x2D, unit=_TICKS),
    _Row("packet_garbage_check_period", 46, 40, default=0x12, unit=_TICKS),
    _Row("stop_detection_period", 47, 41, default=0x1B, unit=_TICKS),
    _Row("overload_detection_period", 48, 42, default=0x96, unit=_TICKS),
    _Row("stop_threshold", 49, 43, default=3, unit="count"),
    _Row("inposition_margin", 50, 44, default=3, unit="count"),
    _Row("calibration_difference", 53, 47, default=0, signed=True, unit="count"),
    # RAM only: status (write zeros to clear), control, then feedback.
    _Row("status_error", None, 48, default=0, high=0x7F, unit="mask"),
    _Row("status_detail", None, 49, default=0, high=0x7F, unit="mask"),
    _Row("torque_control", None, 52, default=TorqueControl.FREE,
         choices=frozenset(TorqueControl)),
    _Row("led_control", None, 53, default=Led.NONE, high=0x07, unit="mask"),
    _Row("voltage", None, 54, read_only=True, unit="0.074 V"),
    _Row("temperature", None, 55, read_only=True, unit="raw"),
    _Row("current_control_mode", None, 56, read_only=True),
    _Row("tick", None, 57, read_only=True, unit=_TICKS),
    # 58 is the JOG coordinate (absolute - calibration difference); 60 is the raw pot.
    _Row("calibrated_position", None, 58, size=2, read_only=True, unit="count"),
    _Row("absolute_position", None, 60, size=2, read_only=True, unit="count"),
    _Row("differential_position", None, 62, size=2, signed=True, read_only=True,
         unit="29.09 deg/s"),
    _Row("pwm", None, 64, size=2, signed=True, read_only=True),
    _Row("absolute_goal_position", None, 68, size=2, read_only=True, unit="count"),
    _Row("absolute_desired_trajectory_position", None, 70, size=2, read_only=True,
         unit="count"),
    _Row("desired_velocity", None, 72, size=2, signed=True, read_only=True,
         unit="29.09 deg/s"),
)
# fmt: on


def _build(memory: Memory, size: int) -> RegisterMap:
    regs: list[Register] = []
    for row in _TABLE:
        addr = row.eep if memory is Memory.EEP else row.ram
        if addr is None:
            continue
        bits = 8 * row.size
        if row.signed:
            natural_low, natural_high = -(1 << (bits - 1)), (1 << (bits - 1)) - 1
        else:
            natural_low, natural_high = 0, (1 << bits) - 1
        if row.choices is not None:
            natural_low, natural_high = min(row.choices), max(row.choices)
        regs.append(
            Register(
                name=row.name,
                memory=memory,
                addr=addr,
                size=row.size,
                default=None if row.default is None else int(row.default),
                low=natural_low if row.low is None else row.low,
                high=natural_high if row.high is None else row.high,
                signed=row.signed,
                read_only=row.read_only,
                unit=row.unit,
                choices=row.choices,
            )
        )
    return RegisterMap(memory, size, tuple(regs))


#: The EEP map (settings that act after REBOOT, plus model, firmware and baud).
EEP: Final = _build(Memory.EEP, EEP_SIZE)
#: The RAM map (live settings, status, torque, LED and feedback).
RAM: Final = _build(Memory.RAM, RAM_SIZE)


# -- the feedback block ---------------------------------------------------------------

#: The block a stream polls in one read: RAM 48 (status error) through 59 (the calibrated
#: position's high byte): status, torque, voltage, temperature and position together.
FEEDBACK_ADDR: Final = RAM["status_error"].addr
FEEDBACK_SIZE: Final = RAM["calibrated_position"].end - FEEDBACK_ADDR


@dataclass(frozen=True, slots=True)
class ServoFeedback:
    """One read of the feedback block (RAM 48..59), decoded.

    Attributes:
        status_error: RAM 48.
        status_detail: RAM 49.
        torque: RAM 52, the torque mode.
        voltage_raw: RAM 54, 0.074 V a count (:func:`~ohmni_tb.herkulex.voltage_v_from_raw`).
        temperature_raw: RAM 55, raw.
        position_raw: RAM 58..59, the calibrated position, 0..1023.
    """

    status_error: StatusError
    status_detail: StatusDetail
    torque: TorqueControl
    voltage_raw: int
    temperature_raw: int
    position_raw: int


def decode_feedback(data: bytes | bytearray) -> ServoFeedback:
    """Decode the data of a read of the feedback block (:data:`FEEDBACK_ADDR`, 12 bytes).

    Raises:
        MalformedReplyError: ``data`` is not :data:`FEEDBACK_SIZE` bytes, or its torque
            byte is not a :class:`TorqueControl` value.
    """
    if len(data) != FEEDBACK_SIZE:
        raise MalformedReplyError(
            f"a servo feedback block is {FEEDBACK_SIZE} bytes, got {len(data)}: "
            f"{bytes(data).hex(' ')}"
        )
    torque = _TORQUE_MODES.get(data[_TORQUE])
    if torque is None:
        raise MalformedReplyError(f"servo feedback: torque byte 0x{data[_TORQUE]:02X}")
    return ServoFeedback(
        status_error=STATUS_ERRORS[data[_STATUS_ERROR]],
        status_detail=STATUS_DETAILS[data[_STATUS_DETAIL]],
        torque=torque,
        voltage_raw=data[_VOLTAGE],
        temperature_raw=data[_TEMPERATURE],
        # A position is 10 bits on these models: the register's upper bits are not one.
        position_raw=(data[_POSITION] | data[_POSITION + 1] << 8) & 0x3FF,
    )


#: Each register's offset in the block, from the map (the one place addresses live).
_STATUS_ERROR: Final = RAM["status_error"].addr - FEEDBACK_ADDR
_STATUS_DETAIL: Final = RAM["status_detail"].addr - FEEDBACK_ADDR
_TORQUE: Final = RAM["torque_control"].addr - FEEDBACK_ADDR
_VOLTAGE: Final = RAM["voltage"].addr - FEEDBACK_ADDR
_TEMPERATURE: Final = RAM["temperature"].addr - FEEDBACK_ADDR
_POSITION: Final = RAM["calibrated_position"].addr - FEEDBACK_ADDR
#: The torque byte to its mode (an enum call per sample costs more).
_TORQUE_MODES: Final[Mapping[int, TorqueControl]] = {int(mode): mode for mode in TorqueControl}
