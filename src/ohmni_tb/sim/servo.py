"""Virtual HerkuleX DRS-0101 / DRS-0201 firmware.

:class:`SimServo` answers the same bytes as the real servo: it keeps a full EEP (54 bytes)
and RAM (74 bytes) file, copies EEP 6..53 to RAM 0..47 at construction, REBOOT and power
cycle, obeys its id (RAM 0) and ACK policy (RAM 1) through
:func:`~ohmni_tb.protocol.reply_expected`, and replies ``addr, len, bytes, status_error,
status_detail`` to reads and the two status bytes to everything else it answers. Time is
injected (``now_s``); nothing here reads a clock, so a test runs minutes of servo time in
microseconds. Everything a test observes is read out of the registers (and, for the LEDs
a person would see, :attr:`SimServo.leds`).

Physics (simple, closed-form in time, so the result does not depend on how often the
servo is advanced; the feedback registers are computed when a read or a reply needs
them):

* **Torque** (RAM 52): free (0x00) and brake (0x40) hold the position where it is (no
  gravity); on (0x60) follows JOGs. Turning torque on holds the current position.
* **Control mode** (RAM 56), as the manual describes it: with torque free, a JOG only
  selects the mode it names (nothing moves); turning torque on then runs that mode, so
  torque free → turn JOG → torque on leaves the servo in turn mode, at rest until the
  next turn JOG. With torque on, a position JOG always acts (from turn mode it stops the
  spin and moves to the goal); a turn JOG in position mode acts only while no position
  JOG has run since torque last went on — changing to turn mode needs torque off first.
  In brake, JOGs are ignored.
* **Position JOG**: the goal (calibrated coordinate) is clamped to RAM 20..22 and offset
  by the calibration difference (RAM 47) to the absolute coordinate; a goal outside RAM
  20..22 also sets StatusError.POSITION_LIMIT (latched until RAM 48 is cleared). The
  servo follows a trapezoidal velocity profile from where it is: it accelerates for
  ``ratio`` (RAM 8, %) of the playtime but no longer than the max acceleration time
  (RAM 9), cruises, and decelerates symmetrically, arriving exactly at the end of the
  playtime. Tracking is ideal, except that the move is stretched when it would need more
  than the model's no-load speed scaled by the max PWM (RAM 16: 1023 = full speed, 0 =
  it does not move), playtime 0 = as fast as it can.
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
* **Writes**: a write is checked against the register table (its read-only rows and
  every register's low..high and allowed values); a write that breaks either changes
  nothing and sets EXCEED_REG_RANGE with INVALID_PACKET. It is still acknowledged (under
  policy 2) so the sender sees why.
* **Temperature**: a first-order model in raw ADC units (the real sensor curve is not
  public): it relaxes towards ``ambient + 100 × load²`` while torque is on and towards
  ambient otherwise, with a 120 s time constant; :meth:`SimServo.set_load` sets the
  external load as a fraction of stall torque. At raw ≥ max temperature (RAM 5) the
  servo sets StatusError.TEMPERATURE; the error latches in RAM 48 until a write of zeros
  clears it, and it comes straight back while the temperature is still at the limit.
  Supply voltage outside RAM 6..7 sets INPUT_VOLTAGE the same way.
* **Torque policy** (RAM 3): while RAM 48 has a bit of the mask, torque is released and
  a write of brake/on to RAM 52 is ignored; clear RAM 48/49, then turn torque on again.
* **Alarm LED policy** (RAM 2): while RAM 48 has a bit of the mask, the red LED blinks
  with the LED blink period (RAM 38) and writes to RAM 53 — and a JOG's LED bits — are
  ignored; RAM 53 keeps the last value it took.
* **Restart**: REBOOT and ROLLBACK send their acknowledgement, reload the registers,
  and then the servo is deaf for :data:`RESTART_S` (0.25 s): it neither decodes nor
  answers anything, even a request in the same write as the REBOOT.
* **Garbage check**: an incomplete packet is dropped after the packet garbage check
  period (RAM 40, factory 0x12 ticks = :data:`GARBAGE_TIMEOUT_S`). The simulated line
  owns the decoder and expires the frame; the servo it names then sets
  GARBAGE_DETECTED with INVALID_PACKET.

Choices where the manual is silent:

* A JOG sent with torque free changes only the control mode: its value, stop flag and
  LED bits are dropped, and torque on starts at rest. Brake does not count as "torque
  off" for a mode change.
* A position JOG with torque on is obeyed in either mode (the manual asks for torque off
  only to change to turn mode); a turn JOG under torque on is refused only once a
  position JOG has run since torque went on.
* A goal outside RAM 20..22 is still clamped and run; POSITION_LIMIT is set when such a
  JOG arrives (not when the horn is outside the limits) and stays until RAM 48 is
  cleared. If the torque policy includes it, torque is released first and the JOG is
  dropped.
* A write that breaks a range is refused whole, not byte by byte; a write of one byte of
  a two-byte register is checked with the other byte as it is in memory. EEP writes are
  checked against the EEP rows the same way.
* Inside one write, each byte is applied in address order, so a write that clears RAM 48
  and sets torque or the LED further on is obeyed if the fault's cause has gone.
* The alarm LED blinks red alone, lit for the first half of each blink period counted
  from boot (period 0: steady red); the user's LED register is not shown meanwhile.
* The restart figure: the manual gives none. The time runs from the REBOOT's arrival;
  the tick (RAM 57) counts from the end of it. A power cycle restarts at once (the
  robot's own power-up is not modelled) and ends a restart under way.
* Garbage is flagged only by the servo whose id (or broadcast) the half packet already
  carries; a frame cut before its id byte concerns nobody.

Not modelled: overload and driver-fault detection, EEP distortion, PID gains, dead zone,
saturator, load-dependent tracking error, and the baud rate (EEP 4 is stored; line speed
is the simulated line's business). A request the servo cannot interpret (malformed
layout, unknown command, a read outside the map) gets no reply.
"""

from __future__ import annotations

import itertools
import math
import struct
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
    Led,
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
    "GARBAGE_TIMEOUT_S",
    "NO_LOAD_SPEED_DPS",
    "RESTART_S",
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
#: How long REBOOT and ROLLBACK leave the servo deaf. The DRS-0101/0201 manual gives no
#: figure. The drs-0x01 driver documents a 250 ms delay "to let the servo reboot", the only
#: public statement of what the servo itself needs; other drivers wait longer (500 ms in
#: the Arduino library's examples, 1-2 s elsewhere), which is margin on top of it.
RESTART_S: Final = 0.25
#: The packet garbage check period at its factory value: the manual's register map gives
#: RAM 40 (EEP 46) a default of 0x12 ticks of 11.2 ms, "201 ms", after which an incomplete
#: packet is discarded. A servo whose RAM 40 was changed uses its own value.
GARBAGE_TIMEOUT_S: Final = 0x12 * TICK_S

_ID = RAM["id"]
_ACK = RAM["ack_policy"]
_ALARM_LED_POLICY = RAM["alarm_led_policy"]
_TORQUE_POLICY = RAM["torque_policy"]
_MAX_TEMP = RAM["max_temperature"]
_MIN_VOLT = RAM["min_voltage"]
_MAX_VOLT = RAM["max_voltage"]
_ACCEL_RATIO = RAM["acceleration_ratio"]
_MAX_ACCEL_TIME = RAM["max_acceleration_time"]
_MAX_PWM = RAM["max_pwm"]
_MIN_POS = RAM["min_position"]
_MAX_POS = RAM["max_position"]
_BLINK = RAM["led_blink_period"]
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
_LATCHED_DETAIL: Final = int(
    StatusDetail.CHECKSUM_ERROR
    | StatusDetail.UNKNOWN_COMMAND
    | StatusDetail.EXCEED_REG_RANGE
    | StatusDetail.GARBAGE_DETECTED
)
_MOTOR_ON: Final = int(StatusDetail.MOTOR_ON)
_MOVING: Final = int(StatusDetail.MOVING)
_INPOSITION: Final = int(StatusDetail.INPOSITION)

_REJECT_DETAIL: Final = {
    RejectReason.CHECKSUM: StatusDetail.CHECKSUM_ERROR,
    RejectReason.UNKNOWN_COMMAND: StatusDetail.UNKNOWN_COMMAND,
    RejectReason.EXPIRED: StatusDetail.GARBAGE_DETECTED,
}
_POSITION_SPAN: Final = POSITION_MAX_RAW + 1
#: A trajectory counts as finished this close to its end (float time arithmetic).
_TIME_EPS_S: Final = 1e-9
_JOGS: Final = frozenset({Command.I_JOG, Command.S_JOG})


def _packer(*regs: Register) -> struct.Struct:
    """One struct for adjacent registers, so a refresh writes them in one call."""
    for before, after in itertools.pairwise(regs):
        if after.addr != before.end:
            raise AssertionError(f"{after.name} does not follow {before.name}")
    codes = {(1, False): "B", (1, True): "b", (2, False): "H", (2, True): "h"}
    return struct.Struct("<" + "".join(codes[reg.size, reg.signed] for reg in regs))


#: RAM 54..65 and 68..73; the reserved RAM 66..67 between them is left alone.
_FEEDBACK_LOW: Final = _packer(
    _VOLTAGE, _TEMPERATURE, _MODE, _TICK, _CAL_POS, _ABS_POS, _DIFF_POS, _PWM
)
_FEEDBACK_HIGH: Final = _packer(_GOAL, _TRAJ_POS, _TRAJ_VEL)


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
        self._restart_until_s = now_s
        self._motion: _Motion = _Trajectory.hold(now_s, float(pos_raw))
        self._goal_abs = float(pos_raw)
        self._mode = JogMode.POSITION
        self._turn_locked = False
        self._load = 0.0
        self._supply_v = NOMINAL_SUPPLY_V
        # The temperature is closed-form between anchors: it relaxes from _temp0_raw at
        # _temp_t0_s towards _temp_target_raw; the anchor moves whenever the target does.
        self._temp_t0_s = now_s
        self._temp0_raw = AMBIENT_TEMP_RAW
        self._temp_target_raw = AMBIENT_TEMP_RAW
        self._overheat_at_s = math.inf
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

    @property
    def leds(self) -> Led:
        """The LEDs lit at the time last advanced to, as a person would see them.

        RAM 53 normally; the blinking red alarm LED while RAM 48 has a bit of the alarm LED
        policy (RAM 2).
        """
        if not self._alarm_on():
            return Led(self._ram[_LED.addr] & 0x07)
        period_s = self._ram[_BLINK.addr] * TICK_S
        if period_s == 0:
            return Led.RED
        phase_s = (self._now_s - self._boot_s) % period_s
        return Led.RED if phase_s < period_s / 2 else Led.NONE

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
        self._reanchor_heat()

    def set_supply_voltage(self, supply_v: float) -> None:
        """Change the supply voltage (from the time last advanced to); default 7.4 V.

        Raises:
            InvalidArgumentError: ``supply_v`` is NaN, infinite or negative.
        """
        if not math.isfinite(supply_v) or supply_v < 0:
            raise InvalidArgumentError(f"supply_v must be finite and >= 0, got {supply_v!r}")
        self._supply_v = float(supply_v)
        self._check_faults()

    # -- SimDevice -------------------------------------------------------------------

    def advance(self, now_s: float) -> None:
        """Run the physics up to ``now_s``, stopping at an over-temperature crossing."""
        if now_s == self._now_s:
            return
        if now_s < self._now_s:
            raise InvalidArgumentError(f"time went backwards: {now_s} < {self._now_s}")
        # Everything else is closed-form in time; only the crossing is an event.
        while self._overheat_at_s <= now_s:
            self._now_s = self._overheat_at_s
            # Land exactly on the limit so float noise cannot schedule the crossing again.
            self._temp_t0_s = self._now_s
            self._temp0_raw = float(self._ram[_MAX_TEMP.addr])
            self._overheat_at_s = math.inf
            self._check_faults()
            self._reanchor_heat()
        self._now_s = now_s

    def handle(self, packet: Packet, now_s: float) -> Packet | None:
        """Act on a request addressed to this servo (or broadcast) and return its reply."""
        sid = packet.sid
        my_id = self._ram[_ID.addr]
        # A packet to another id is ignored whole, jog tags naming this servo included:
        # multi-servo jogs go to broadcast.
        if sid not in (my_id, BROADCAST_ID):
            return None
        self.advance(now_s)
        if packet.cmd & REPLY_FLAG or now_s < self._restart_until_s:
            return None
        try:
            cmd = Command(packet.cmd)
        except ValueError:
            self._flag(StatusDetail.UNKNOWN_COMMAND)
            return None
        answer = reply_expected(cmd, sid, self._ram[_ACK.addr])
        reply_sid = my_id if sid == BROADCAST_ID else sid
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
        """Flag a frame for this servo (or broadcast) that failed to decode.

        EXPIRED (a half packet dropped by the garbage check) sets GARBAGE_DETECTED.
        """
        detail = _REJECT_DETAIL.get(reason)
        # BAD_SIZE / BAD_HEADER: the header itself is implausible, so is its id byte.
        if detail is None or len(frame) <= 3 or frame[3] not in (self.sid, BROADCAST_ID):
            return
        self.advance(now_s)
        if now_s >= self._restart_until_s:
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
        elif cmd in _JOGS:
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
        if table is RAM:
            self._refresh()
            memory = self._ram
        else:
            memory = self._eep
        return bytes((addr, length)) + bytes(memory[addr : addr + length])

    def _write(self, table: RegisterMap, data: bytes) -> None:
        if len(data) < 3 or data[1] != len(data) - 2:
            raise _Unanswerable(StatusDetail.GARBAGE_DETECTED)
        addr, payload = data[0], data[2:]
        memory = self._ram if table is RAM else self._eep
        if not table.writable(addr, len(payload)) or not _in_range(table, memory, addr, payload):
            # Answered (under policy 2) so the sender sees why nothing changed.
            self._flag(StatusDetail.EXCEED_REG_RANGE)
            return
        if table is EEP:
            # EEP acts after REBOOT; the RAM copy stays as it is.
            self._eep[addr : addr + len(payload)] = payload
            return
        for offset, byte in enumerate(payload):
            at = addr + offset
            if at == _TORQUE.addr:
                self._set_torque(byte)
            elif at == _LED.addr:
                self._set_led(byte)
            else:
                self._ram[at] = byte
        # A cleared fault whose cause persists comes straight back; a new limit or
        # policy acts at once.
        self._check_faults()
        self._reanchor_heat()

    def _jog(self, target: JogTarget) -> None:
        torque = self._ram[_TORQUE.addr]
        if torque == TorqueControl.FREE:
            # The manual's mode change: torque off, a JOG of the new mode, torque on.
            self._mode = target.mode
            return
        if torque != TorqueControl.ON:
            return
        if target.mode == JogMode.TURN and self._mode == JogMode.POSITION and self._turn_locked:
            return
        now = self._now_s
        pos, _ = self._motion.at(now)
        if target.mode == JogMode.POSITION and not target.stop:
            low, high = self._get(_MIN_POS), self._get(_MAX_POS)
            if not low <= target.value <= high:
                self._put(_ERROR, self._get(_ERROR) | StatusError.POSITION_LIMIT)
                self._check_faults()
                if self._ram[_TORQUE.addr] != TorqueControl.ON:
                    return  # released by the torque policy
        self._mode = target.mode
        if target.mode == JogMode.POSITION:
            self._turn_locked = True
        self._set_led(int(target.led))
        if target.mode == JogMode.TURN:
            max_pwm = self._get(_MAX_PWM)
            pwm = max(-max_pwm, min(max_pwm, target.value))
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

    def _plan(self, now: float, start: float, goal: float, playtime_s: float) -> _Trajectory:
        distance = abs(goal - start)
        if distance == 0:
            return _Trajectory.hold(now, goal)
        ratio = min(self._get(_ACCEL_RATIO), 50) / 100
        # The max PWM (RAM 16) caps the motor's drive, and with it its top speed.
        top_cps = self._max_speed_cps * min(self._get(_MAX_PWM), 1023) / 1023
        if top_cps <= 0:
            return _Trajectory.hold(now, start)  # no drive at all: it stays
        # The peak speed of the profile is distance / (T (1 - ratio)); the motor cannot
        # exceed its top speed, so a too-short playtime is stretched.
        duration = max(playtime_s, distance / (top_cps * (1 - ratio)))
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
        self._restart_until_s = self._now_s + RESTART_S
        self._boot_s = self._restart_until_s

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
        self._turn_locked = False
        self._boot_s = self._now_s
        self._restart_until_s = self._now_s
        self._check_faults()
        self._reanchor_heat()

    def _set_torque(self, value: int) -> None:
        if value != TorqueControl.FREE and self._get(_ERROR) & self._get(_TORQUE_POLICY):
            # Released by the torque policy: stays free until RAM 48 is cleared.
            return
        was_on = self._ram[_TORQUE.addr] == TorqueControl.ON
        self._ram[_TORQUE.addr] = value
        if was_on == (value == TorqueControl.ON):
            return
        pos, _ = self._motion.at(self._now_s)
        # Whether torque goes on or off, the horn stays where it is (in turn mode too:
        # torque on starts the spin at rest).
        self._motion = _Trajectory.hold(self._now_s, pos)
        self._goal_abs = pos
        if value != TorqueControl.ON:
            self._turn_locked = False
        self._reanchor_heat()

    def _set_led(self, value: int) -> None:
        # The alarm LED owns the LEDs while it is on; the manual has writes ignored then.
        if not self._alarm_on():
            self._ram[_LED.addr] = value

    def _alarm_on(self) -> bool:
        return bool(self._ram[_ERROR.addr] & self._ram[_ALARM_LED_POLICY.addr])

    def _flag(self, detail: StatusDetail) -> None:
        """Latch a packet fault: the detail bit plus INVALID_PACKET."""
        self._ram[_DETAIL.addr] |= detail
        self._ram[_ERROR.addr] |= StatusError.INVALID_PACKET
        self._check_faults()

    def _check_faults(self) -> None:
        """Set the error bits whose cause holds now; release torque per the policy."""
        error = self._get(_ERROR)
        if self._temp_raw() >= self._get(_MAX_TEMP):
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
        torque_on = self._ram[_TORQUE.addr] == TorqueControl.ON
        abs_pos = max(0, min(POSITION_MAX_RAW, round(pos)))
        diff = max(-32768, min(32767, round(speed_cps * DEG_PER_COUNT / DEG_S_PER_DIFF)))
        pwm = 0
        if torque_on:
            max_pwm = self._get(_MAX_PWM)
            pwm = round(1023 * (self._load + speed_cps / self._max_speed_cps))
            pwm = max(-max_pwm, min(max_pwm, pwm))
        cal_pos = max(0, min(POSITION_MAX_RAW, abs_pos - self._get(_CAL_DIFF)))
        _FEEDBACK_LOW.pack_into(
            self._ram,
            _VOLTAGE.addr,
            max(0, min(0xFF, self._voltage_raw())),
            max(0, min(0xFF, math.floor(self._temp_raw()))),
            self._mode,
            int((now - self._boot_s) / TICK_S + _TIME_EPS_S) & 0xFF,
            cal_pos,
            abs_pos,
            diff,
            pwm,
        )
        # RAM 66..67 are reserved (and writable): they keep what was written there.
        goal = max(0, min(POSITION_MAX_RAW, round(self._goal_abs)))
        _FEEDBACK_HIGH.pack_into(self._ram, _GOAL.addr, goal, abs_pos, diff)
        self._refresh_detail(pos, torque_on)

    def _refresh_detail(self, pos: float, torque_on: bool) -> None:
        """Recompute the live bits of RAM 49 (the latched ones stay)."""
        live = 0
        if torque_on:
            live = _MOTOR_ON
            if self._motion.moving(self._now_s):
                live |= _MOVING
            # Near the end of a move both bits are set: in position means within the
            # margin of the goal, not stopped.
            if (
                self._mode == JogMode.POSITION
                and abs(pos - self._goal_abs) <= self._ram[_MARGIN.addr]
            ):
                live |= _INPOSITION
        self._ram[_DETAIL.addr] = (self._ram[_DETAIL.addr] & _LATCHED_DETAIL) | live

    def _reply(self, sid: int, cmd: Command, payload: bytes) -> Packet:
        if cmd != Command.RAM_READ:
            # A RAM read refreshed everything; otherwise only the status pair goes out,
            # and the other feedback can wait for a read.
            pos, _ = self._motion.at(self._now_s)
            self._refresh_detail(pos, self._ram[_TORQUE.addr] == TorqueControl.ON)
        status = bytes((self._ram[_ERROR.addr], self._ram[_DETAIL.addr]))
        return Packet(sid, cmd | REPLY_FLAG, payload + status)

    # -- thermal ---------------------------------------------------------------------

    def _temp_raw(self) -> float:
        """The temperature at ``_now_s``, from the last anchor (closed form)."""
        if self._now_s == self._temp_t0_s or self._temp0_raw == self._temp_target_raw:
            return self._temp0_raw
        decay = math.exp(-(self._now_s - self._temp_t0_s) / THERMAL_TIME_CONSTANT_S)
        return self._temp_target_raw + (self._temp0_raw - self._temp_target_raw) * decay

    def _reanchor_heat(self) -> None:
        """Start a new closed-form segment at ``_now_s`` and schedule its overheat."""
        self._temp0_raw = self._temp_raw()
        self._temp_t0_s = self._now_s
        if self._ram[_TORQUE.addr] == TorqueControl.ON:
            target = AMBIENT_TEMP_RAW + TEMP_RISE_FULL_LOAD_RAW * self._load**2
        else:
            target = AMBIENT_TEMP_RAW
        self._temp_target_raw = target
        limit = self._ram[_MAX_TEMP.addr]
        if self._temp0_raw < limit < target:
            dt = THERMAL_TIME_CONSTANT_S * math.log((target - self._temp0_raw) / (target - limit))
            self._overheat_at_s = self._now_s + dt
        else:
            self._overheat_at_s = math.inf

    # -- registers -------------------------------------------------------------------

    def _voltage_raw(self) -> int:
        return round(self._supply_v / VOLT_PER_COUNT)

    def _get(self, reg: Register) -> int:
        return int.from_bytes(self._ram[reg.addr : reg.end], "little", signed=reg.signed)

    def _put(self, reg: Register, value: int) -> None:
        self._ram[reg.addr : reg.end] = int(value).to_bytes(reg.size, "little", signed=reg.signed)


def _in_range(table: RegisterMap, memory: bytearray, addr: int, payload: bytes) -> bool:
    """Whether every register the write touches would hold a value its row allows."""
    after = bytearray(memory)
    after[addr : addr + len(payload)] = payload
    end = addr + len(payload)
    for reg in table:
        if reg.addr < end and addr < reg.end:
            value = int.from_bytes(after[reg.addr : reg.end], "little", signed=reg.signed)
            if not reg.low <= value <= reg.high:
                return False
            if reg.choices is not None and value not in reg.choices:
                return False
    return True


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
