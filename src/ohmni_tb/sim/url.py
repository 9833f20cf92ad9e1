"""``sim://`` URLs: build a simulated robot and its line from the URL's options.

``open_transport("sim://?neck=worm&docked=1")`` (and ``ohmni sim --pty --url ...``) take
these options:

==================  =========================================================  ==========
option              meaning                                                    default
==================  =========================================================  ==========
``neck``            ``0101`` / ``0201`` (HerkuleX at sid 3) or ``worm`` (sid 4) ``0101``
``ext_servos``      external servo ids, comma-separated, or ``none`` (``ext``  ``11,12``
                    is the same option)
``soc``             battery state of charge at start, percent                  ``80``
``docked``          start on the dock (1/0)                                    ``0``
``count_offset``    initial wheel count of both boards (int32 wrap tests)      ``0``
``stall``           drive board ids whose wheel is blocked (it does not turn   none
                    whatever its PWM), comma-separated
``slip``            drive board ids whose wheel has no traction (it turns,     none
                    the robot does not follow), comma-separated
``wheel_form``      the wheel command the drive boards take: ``s_jog`` or      ``s_jog``
                    ``i_jog``
``right_mirrored``  the right motor is mounted mirrored (1/0)                  ``1``
``drive_torque_addr``  RAM address of the drive boards' torque control         ``52``
``battery_addr``    RAM address of the core board's battery/dock block          ``0xA0``
``battery_length``  its length, bytes (at least its layout's)                  ``18``
``battery_layout``  its layout: ``tbcore`` (18 bytes) or ``cells`` (10)        ``tbcore``
``worm_target_addr``   RAM address of the worm neck's target                   ``0x70``
``worm_feedback_addr`` RAM address of the worm neck's feedback                 ``0x74``
``baudrate``        line speed                                                 ``115200``
``turnaround_us``   device reply delay                                         ``500``
``realtime``        1: replies take their wire time on the clock; 0: at once,  ``1``
                    simulated time running ahead by the traffic's wire time
``usb_latency_ms``  the host adapter's latency timer, 0..32 (0: off): bytes    ``0``
                    reach the host on a grid of this period, or as soon as 62
                    are waiting (an FTDI adapter's USB packet)
``drop``            share of bytes lost on the line, 0..1                      ``0``
``corrupt``         share of bytes garbled on the line, 0..1                   ``0``
``silent``          device ids that never answer, comma-separated              none
``seed``            seed of the fault generator                                ``0``
``tbnode_log``      a file to log the host's bytes to, in the tb-node capture  none
                    format (:mod:`ohmni_tb.sim.tbnode_log`), for ``ohmni bus
                    convert``
==================  =========================================================  ==========

The options from ``neck`` to ``worm_feedback_addr`` describe the robot
(:class:`~ohmni_tb.sim.robot.SimRobot`); the ones from ``wheel_form`` on are its bus
profile, named as the Robot's settings (:class:`~ohmni_tb.protocol.profile.BusProfile`),
so ``sim://?wheel_form=i_jog&battery_addr=0xB0&ext_servos=13,14`` plays a robot whose
boards differ from the assumed profile in those three ways. The rest describe the line
(:class:`~ohmni_tb.sim.line.SimLine`).
"""

from __future__ import annotations

from urllib.parse import SplitResult

from ohmni_tb.errors import ConfigError
from ohmni_tb.sim.line import DEFAULT_TURNAROUND_S, MAX_USB_LATENCY_S, SimLine
from ohmni_tb.sim.robot import SimRobot, parse_ids
from ohmni_tb.sim.tbnode_log import TbnodeLog
from ohmni_tb.sim.transport import SimTransport
from ohmni_tb.transport import (
    DEFAULT_BAUDRATE,
    Transport,
    option_bool,
    option_int,
    register_transport,
    reject_unknown_options,
)

__all__ = ["build_line", "open_sim"]


def build_line(options: dict[str, str]) -> tuple[SimLine, SimRobot]:
    """Build a simulated robot and its line from ``sim://`` options, consuming them.

    Raises:
        ConfigError: An option's value is invalid; the message names it.
    """
    baudrate = option_int(options, "baudrate", DEFAULT_BAUDRATE, 1200, 4_000_000)
    turnaround_us = option_int(
        options, "turnaround_us", round(DEFAULT_TURNAROUND_S * 1e6), 0, 100_000
    )
    seed = option_int(options, "seed", 0, 0, 2**32 - 1)
    realtime = option_bool(options, "realtime", True)
    usb_latency_ms = option_int(options, "usb_latency_ms", 0, 0, round(MAX_USB_LATENCY_S * 1e3))
    drop = _option_rate(options, "drop")
    corrupt = _option_rate(options, "corrupt")
    silent = parse_ids("silent", options.pop("silent", ""))
    tbnode_log = options.pop("tbnode_log", None)
    robot = SimRobot.from_options(options)
    line = SimLine(
        robot.devices,
        baudrate=baudrate,
        turnaround_s=turnaround_us / 1e6,
        seed=seed,
        realtime=realtime,
        usb_latency_s=usb_latency_ms / 1e3,
    )
    line.faults.drop_rate = drop
    line.faults.corrupt_rate = corrupt
    line.faults.silent = set(silent)
    if tbnode_log is not None:
        # Last: the file is created once the other options have parsed.
        line.add_tap(TbnodeLog(tbnode_log))
    return line, robot


async def open_sim(url: SplitResult, options: dict[str, str]) -> Transport:
    """Open a simulated robot from a ``sim://`` URL (options: the module docstring)."""
    if url.netloc or url.path.strip("/"):
        raise ConfigError(f"sim:// takes options only, not {url.netloc + url.path!r}")
    line, robot = build_line(options)
    reject_unknown_options(url, options)
    return SimTransport(line, robot=robot)


def _option_rate(options: dict[str, str], key: str) -> float:
    raw = options.pop(key, None)
    if raw is None:
        return 0.0
    try:
        value = float(raw)
    except ValueError:
        raise ConfigError(f"option {key}={raw!r} is not a number") from None
    if not 0.0 <= value <= 1.0:
        raise ConfigError(f"option {key}={value} is out of range: allowed 0..1")
    return value


register_transport("sim", open_sim)
