"""``ohmni_tb.cli.common.run``: Ctrl-C lets a command's cleanup (the Robot's wheel stop)
finish, even when it is pressed again meanwhile."""

from __future__ import annotations

import asyncio
import signal

import pytest
import typer

from ohmni_tb.cli import common


def test_a_second_ctrl_c_does_not_cut_the_cleanup_short(
    capsys: pytest.CaptureFixture[str],
) -> None:
    done: list[str] = []
    summaries: list[str] = []

    async def main() -> None:
        try:
            signal.raise_signal(signal.SIGINT)  # Ctrl-C: the task is cancelled
            await asyncio.sleep(10)
        finally:
            # The cleanup (as the Robot's close: stop the wheels, confirm it) takes a
            # while, and the user presses Ctrl-C again meanwhile.
            signal.raise_signal(signal.SIGINT)
            await asyncio.sleep(0.05)
            signal.raise_signal(signal.SIGINT)
            await asyncio.sleep(0.05)
            done.append("cleaned up")

    with pytest.raises(typer.Exit) as exit_info:
        common.run(main, on_interrupt=lambda: summaries.append("summary"))
    assert exit_info.value.exit_code == 130
    assert done == ["cleaned up"]
    assert summaries == ["summary"]
    err = capsys.readouterr().err
    assert err.count("interrupted again: finishing the cleanup first") == 1
    # Ctrl-C is Python's again afterwards.
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler


def test_ctrl_c_a_command_treats_as_its_end_returns_its_result() -> None:
    async def main() -> str:
        try:
            signal.raise_signal(signal.SIGINT)
            await asyncio.sleep(10)
        except asyncio.CancelledError:
            task = asyncio.current_task()
            assert task is not None
            task.uncancel()
            return "ended by Ctrl-C"
        return "not interrupted"

    assert common.run(main) == "ended by Ctrl-C"


def test_a_cancellation_that_is_not_ctrl_c_is_not_exit_130() -> None:
    async def main() -> None:
        task = asyncio.current_task()
        assert task is not None
        task.cancel()
        await asyncio.sleep(1)

    with pytest.raises(asyncio.CancelledError):
        common.run(main)


@pytest.mark.parametrize(("signum", "code"), [(signal.SIGTERM, 143), (signal.SIGHUP, 129)])
def test_sigterm_and_sighup_end_a_command_through_its_cleanup(signum: int, code: int) -> None:
    # Killed at once, the process would leave the wheels at their last command: the
    # Robot's watchdog runs in this process, and the drive boards have none.
    done: list[str] = []

    async def main() -> None:
        try:
            signal.raise_signal(signum)
            await asyncio.sleep(10)
        finally:
            await asyncio.sleep(0.01)
            done.append("cleaned up")

    with pytest.raises(typer.Exit) as exit_info:
        common.run(main)
    assert exit_info.value.exit_code == code
    assert done == ["cleaned up"]
    assert signal.getsignal(signum) is signal.SIG_DFL


@pytest.mark.parametrize(
    ("via", "source"),
    [
        (None, "local"),  # the port opened on this computer: the robot's
        ("ws://127.0.0.1:8766", "local"),
        ("ws://[::1]:8766", "local"),
        ("ws://localhost:8766", "local"),
        ("wss://127.0.0.2:8766", "local"),
        ("ws://192.0.2.7:8766", "remote"),
        ("ws://robot.lan:8766", "remote"),
    ],
)
def test_a_person_drives_as_local_on_the_robots_computer_and_remote_elsewhere(
    via: str | None, source: str
) -> None:
    assert common.drive_source(via) == source
