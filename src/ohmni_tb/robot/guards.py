"""The HerkuleX guards: a hot servo is freed (the neck rested first), and a neck left
holding torque for ``neck_hold_s`` since its last command is rested.

Both act on each servo sample (:meth:`Guards.check`), in a background task of their own,
so a slow move never holds up the stream that saw the heat.
"""

from __future__ import annotations

import contextlib
import logging

from ohmni_tb.errors import OhmniError
from ohmni_tb.herkulex import TorqueControl
from ohmni_tb.protocol.messages import StatusError
from ohmni_tb.robot.samples import ServoSample
from ohmni_tb.robot.servo_settings import NeckSettings
from ohmni_tb.robot.state import RobotState, ServoWatch

__all__ = ["THERMAL_HYSTERESIS_RAW", "Guards", "sample_ok"]

_log = logging.getLogger(__name__)

#: The status error bits the thermal guard acts on.
_HOT_BITS = int(StatusError.TEMPERATURE | StatusError.OVERLOAD)
#: A thermal fault clears this many raw degrees below the limit.
THERMAL_HYSTERESIS_RAW = 10


class Guards:
    """The thermal and hold guards over every HerkuleX servo of the Robot."""

    def __init__(self, state: RobotState, settings: NeckSettings | None = None) -> None:
        self._state = state
        self._settings = settings

    def check(self, watch: ServoWatch, sample: ServoSample) -> None:
        """Act on a new sample of ``watch``'s servo."""
        state = self._state
        if self._settings is not None and watch.stream == "servo_neck":
            # Back after a silence (a reboot?): the servo's settings are checked.
            self._settings.check(sample)
        config = state.config
        if not config.thermal_guard:
            return
        # On the flags' int value: an IntFlag's own & makes a new flag each time.
        hot_bits = int(sample.status_error) & _HOT_BITS
        hot = bool(hot_bits) or sample.temperature_raw >= config.thermal_limit_raw
        if hot and not watch.tripped:
            watch.tripped = True
            state.faults.add(f"thermal:{sample.sid}")
            rest = watch.stream == "servo_neck"
            state.publish(
                f"thermal guard: servo {sample.sid} at temperature {sample.temperature_raw} "
                f"(limit {config.thermal_limit_raw}), errors {sample.status_error!r}: "
                + ("resting, then freeing it" if rest else "freeing it")
            )
            self._guard(watch, rest=rest)
            return
        cool = (
            not hot_bits
            and sample.temperature_raw < config.thermal_limit_raw - THERMAL_HYSTERESIS_RAW
        )
        if watch.tripped and cool:
            watch.tripped = False
            state.faults.discard(f"thermal:{sample.sid}")
            state.publish(f"thermal guard: servo {sample.sid} cooled down")
        held = state.loop.time() - watch.last_command_s
        if (
            config.neck_hold_s > 0
            and watch.stream == "servo_neck"
            and sample.torque is TorqueControl.ON
            and held > config.neck_hold_s
            and (watch.guard is None or watch.guard.done())
        ):
            state.publish(
                f"hold guard: neck torque on for {held:.0f} s since its last command: resting"
            )
            watch.last_command_s = state.loop.time()
            self._guard(watch, rest=True)

    def _guard(self, watch: ServoWatch, *, rest: bool) -> None:
        if watch.guard is not None and not watch.guard.done():
            return

        async def run() -> None:
            handle = watch.handle
            try:
                if rest and sample_ok(watch.sample):
                    await handle.rest()
                else:
                    await handle.free()
            except OhmniError as exc:
                # A servo in a fault refuses moves: freeing still takes the load off.
                _log.warning("guard: servo %d: %s; freeing it", handle.sid, exc)
                with contextlib.suppress(OhmniError):
                    await handle.free()

        watch.guard = self._state.spawn(run(), f"guard servo {watch.handle.sid}")


def sample_ok(sample: ServoSample | None) -> bool:
    """Whether a servo may still move: no error that blocks moves."""
    if sample is None:
        return True
    return not sample.status_error & (
        StatusError.TEMPERATURE | StatusError.OVERLOAD | StatusError.DRIVER_FAULT
    )
