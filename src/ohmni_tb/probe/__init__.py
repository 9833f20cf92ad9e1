"""``ohmni probe`` as a library: find what a robot's boards really speak.

The project's bus profile (:class:`~ohmni_tb.protocol.profile.BusProfile`) is partly
assumed: the wheel command's form, the drive boards' torque register, the battery block,
the worm neck's registers, the external servo ids. :func:`probe_port` opens a port, asks
every id which answers (read-only), finds each assumed part or says it differs, and —
only with ``allow_motion=True`` — turns each wheel a little to find the wheel command.
The report gives each finding, the devices with their reply latency, the USB adapter,
and the profile found as settings::

    import asyncio
    from ohmni_tb.probe import probe_port

    async def main() -> None:
        report = await probe_port("sim://?battery_addr=0xB0", ids=range(0, 21))
        for finding in report.findings:
            print(finding.name, finding.status.value, finding.detail)
        print(report.differing())            # {'battery_addr': (160, 176)}

    asyncio.run(main())

The judging is sans-IO (:mod:`ohmni_tb.probe.findings`: bytes in, findings out), the USB
adapter is read from sysfs (:mod:`ohmni_tb.probe.adapter`), and the async part drives the
:class:`~ohmni_tb.bus.Bus` (:mod:`ohmni_tb.probe.session`).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from ohmni_tb.probe.findings import (
    AdapterInfo,
    Device,
    Finding,
    ProbeReport,
    RawRead,
    Skipped,
    Status,
    WheelTrial,
    shareable,
)

if TYPE_CHECKING:
    from ohmni_tb.probe.adapter import read_adapter
    from ohmni_tb.probe.session import ALL_IDS, probe, probe_port, wheel_stops

__all__ = [
    "ALL_IDS",
    "AdapterInfo",
    "Device",
    "Finding",
    "ProbeReport",
    "RawRead",
    "Skipped",
    "Status",
    "WheelTrial",
    "probe",
    "probe_port",
    "read_adapter",
    "shareable",
    "wheel_stops",
]

#: The names whose modules do I/O, imported on first use: the judges
#: (:mod:`ohmni_tb.probe.findings`) stay importable without asyncio.
_LAZY = {
    "read_adapter": "ohmni_tb.probe.adapter",
    "ALL_IDS": "ohmni_tb.probe.session",
    "probe": "ohmni_tb.probe.session",
    "probe_port": "ohmni_tb.probe.session",
    "wheel_stops": "ohmni_tb.probe.session",
}


def __getattr__(name: str) -> Any:
    module = _LAZY.get(name)
    if module is None:
        raise AttributeError(f"module 'ohmni_tb.probe' has no attribute {name!r}")
    import importlib  # noqa: PLC0415  # lazy on purpose: see _LAZY

    value = getattr(importlib.import_module(module), name)
    globals()[name] = value
    return value
