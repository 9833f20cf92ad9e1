"""Virtual HerkuleX DRS-0101 / DRS-0201 firmware.

:class:`SimServo` answers the same bytes as the real servo: it keeps a full EEP (54 bytes)
and RAM (74 bytes) file, copies EEP 6..53 to RAM 0..47 at construction, REBOOT and power
cycle, obeys its id (RAM 0) and ACK policy (RAM 1) through
:func:`~ohmni_tb.protocol.reply_expected`, and replies ``addr, len, bytes, status_error,
status_detail`` to reads and the two status bytes to everything else it answers. Time is
injected (``now_s``); nothing here reads a clock, so a test runs minutes of servo time in
microseconds. Everything a test observes is read out of the registers.

Physics (simple, closed-form in time, so the result does not depend on how often the
servo is advanced):

* **Torque** (RAM 52): free (0x00) and brake (0x40) hold the position where it is (no
  gravity) and ignore JOGs; on (0x60) follows them. Turning torque on holds the current
  position. Changing between position and turn mode needs torque off first: once a JOG
  has run under torque, a JOG of the other mode is ignored until torque leaves "on".
* **Position JOG**: the goal (calibrated coordinate) is clamped to RAM 20..22 and offset
  by the calibration difference (RAM 47) to the absolute coordinate. The servo follows a
  trapezoidal velocity profile from where it is: it accelerates for ``ratio`` (RAM 8, %)
  of the playtime but no longer than the max acceleration time (RAM 9), cruises, and
  decelerates symmetrically, arriving exactly at the end of the playtime. Tracking is
  ideal, except that the move is stretched when it would need more than the model's
  no-load speed (playtime 0 = as fast as it can).
* **Turn JOG**: speed = PWM / 1023 × no-load speed (PWM magnitude capped by RAM 16);
  the absolute position wraps modulo 1024.
* **Feedback**: RAM 60 = absolute position, 58 = 60 − calibration difference, 62 =
  speed in units of 29.09 °/s, 64 = PWM = 1023 × (load + speed / no-load speed) while
  torque is on (0 otherwise), 68 = absolute goal, 70 = trajectory point (= 60, since
  tracking is ideal), 72 = trajectory speed (= 62), 56 = control mode, 57 = ticks of
  11.2 ms since boot, 54 = supply voltage / 0.074 V, 55 = temperature (raw, truncated).
* **Status detail** (RAM 49), all three only while torque is on: MOVING while a
  trajectory runs (or a turn JOG spins); INPOSITION in position mode within the
  in-position margin (RAM 44) of the goal, so it rises shortly before MOVING falls;
  MOTOR_ON. Packet faults are latched
  there (CHECKSUM_ERROR, UNKNOWN_COMMAND, EXCEED_REG_RANGE, GARBAGE_DETECTED) together
  with StatusError.INVALID_PACKET in RAM 48.
* **Temperature**: a first-order model in raw ADC units (the real sensor curve is not
  public): it relaxes towards ``ambient + 100 × load²`` while torque is on and towards
  ambient otherwise, with a 120 s time constant; :meth:`SimServo.set_load` sets the
  external load as a fraction of stall torque. At raw ≥ max temperature (RAM 5) the
  servo sets StatusError.TEMPERATURE; the error latches in RAM 48 until a write of zeros
  clears it, and it comes straight back while the temperature is still at the limit.
  Supply voltage outside RAM 6..7 sets INPUT_VOLTAGE the same way.
* **Torque policy** (RAM 3): while RAM 48 has a bit of the mask, torque is released and
  a write of brake/on to RAM 52 is ignored; clear RAM 48/49, then turn torque on again.

Not modelled: overload, position-limit and driver-fault detection, EEP distortion, the
alarm LED blinking, PID gains, dead zone, saturator, load-dependent tracking error, and
the baud rate (EEP 4 is stored; line speed is the simulated line's business).
Values written to registers are stored as sent (the builders are what refuse bad
values); only the addresses are checked, as the firmware does. A request the servo
cannot interpret (malformed layout, unknown command, a read outside the map) gets no
reply; a well-formed write to a read-only or missing address is acknowledged (policy 2)
with the error bits set.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Final

from ohmni_tb.errors import InvalidArgumentError, OutOfRangeError, ProtocolError
from ohmni_tb.herkulex.commands import JogMode, JogTarget, decode_jog
from ohmni_tb.herkulex.registers import (
    EEP,
    EEP_SIZE,
    EEP_TO_RAM_OFFSET,
    RAM,
    RAM_SIZE,
    Model,
    Register,
    RegisterMap,
    TorqueControl,
)
from ohmni_tb.herkulex.units import (
    DEG_PER_COUNT,
    DEG_S_PER_DIFF,
    POSITION_MAX_RAW,
    TICK_S,
    VOLT_PER_COUNT,
)
from ohmni_tb.protocol import (
    BROADCAST_ID,
    REPLY_FLAG,
    Command,
    Packet,
    RejectReason,
    StatusDetail,
    StatusError,
    reply_expected,
)
from ohmni_tb.sim.device import SimDevice

__all__ = [
    "AMBIENT_TEMP_RAW",
    "NO_LOAD_SPEED_DPS",
    "SIM_FIRMWARE_VERSION",
    "TEMP_RISE_FULL_LOAD_RAW",
    "THERMAL_TIME_CONSTANT_S",
    "SimServo",
]

#: Datasheet no-load speed at 7.4 V (0.166 s / 60° for the 0101, 0.147 s / 60° for the 0201).
NO_LOAD_SPEED_DPS: Final = {Model.DRS_0101: 60 / 0.166, Model.DRS_0201: 60 / 0.147}
#: The firmware version bytes (EEP 2..3) are not public; the simulator reports this.
SIM_FIRMWARE_VERSION: Final = 0x0001
#: Room temperature as a raw sensor value. A placeholder: the sensor curve is not public.
AMBIENT_TEMP_RAW: Final = 160.0
#: Equilibrium rise over ambient when holding full stall torque (I²R heating ∝ load²).
TEMP_RISE_FULL_LOAD_RAW: Final = 100.0
#: Heating and cooling time constant of the first-order thermal model.
THERMAL_TIME_CONSTANT_S: Final = 120.0
#: The nominal supply of these servos.
NOMINAL_SUPPLY_V: Final = 7.4

_ID = RAM["id"]
_ACK = RAM["ack_policy"]
_TORQUE_POLICY = RAM["torque_policy"]
_MAX_TEMP = RAM["max_temperature"]
_MIN_VOLT = RAM["min_voltage"]
_MAX_VOLT = RAM["max_voltage"]
_ACCEL_RATIO = RAM["acceleration_ratio"]
_MAX_ACCEL_TIME = RAM["max_acceleration_time"]
_MAX_PWM = RAM["max_pwm"]
_MIN_POS = RAM["min_position"]
_MAX_POS = RAM["max_position"]
_MARGIN = RAM["inposition_margin"]
_CAL_DIFF = RAM["calibration_difference"]
_ERROR = RAM["status_error"]
_DETAIL = RAM["status_detail"]
_TORQUE = RAM["torque_control"]
_LED = RAM["led_control"]
_VOLTAGE = RAM["voltage"]
_TEMPERATURE = RAM["temperature"]
_MODE = RAM["current_control_mode"]
_TICK = RAM["tick"]
_CAL_POS = RAM["calibrated_position"]
_ABS_POS = RAM["absolute_position"]
_DIFF_POS = RAM["differential_position"]
_PWM = RAM["pwm"]
_GOAL = RAM["absolute_goal_position"]
_TRAJ_POS = RAM["absolute_desired_trajectory_position"]
_TRAJ_VEL = RAM["desired_velocity"]

#: Detail bits that report a packet fault and stay until cleared.
_LATCHED_DETAIL: Final = (
    StatusDetail.CHECKSUM_ERROR
    | StatusDetail.UNKNOWN_COMMAND
    | StatusDetail.EXCEED_REG_RANGE
    | StatusDetail.GARBAGE_DETECTED
)
_REJECT_DETAIL: Final = {
    RejectReason.CHECKSUM: StatusDetail.CHECKSUM_ERROR,
    RejectReason.UNKNOWN_COMMAND: StatusDetail.UNKNOWN_COMMAND,
    RejectReason.EXPIRED: StatusDetail.GARBAGE_DETECTED,
}
_POSITION_SPAN: Final = POSITION_MAX_RAW + 1
#: A trajectory counts as finished this close to its end (float time arithmetic).
_TIME_EPS_S: Final = 1e-9


class SimServo(SimDevice):
    """A simulated DRS-0101 or DRS-0201 on the bus.

    Args:
        sid: The id stored in EEP 6 (and so RAM 0); factory servos are 0xFD.
        model: The model reported in EEP 0.
        pos_raw: The absolute position the horn starts at.
        now_s: The virtual time of power-up.
    """

    def __init__(
        self,
        sid: int = 0xFD,
        *,
        model: Model = Model.DRS_0101,
        pos_raw: float = 512.0,
        now_s: float = 0.0,
    ) -> None:
        EEP["id"].check(sid)
        if not (math.isfinite(pos_raw) and 0 <= pos_raw <= POSITION_MAX_RAW):
            raise OutOfRangeError("pos_raw", pos_raw, 0, POSITION_MAX_RAW, "count")
        self._model = Model(model)
        self._max_speed_cps = NO_LOAD_SPEED_DPS[self._model] / DEG_PER_COUNT
        self._eep = self._factory_eep()
        self._eep[EEP["id"].addr] = sid
        self._ram = bytearray(RAM_SIZE)
        self._now_s = now_s
        self._boot_s = now_s
        self._motion: _Motion = _Trajectory.hold(now_s, float(pos_raw))
        self._goal_abs = float(pos_raw)
        self._mode = JogMode.POSITION
        self._mode_locked = False
        self._temp_raw = AMBIENT_TEMP_RAW
        self._load = 0.0
        self._supply_v = NOMINAL_SUPPLY_V
        self._boot()

    # -- test hooks ------------------------------------------------------------------

    @property
    def sid(self) -> int:
        """The id the servo answers to now (RAM 0)."""
        return self._ram[_ID.addr]

    @property
    def model(self) -> Model:
        """The simulated model."""
        return self._model

    def set_load(self, load_fraction: float) -> None:
        """Apply an external load, as a fraction of stall torque (-1..1).

        It acts from the time the servo was last advanced to. Holding it with torque on
        costs PWM (RAM 64) and heats the servo.

        Raises:
            InvalidArgumentError: ``load_fraction`` is NaN or infinite.
            OutOfRangeError: ``load_fraction`` is outside -1..1.
        """
        if not math.isfinite(load_fraction):
            raise InvalidArgumentError(f"load_fraction must be finite, got {load_fraction!r}")
        if not -1.0 <= load_fraction <= 1.0:
            raise OutOfRangeError("load_fraction", load_fraction, -1.0, 1.0)
        self._load = float(load_fraction)
        self._refresh()

    def set_supply_voltage(self, supply_v: float) -> None:
        """Change the supply voltage (from the time last advanced to); default 7.4 V.

        Raises:
            InvalidArgumentError: ``supply_v`` is NaN, infinite or negative.
        """
        if not math.isfinite(supply_v) or supply_v < 0:
            raise InvalidArgumentError(f"supply_v must be finite and >= 0, got {supply_v!r}")
        self._supply_v = float(supply_v)
        self._check_faults()
        self._refresh()

    # -- SimDevice -------------------------------------------------------------------

    def advance(self, now_s: float) -> None:
        """Run the physics up to ``now_s``, stopping at an over-temperature crossing."""
        if now_s < self._now_s:
            raise InvalidArgumentError(f"time went backwards: {now_s} < {self._now_s}")
        while True:
            crossing_s = self._overheat_time(now_s)
            if crossing_s is None:
                self._heat(now_s)
                break
            self._heat(crossing_s)
            # Land exactly on the limit so float noise cannot schedule the crossing again.
            self._temp_raw = float(self._get(_MAX_TEMP))
            self._check_faults()
        self._check_faults()
        self._refresh()

    def handle(self, packet: Packet, now_s: float) -> Packet | None:
        """Act on a request addressed to this servo (or broadcast) and return its reply."""
        self.advance(now_s)
        my_id = self.sid
        if packet.is_reply or packet.sid not in (my_id, BROADCAST_ID):
            return None
        try:
            cmd = Command(packet.cmd)
        except ValueError:
            self._flag(StatusDetail.UNKNOWN_COMMAND)
            return None
        answer = reply_expected(cmd, packet.sid, self._get(_ACK))
        reply_sid = my_id if packet.sid == BROADCAST_ID else packet.sid
        try:
            if cmd in (Command.REBOOT, Command.ROLLBACK):
                # The acknowledgement leaves before the restart wipes the status.
                reply = self._reply(reply_sid, cmd, b"") if answer else None
                self._restart(cmd, packet.data)
                return reply
            payload = self._execute(cmd, packet, my_id)
        except _Unanswerable as exc:
            self._flag(exc.detail)
            return None
        return self._reply(reply_sid, cmd, payload) if answer else None

    def on_rejected(self, reason: RejectReason, frame: bytes, now_s: float) -> None:
        """Flag a frame for this servo (or broadcast) that failed to decode."""
        self.advance(now_s)
        detail = _REJECT_DETAIL.get(reason)
        # BAD_SIZE / BAD_HEADER: the header itself is implausible, so is its id byte.
        if detail is not None and len(frame) > 3 and frame[3] in (self.sid, BROADCAST_ID):
            self._flag(detail)

    def power_cycle(self, now_s: float) -> None:
        """Power off and on: EEP to RAM, torque free, faults cleared (heat stays)."""
        self.advance(now_s)
        self._boot()

    # -- requests --------------------------------------------------------------------

    def _execute(self, cmd: Command, packet: Packet, my_id: int) -> bytes:
        """Carry out a request; return the reply's bytes before the status pair."""
        if cmd in (Command.RAM_READ, Command.EEP_READ):
            return self._read(RAM if cmd == Command.RAM_READ else EEP, packet.data)
        if cmd in (Command.RAM_WRITE, Command.EEP_WRITE):
            self._write(RAM if cmd == Command.RAM_WRITE else EEP, packet.data)
        elif cmd in (Command.I_JOG, Command.S_JOG):
            try:
                targets = decode_jog(packet)
            except ProtocolError:
                raise _Unanswerable(StatusDetail.GARBAGE_DETECTED) from None
            for target in targets:
                if target.sid == my_id:
                    self._jog(target)
        # STAT has nothing to do but answer.
        return b""

    def _read(self, table: RegisterMap, data: bytes) -> bytes:
        if len(data) != 2:
            raise _Unanswerable(StatusDetail.GARBAGE_DETECTED)
        addr, length = data
        if addr + length > table.size:
            raise _Unanswerable(StatusDetail.EXCEED_REG_RANGE)
        memory = self._ram if table is RAM else self._eep
        return bytes((addr, length)) + bytes(memory[addr : addr + length])

    def _write(self, table: RegisterMap, data: bytes) -> None:
        if len(data) < 3 or data[1] != len(data) - 2:
            raise _Unanswerable(StatusDetail.GARBAGE_DETECTED)
        addr, payload = data[0], data[2:]
        if not table.writable(addr, len(payload)):
            # Answered (under policy 2) so the sender sees why nothing changed.
            self._flag(StatusDetail.EXCEED_REG_RANGE)
            return
        if table is EEP:
            # EEP acts after REBOOT; the RAM copy stays as it is.
            self._eep[addr : addr + len(payload)] = payload
            return
        for offset, byte in enumerate(payload):
            if addr + offset == _TORQUE.addr:
                self._set_torque(byte)
            else:
                self._ram[addr + offset] = byte
        # A cleared fault whose cause persists comes straight back.
        self._check_faults()
        self._refresh()

    def _jog(self, target: JogTarget) -> None:
        if self._get(_TORQUE) != TorqueControl.ON:
            return
        if target.mode != self._mode and self._mode_locked:
            return
        self._mode = target.mode
        self._mode_locked = True
        self._put(_LED, int(target.led))
        now = self._now_s
        pos, _ = self._motion.at(now)
        if target.mode == JogMode.TURN:
            pwm = max(-self._get(_MAX_PWM), min(self._get(_MAX_PWM), target.value))
            speed = 0.0 if target.stop else pwm / 1023 * self._max_speed_cps
            self._motion = _Spin(now, pos, speed)
            self._goal_abs = pos
        elif target.stop:
            self._motion = _Trajectory.hold(now, pos)
            self._goal_abs = pos
        else:
            goal_cal = max(self._get(_MIN_POS), min(self._get(_MAX_POS), target.value))
            goal = float(_clip(goal_cal + self._get(_CAL_DIFF), 0, POSITION_MAX_RAW))
            self._motion = self._plan(now, pos, goal, target.playtime_ticks * TICK_S)
            self._goal_abs = goal
        self._refresh()

    def _plan(self, now: float, start: float, goal: float, playtime_s: float) -> _Trajectory:
        distance = abs(goal - start)
        if distance == 0:
            return _Trajectory.hold(now, goal)
        ratio = min(self._get(_ACCEL_RATIO), 50) / 100
        # The peak speed of the profile is distance / (T (1 - ratio)); the motor cannot
        # exceed its no-load speed, so a too-short playtime is stretched.
        duration = max(playtime_s, distance / (self._max_speed_cps * (1 - ratio)))
        accel = min(ratio * duration, self._get(_MAX_ACCEL_TIME) * TICK_S)
        return _Trajectory(now, start, goal, duration, accel)

    def _restart(self, cmd: Command, data: bytes) -> None:
        if cmd == Command.ROLLBACK:
            if len(data) != 2:
                raise _Unanswerable(StatusDetail.GARBAGE_DETECTED)
            keep_id, keep_baud = data
            factory = self._factory_eep()
            for reg, keep in ((EEP["id"], keep_id), (EEP["baud_rate"], keep_baud)):
                if keep:
                    factory[reg.addr : reg.end] = self._eep[reg.addr : reg.end]
            self._eep = factory
        self._boot()

    # -- state -----------------------------------------------------------------------

    def _factory_eep(self) -> bytearray:
        eep = bytearray(EEP_SIZE)
        for reg in EEP:
            if reg.default is not None:
                eep[reg.addr : reg.end] = reg.default.to_bytes(
                    reg.size, "little", signed=reg.signed
                )
        eep[EEP["model_no1"].addr] = self._model
        fw = EEP["firmware_version"]
        eep[fw.addr : fw.end] = SIM_FIRMWARE_VERSION.to_bytes(fw.size, "little")
        return eep

    def _boot(self) -> None:
        """Power-up / REBOOT: EEP settings to RAM, RAM-only registers to defaults."""
        self._ram[:] = bytes(RAM_SIZE)
        self._ram[: EEP_SIZE - EEP_TO_RAM_OFFSET] = self._eep[EEP_TO_RAM_OFFSET:]
        for reg in RAM:
            if reg.addr >= EEP_SIZE - EEP_TO_RAM_OFFSET and reg.default is not None:
                self._put(reg, reg.default)
        pos, _ = self._motion.at(self._now_s)
        self._motion = _Trajectory.hold(self._now_s, pos)
        self._goal_abs = pos
        self._mode = JogMode.POSITION
        self._mode_locked = False
        self._boot_s = self._now_s
        self._check_faults()
        self._refresh()

    def _set_torque(self, value: int) -> None:
        if value != TorqueControl.FREE and self._get(_ERROR) & self._get(_TORQUE_POLICY):
            # Released by the torque policy: stays free until RAM 48 is cleared.
            return
        was_on = self._get(_TORQUE) == TorqueControl.ON
        self._ram[_TORQUE.addr] = value
        if was_on == (value == TorqueControl.ON):
            return
        pos, _ = self._motion.at(self._now_s)
        # Whether torque goes on or off, the horn stays where it is.
        self._motion = _Trajectory.hold(self._now_s, pos)
        self._goal_abs = pos
        if value != TorqueControl.ON:
            self._mode_locked = False

    def _flag(self, detail: StatusDetail) -> None:
        """Latch a packet fault: the detail bit plus INVALID_PACKET."""
        self._put(_DETAIL, self._get(_DETAIL) | detail)
        self._put(_ERROR, self._get(_ERROR) | StatusError.INVALID_PACKET)
        self._check_faults()
        self._refresh()

    def _check_faults(self) -> None:
        """Set the error bits whose cause holds now; release torque per the policy."""
        error = self._get(_ERROR)
        if self._temp_raw >= self._get(_MAX_TEMP):
            error |= StatusError.TEMPERATURE
        if not self._get(_MIN_VOLT) <= self._voltage_raw() <= self._get(_MAX_VOLT):
            error |= StatusError.INPUT_VOLTAGE
        self._put(_ERROR, error)
        if error & self._get(_TORQUE_POLICY):
            self._set_torque(TorqueControl.FREE)

    def _refresh(self) -> None:
        """Write the feedback registers and the live status bits for ``_now_s``."""
        now = self._now_s
        pos, speed_cps = self._motion.at(now)
        torque_on = self._get(_TORQUE) == TorqueControl.ON
        abs_pos = _clip(round(pos), 0, POSITION_MAX_RAW)
        diff = _clip(round(speed_cps * DEG_PER_COUNT / DEG_S_PER_DIFF), -32768, 32767)
        max_pwm = self._get(_MAX_PWM)
        pwm = (
            _clip(round(1023 * (self._load + speed_cps / self._max_speed_cps)), -max_pwm, max_pwm)
            if torque_on
            else 0
        )
        self._put(_VOLTAGE, _clip(self._voltage_raw(), 0, 0xFF))
        self._put(_TEMPERATURE, _clip(math.floor(self._temp_raw), 0, 0xFF))
        self._put(_MODE, self._mode)
        self._put(_TICK, int((now - self._boot_s) / TICK_S + _TIME_EPS_S) & 0xFF)
        self._put(_ABS_POS, abs_pos)
        self._put(_CAL_POS, _clip(abs_pos - self._get(_CAL_DIFF), 0, POSITION_MAX_RAW))
        self._put(_DIFF_POS, diff)
        self._put(_PWM, pwm)
        self._put(_GOAL, _clip(round(self._goal_abs), 0, POSITION_MAX_RAW))
        self._put(_TRAJ_POS, abs_pos)
        self._put(_TRAJ_VEL, diff)
        live = StatusDetail.NONE
        if torque_on:
            live |= StatusDetail.MOTOR_ON
            if self._motion.moving(now):
                live |= StatusDetail.MOVING
            # Near the end of a move both bits are set: in position means within the
            # margin of the goal, not stopped.
            if self._mode == JogMode.POSITION and abs(pos - self._goal_abs) <= self._get(_MARGIN):
                live |= StatusDetail.INPOSITION
        self._put(_DETAIL, (self._get(_DETAIL) & _LATCHED_DETAIL) | live)

    def _reply(self, sid: int, cmd: Command, payload: bytes) -> Packet:
        status = bytes((self._get(_ERROR), self._get(_DETAIL)))
        return Packet(sid, cmd | REPLY_FLAG, payload + status)

    # -- thermal ---------------------------------------------------------------------

    def _temp_target_raw(self) -> float:
        if self._get(_TORQUE) == TorqueControl.ON:
            return AMBIENT_TEMP_RAW + TEMP_RISE_FULL_LOAD_RAW * self._load**2
        return AMBIENT_TEMP_RAW

    def _heat(self, until_s: float) -> None:
        """Relax the temperature towards its target from ``_now_s`` to ``until_s``."""
        target = self._temp_target_raw()
        decay = math.exp(-(until_s - self._now_s) / THERMAL_TIME_CONSTANT_S)
        self._temp_raw = target + (self._temp_raw - target) * decay
        self._now_s = until_s

    def _overheat_time(self, until_s: float) -> float | None:
        """When the temperature reaches the limit before ``until_s``, if it does."""
        limit = self._get(_MAX_TEMP)
        target = self._temp_target_raw()
        if not self._temp_raw < limit <= target or target == limit:
            return None
        dt = THERMAL_TIME_CONSTANT_S * math.log((target - self._temp_raw) / (target - limit))
        crossing = self._now_s + dt
        return crossing if crossing <= until_s else None

    # -- registers -------------------------------------------------------------------

    def _voltage_raw(self) -> int:
        return round(self._supply_v / VOLT_PER_COUNT)

    def _get(self, reg: Register) -> int:
        return reg.decode(self._ram[reg.addr : reg.end])

    def _put(self, reg: Register, value: int) -> None:
        self._ram[reg.addr : reg.end] = int(value).to_bytes(reg.size, "little", signed=reg.signed)


# -- motion ---------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class _Trajectory:
    """A trapezoidal move from ``start`` to ``goal`` (absolute counts) over ``duration_s``.

    Accelerate for ``accel_s``, cruise, decelerate for ``accel_s``; the area under the
    velocity curve is the distance, so the peak speed is distance / (duration - accel).
    """

    t0_s: float
    start: float
    goal: float
    duration_s: float
    accel_s: float

    @classmethod
    def hold(cls, now_s: float, pos: float) -> _Trajectory:
        """Stay at ``pos``."""
        return cls(now_s, pos, pos, 0.0, 0.0)

    def at(self, now_s: float) -> tuple[float, float]:
        """Position (counts) and speed (counts/s) at ``now_s``."""
        t = now_s - self.t0_s
        if t >= self.duration_s:
            return self.goal, 0.0
        peak = (self.goal - self.start) / (self.duration_s - self.accel_s)
        if t < self.accel_s:
            return self.start + 0.5 * peak / self.accel_s * t * t, peak * t / self.accel_s
        left = self.duration_s - t
        if left < self.accel_s:
            return self.goal - 0.5 * peak / self.accel_s * left * left, peak * left / self.accel_s
        return self.start + peak * (t - 0.5 * self.accel_s), peak

    def moving(self, now_s: float) -> bool:
        """Whether the move is still under way."""
        return now_s - self.t0_s < self.duration_s - _TIME_EPS_S


@dataclass(frozen=True, slots=True)
class _Spin:
    """Continuous rotation at a constant speed; the pot reading wraps every 1024 counts."""

    t0_s: float
    start: float
    speed_cps: float

    def at(self, now_s: float) -> tuple[float, float]:
        """Position (counts, wrapped) and speed (counts/s) at ``now_s``."""
        return (self.start + self.speed_cps * (now_s - self.t0_s)) % _POSITION_SPAN, self.speed_cps

    def moving(self, now_s: float) -> bool:
        """Whether the horn turns."""
        del now_s
        return self.speed_cps != 0


_Motion = _Trajectory | _Spin


class _Unanswerable(Exception):  # noqa: N818 - internal control flow, not an error for users
    """The servo cannot interpret the request: flag ``detail`` and stay silent."""

    def __init__(self, detail: StatusDetail) -> None:
        super().__init__(detail)
        self.detail = detail


def _clip(value: int, low: int, high: int) -> int:
    return max(low, min(high, value))
