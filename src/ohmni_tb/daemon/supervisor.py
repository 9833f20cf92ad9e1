"""``ohmni serve``'s supervisor: a daemon that dies does not leave the robot driving.

The drive boards keep the last wheel command they were given, and the motion watchdog
runs in the process that drives them: when that process dies (``kill -9``, the OOM
killer, a crash) nothing else would stop the wheels. So ``ohmni serve`` is two
processes::

    ohmni serve  (the supervisor: the PID users and service managers see; no port)
      │  stdin/stderr shared; the worker's stdout read and passed on
      │  a socket pair: the supervisor writes only to ask for a stop; the worker
      │  writes a heartbeat from its event loop every HEARTBEAT_S
      └── ohmni serve --supervisor-fd FD  (the worker: the Robot and the server)

- **The worker dies** without a clean exit (killed, crashed, failed while serving): the
  supervisor opens the port — the worker's exclusive lock went with it — and stops the
  wheels with :func:`~ohmni_tb.safety.stop_wheels` (confirmed by the wheel counts),
  logs it, and starts a new worker after a back-off (:data:`RESTART_BACKOFF_S`). After
  :data:`MAX_QUICK_DEATHS` deaths in a row, each within :data:`QUICK_DEATH_S` of its
  start, it gives up and exits 1. On ``sim://`` the simulator dies with the worker:
  there is nothing to stop, and it just starts a new one.
- **The worker hangs** (its event loop stuck: the Robot's watchdog and control tick with
  it): no heartbeat for :data:`HUNG_S`, and the supervisor kills it, then goes on as
  after a death.
- **The supervisor dies**: the worker's end of the pipe reads end-of-file at once, on
  every OS, and the worker shuts down as on SIGTERM (:func:`until_stopped`): the Robot
  brakes at once, the clients are closed, the wheels are stopped (confirmed) and the
  port closed.
- **A requested stop** (SIGINT, SIGTERM, SIGHUP to the supervisor): the supervisor asks
  the worker through the pipe and exits with the worker's code: 0 after a clean
  shutdown. A worker that has not ended :data:`WORKER_EXIT_S` later is killed, and the
  supervisor stops the wheels itself (exit 1).

The worker runs in a session of its own: a terminal's Ctrl-C or hang-up reaches the
supervisor, which passes it on, and only once. The first worker's stdout lines (the
addresses) are the supervisor's stdout; a restarted worker's are logged instead.

What this does not cover: the host losing power (the drive boards keep their last
command), and a supervisor that hangs without dying while its worker dies or hangs.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import os
import signal
import socket
import sys
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Final

from ohmni_tb.errors import OhmniError, StateError

if TYPE_CHECKING:
    from ohmni_tb.protocol.drive import DriveProfile
    from ohmni_tb.safety import StopReport

__all__ = [
    "HEARTBEAT_S",
    "HUNG_S",
    "MAX_QUICK_DEATHS",
    "QUICK_DEATH_S",
    "RESTART_BACKOFF_S",
    "WORKER_EXIT_S",
    "WorkerCommand",
    "stop_wheels_at",
    "supervise",
    "until_stopped",
]

#: The waits before each restart after deaths in a row (the last one repeats): a worker
#: that dies at once is not restarted in a tight loop.
RESTART_BACKOFF_S: Final = (0.5, 1.0, 2.0, 4.0)
#: A worker that dies sooner than this after its start counts as a quick death.
QUICK_DEATH_S: Final = 30.0
#: Quick deaths in a row after which the supervisor gives up (exit 1).
MAX_QUICK_DEATHS: Final = 5
#: How long a worker asked to stop may take (its clients closed, the stop confirmed, the
#: neck rested) before it is killed: below the systemd unit's TimeoutStopSec (10 s).
WORKER_EXIT_S: Final = 8.0

#: How often a serving worker's event loop tells the supervisor it runs.
HEARTBEAT_S: Final = 0.1
#: A worker silent this long (its loop stuck) is killed, and the wheels stopped: its
#: watchdog cannot act. Well above the loop's longest pauses (a collector pass, a slow
#: start), well below the time a robot driving at 1 m/s may be left alone.
HUNG_S: Final = 1.0

#: The worker's command line, from the pipe's descriptor and the lines the first worker
#: printed (empty for the first worker: a restarted one keeps the addresses it chose).
WorkerCommand = Callable[[int, Sequence[str]], list[str]]

_log = logging.getLogger(__name__)
#: What the supervisor writes before closing the pipe when it asks for a stop (a plain
#: end of file means it died).
_STOP_WORD: Final = b"stop\n"


async def supervise(
    command: WorkerCommand,
    *,
    port: str,
    stop: asyncio.Event,
    ready_lines: int = 1,
    write: Callable[[str], object] | None = None,
) -> int:
    """Run the worker, stop the wheels whenever it dies, and restart it (module docstring).

    Args:
        command: Builds the worker's command line.
        port: The port the worker opens (the supervisor opens it only after a death).
        stop: Set when a stop is requested (``ohmni_tb.cli.common.run``'s signals).
        ready_lines: How many stdout lines a serving worker prints (its addresses).
        write: Where the first worker's stdout lines go (default: this stdout).

    Returns:
        The exit code: the worker's after a requested stop (0 once it shut down cleanly),
        the first worker's when it could not start, 1 when a stop was not confirmed.

    Raises:
        StateError: The worker died :data:`MAX_QUICK_DEATHS` times in a row soon after its
            start: it is not restarted again.
    """
    loop = asyncio.get_running_loop()
    simulated = port.lower().startswith("sim:")
    emit = write if write is not None else _print
    shown: list[str] = []  # the address lines on stdout
    quick_deaths = 0
    starts = 0
    gave_up = ""
    async with asyncio.TaskGroup() as tasks:
        # Loaded while the worker starts, so a death costs no import before the stop.
        prepared = None if simulated else tasks.create_task(asyncio.to_thread(_prepare))
        while True:
            starts += 1
            worker = await _Worker.start(command, shown)
            tasks.create_task(worker.forward(shown, ready_lines, emit))
            hang_watch = tasks.create_task(worker.watch_heartbeat())
            if starts > 1:
                _log.warning("worker restarted (pid %d)", worker.proc.pid)
            ended = tasks.create_task(worker.proc.wait())
            requested = tasks.create_task(stop.wait())
            await asyncio.wait((ended, requested), return_when=asyncio.FIRST_COMPLETED)
            requested.cancel()
            hang_watch.cancel()
            if not ended.done():
                return await _stop_worker(worker, ended, port, prepared)
            code = ended.result()
            worker.close_pipe()
            if code == 0:
                return 0  # it was told to stop directly (a signal of its own) and did
            if starts == 1 and not worker.ready.is_set() and code > 0:
                return code  # it could not start: its error is on stderr already
            lived_s = loop.time() - worker.started_at
            confirmed = await _stop_after(worker, code, port, prepared)
            quick_deaths = quick_deaths + 1 if lived_s < QUICK_DEATH_S else 1
            if quick_deaths >= MAX_QUICK_DEATHS:
                gave_up = (
                    f"the daemon's worker died {quick_deaths} times in a row, each within "
                    f"{QUICK_DEATH_S:g} s of its start (the last {_how(code)}): not restarted "
                    "again"
                )
                break
            backoff_s = RESTART_BACKOFF_S[min(quick_deaths, len(RESTART_BACKOFF_S)) - 1]
            _log.warning("restarting the worker in %g s", backoff_s)
            with contextlib.suppress(TimeoutError):
                async with asyncio.timeout(backoff_s):
                    await stop.wait()
            if stop.is_set():
                return 0 if confirmed else 1
    # Raised here, not inside the task group (which would wrap it in an ExceptionGroup).
    raise StateError(gave_up)


async def until_stopped(stop: asyncio.Event, supervisor_fd: int | None = None) -> str:
    """The worker's wait: until ``stop`` is set (a signal) or the supervisor's pipe ends.

    Args:
        stop: Set by the worker's own stop signals.
        supervisor_fd: The read end of the supervisor's pipe (``--supervisor-fd``), or
            ``None`` when nobody supervises.

    Returns:
        Why: ``"signal"``, ``"asked"`` (the supervisor asked for a stop) or ``"gone"``
        (the supervisor died: the pipe ended without a word).
    """
    if supervisor_fd is None:
        await stop.wait()
        return "signal"
    loop = asyncio.get_running_loop()
    why = "signal"
    heard = bytearray()

    def readable() -> None:
        nonlocal why
        try:
            data = os.read(supervisor_fd, 64)
        except BlockingIOError:
            return
        except OSError:
            data = b""  # the pipe failed: as good as gone
        if data:
            heard.extend(data[: len(_STOP_WORD)])
            return
        loop.remove_reader(supervisor_fd)
        if not stop.is_set():
            why = "asked" if bytes(heard).startswith(_STOP_WORD) else "gone"
            stop.set()

    beat_timer: asyncio.Handle | None = None

    def beat() -> None:
        nonlocal beat_timer
        with contextlib.suppress(OSError):  # full (the supervisor is busy) or gone
            os.write(supervisor_fd, b".")
        beat_timer = loop.call_later(HEARTBEAT_S, beat)

    os.set_blocking(supervisor_fd, False)
    loop.add_reader(supervisor_fd, readable)
    beat_timer = loop.call_soon(beat)
    try:
        await stop.wait()
    finally:
        beat_timer.cancel()
        loop.remove_reader(supervisor_fd)
    return why


async def stop_wheels_at(
    url: str,
    *,
    timeout_s: float | None = None,
    bus_timeout_s: float | None = None,
    profile: DriveProfile | None = None,
) -> StopReport:
    """Open ``url``, stop both wheels confirmed by their counts
    (:func:`~ohmni_tb.safety.stop_wheels`), send a last stop and close the port.

    Args:
        url: The port (``/dev/ttyUSB0``, ``serial://…``, ``auto``, ``sim://``).
        timeout_s: How long to try (default :data:`~ohmni_tb.safety.DEFAULT_STOP_TIMEOUT_S`).
        bus_timeout_s: The bus's reply timeout (default the bus's).
        profile: The drive boards' profile: the wheel command's form (default the
            assumed one).

    Raises:
        TransportError: The port cannot be opened (missing, held by another program).
        StopNotConfirmedError: The counts did not show the wheels still in time.
    """
    from ohmni_tb.bus import DEFAULT_TIMEOUT_S, Bus  # noqa: PLC0415  # loaded when used
    from ohmni_tb.protocol.drive import DRIVE_PROFILE, wheel_command  # noqa: PLC0415
    from ohmni_tb.safety import DEFAULT_STOP_TIMEOUT_S, stop_wheels  # noqa: PLC0415
    from ohmni_tb.transport import open_transport  # noqa: PLC0415

    boards = DRIVE_PROFILE if profile is None else profile
    transport = await open_transport(url)
    bus = Bus(transport, timeout_s=DEFAULT_TIMEOUT_S if bus_timeout_s is None else bus_timeout_s)
    bus.start()
    try:
        return await stop_wheels(
            bus,
            timeout_s=DEFAULT_STOP_TIMEOUT_S if timeout_s is None else timeout_s,
            profile=boards,
        )
    finally:
        await bus.aclose(final=[wheel_command(0, 0, boards)])


# -- private ------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class _StopSettings:
    """The settings a stop after a death uses: the config file's, as the worker's."""

    bus_timeout_s: float | None = None
    stop_timeout_s: float | None = None
    profile: DriveProfile | None = None


def _prepare() -> _StopSettings:
    """Load what a stop needs (run in a thread while the first worker starts)."""
    import ohmni_tb.bus  # noqa: PLC0415  # loaded now, not after a death
    import ohmni_tb.safety  # noqa: PLC0415
    import ohmni_tb.transport  # noqa: F401, PLC0415
    from ohmni_tb.config import RobotConfig  # noqa: PLC0415
    from ohmni_tb.errors import ConfigError  # noqa: PLC0415

    try:
        config = RobotConfig.load()
    except ConfigError:
        return _StopSettings()  # the worker says what is wrong with it
    return _StopSettings(config.bus_timeout_s(), config.stop_timeout_s, config.profile().drive)


class _Worker:
    """One worker process, its pipe and what it printed."""

    def __init__(self, proc: asyncio.subprocess.Process, pipe: int, started_at: float) -> None:
        self.proc = proc
        self._pipe: int | None = pipe
        self.started_at = started_at
        self.ready = asyncio.Event()
        #: When the worker's last heartbeat came (``None``: none yet, it is starting).
        self.last_beat_s: float | None = None
        loop = asyncio.get_running_loop()
        os.set_blocking(pipe, False)
        loop.add_reader(pipe, self._heard)

    def _heard(self) -> None:
        if self._pipe is None:
            return
        try:
            data = os.read(self._pipe, 4096)
        except BlockingIOError:
            return
        except OSError:
            data = b""
        if data:
            self.last_beat_s = asyncio.get_running_loop().time()
        else:  # the worker's end closed: it is ending; its exit says how
            asyncio.get_running_loop().remove_reader(self._pipe)

    async def watch_heartbeat(self) -> None:
        """Kill a worker whose heartbeat stopped for :data:`HUNG_S` while it runs: its
        event loop is stuck, and the wheels with whatever it last sent them."""
        loop = asyncio.get_running_loop()
        while self.proc.returncode is None:
            await asyncio.sleep(HEARTBEAT_S)
            beat = self.last_beat_s
            if beat is None or loop.time() - beat <= HUNG_S:
                continue
            _log.error(
                "the worker (pid %d) has not run for %.1f s (hung): killing it",
                self.proc.pid,
                loop.time() - beat,
            )
            with contextlib.suppress(ProcessLookupError):
                self.proc.kill()
            return

    @classmethod
    async def start(cls, command: WorkerCommand, shown: Sequence[str]) -> _Worker:
        # One socket each way would do as two pipes; a socket pair is both in one
        # descriptor. Neither end is inherited but as pass_fds says.
        ours, theirs = socket.socketpair()
        write_end = ours.detach()
        read_end = theirs.detach()
        try:
            proc = await asyncio.create_subprocess_exec(
                *command(read_end, tuple(shown)),
                stdout=asyncio.subprocess.PIPE,
                pass_fds=(read_end,),
                # The terminal's Ctrl-C and hang-up reach the supervisor only, which
                # passes them on once (the pipe); a service manager's signals reach both.
                start_new_session=True,
            )
        except BaseException:
            os.close(write_end)
            raise
        finally:
            os.close(read_end)
        return cls(proc, write_end, asyncio.get_running_loop().time())

    async def forward(
        self, shown: list[str], ready_lines: int, emit: Callable[[str], object]
    ) -> None:
        """Pass the worker's address lines on while stdout has not shown them all yet
        (and keep them); log what a restarted worker prints instead."""
        stream = self.proc.stdout
        assert stream is not None  # started with stdout=PIPE
        seen = 0
        while line := await stream.readline():
            text = line.decode(errors="replace").rstrip("\n")
            if seen == len(shown) < ready_lines:
                shown.append(text)
                emit(text)
            else:
                _log.warning("the restarted worker (pid %d) serves: %s", self.proc.pid, text)
            seen += 1
            if seen == ready_lines:
                self.ready.set()

    def ask_to_stop(self) -> None:
        if self._pipe is not None:
            with contextlib.suppress(OSError):  # it died meanwhile: nobody reads
                os.write(self._pipe, _STOP_WORD)
        self.close_pipe()

    def close_pipe(self) -> None:
        if self._pipe is not None:
            with contextlib.suppress(ValueError, RuntimeError):  # the loop closed first
                asyncio.get_running_loop().remove_reader(self._pipe)
            os.close(self._pipe)
            self._pipe = None


async def _stop_worker(
    worker: _Worker,
    ended: asyncio.Task[int],
    port: str,
    prepared: asyncio.Task[_StopSettings] | None,
) -> int:
    """A requested stop: ask the worker, wait for it, and take over if it does not end."""
    worker.ask_to_stop()
    try:
        async with asyncio.timeout(WORKER_EXIT_S):
            code = await asyncio.shield(ended)
    except TimeoutError:
        _log.warning(
            "the worker (pid %d) did not stop within %g s: killing it",
            worker.proc.pid,
            WORKER_EXIT_S,
        )
        with contextlib.suppress(ProcessLookupError):
            worker.proc.kill()
        code = await ended
    if code == 0:
        return 0
    await _stop_after(worker, code, port, prepared)
    return code if code > 0 else 1


async def _stop_after(
    worker: _Worker, code: int, port: str, prepared: asyncio.Task[_StopSettings] | None
) -> bool:
    """Stop the wheels after the worker ended badly; log it. Whether the stop confirmed."""
    how = f"the worker (pid {worker.proc.pid}) {_how(code)}"
    if prepared is None:
        _log.warning("%s: the simulator went with it, nothing to stop", how)
        return True
    settings = await prepared
    try:
        report = await stop_wheels_at(
            port,
            timeout_s=settings.stop_timeout_s,
            bus_timeout_s=settings.bus_timeout_s,
            profile=settings.profile,
        )
    except OhmniError as exc:
        _log.error("%s, and the wheels may still be moving: %s", how, exc)
        return False
    _log.warning(
        "%s: the wheels are stopped, confirmed by their counts %.3f s after the first stop "
        "(%d stops sent)",
        how,
        report.elapsed_s,
        report.stops_sent,
    )
    return True


def _how(code: int) -> str:
    """``killed by SIGKILL`` / ``exited with code 1``."""
    if code < 0:
        try:
            name = signal.Signals(-code).name
        except ValueError:
            name = f"signal {-code}"
        return f"was killed by {name}"
    return f"exited with code {code}"


def _print(text: str) -> None:
    try:
        sys.stdout.write(text + "\n")
        sys.stdout.flush()
    except (BrokenPipeError, ValueError):
        pass  # the reader of the addresses has gone: serving goes on
