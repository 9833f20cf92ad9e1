"""ohmni_tb.robot.teleop: terminal keys to drive commands, on the simulator in virtual time."""

from __future__ import annotations

import asyncio

import pytest

from ohmni_tb import Robot
from ohmni_tb.errors import InvalidArgumentError
from ohmni_tb.robot.teleop import KEY_HOLD_S, SCALE_STEP, KeyParser, KeyTeleop
from ohmni_tb.sim.clock import run_virtual


@pytest.mark.parametrize(
    ("chunks", "actions"),
    [
        ([b"wasd q"], ["forward", "left", "back", "right", "stop", "quit"]),
        ([b"\x1b[A\x1b[B\x1b[C\x1b[D"], ["forward", "back", "right", "left"]),
        ([b"\x1bOA"], ["forward"]),  # application mode
        ([b"\x1b[1;5A"], ["forward"]),  # with a modifier
        ([b"\x1b[", b"A"], ["forward"]),  # split across reads
        ([b"\x1b[2~w"], ["forward"]),  # another sequence is skipped whole, not read as keys
        ([b"x\x03"], ["quit"]),  # no key: ignored; Ctrl-C quits
        ([b"+-="], ["faster", "slower", "faster"]),
    ],
)
def test_terminal_bytes_become_actions(chunks: list[bytes], actions: list[str]) -> None:
    parser = KeyParser()
    got = [action for chunk in chunks for action in parser.feed(chunk)]
    assert got == actions


def test_a_lone_escape_is_dropped_on_flush() -> None:
    parser = KeyParser()
    assert parser.feed(b"\x1b") == []
    parser.flush()
    assert parser.feed(b"[A") == ["left"]  # the Esc was dropped: not an arrow, a key


def test_a_held_key_drives_and_letting_go_stops() -> None:
    async def main() -> tuple[float, float, float, str]:
        loop = asyncio.get_running_loop()
        async with Robot.open("sim://") as robot:
            teleop = KeyTeleop(robot, linear_mps=0.3)
            start = robot.sim.pose.x
            until = loop.time() + 1.0
            while loop.time() < until:  # a terminal repeats a held key ~30 times a second
                teleop.press("forward", loop.time())
                await asyncio.sleep(0.03)
                teleop.decay(loop.time())
            moving = robot.sim.wheel_speeds_mps()[0]
            await asyncio.sleep(KEY_HOLD_S + 0.05)
            teleop.decay(loop.time())
            await asyncio.sleep(1.0)
            return (
                robot.sim.pose.x - start,
                moving,
                robot.sim.wheel_speeds_mps()[0],
                (teleop.action),
            )

    travelled, moving, after, action = run_virtual(main())
    assert moving == pytest.approx(0.3, abs=0.05)
    assert 0.25 < travelled < 0.5  # 1 s of keys, the hold time, the ramps
    assert after == 0.0
    assert action == f"stopped (no key for {KEY_HOLD_S:g} s)"


def test_faster_stays_within_the_robots_limits_and_turning_keys_turn() -> None:
    async def main() -> tuple[float, float, tuple[float, float]]:
        loop = asyncio.get_running_loop()
        async with Robot.open("sim://", max_linear_mps=0.5) as robot:
            teleop = KeyTeleop(robot, linear_mps=0.3)
            for _ in range(10):
                teleop.press("faster", loop.time())
            top = teleop.linear_mps
            teleop.press("slower", loop.time())
            teleop.press("left", loop.time())
            return top, teleop.linear_mps, teleop.command

    top, slower, command = run_virtual(main())
    assert top == 0.5
    assert slower == pytest.approx(0.5 / SCALE_STEP)
    assert command[0] == 0.0
    assert command[1] > 0.0  # counter-clockwise


def test_an_unknown_action_is_refused_and_nothing_is_sent() -> None:
    async def main() -> tuple[str, tuple[float, float]]:
        async with Robot.open("sim://") as robot:
            teleop = KeyTeleop(robot)
            with pytest.raises(InvalidArgumentError) as caught:
                teleop.press("jump", 0.0)
            return str(caught.value), teleop.command

    message, command = run_virtual(main())
    assert "no teleop action 'jump'" in message
    assert "forward, back, left, right" in message
    assert command == (0.0, 0.0)
