"""The Robot on the line: what it leaves between a reply and its next request."""

from __future__ import annotations

import asyncio
import itertools

from ohmni_tb.protocol.timing import DEFAULT_GUARD_S
from ohmni_tb.robot import LocalRobot

#: A bit at the simulator's 115200 baud.
_BIT_S = 1 / 115_200


async def test_the_next_request_goes_a_few_bit_times_after_a_reply_from_its_callback() -> None:
    # The reply's sender only has to turn its line driver around: the next request goes
    # three bit times after the reply is seen (the cost model's 0.2 ms guard is for its
    # budget), so the reply's own callback sends it, without a timer.
    async with LocalRobot.open("sim://") as robot:
        await asyncio.sleep(0.5)  # every stream running
        taps: list[tuple[bool, float]] = []
        remove = robot.bus.add_tap(lambda sent, data, t_s: taps.append((sent, t_s)))
        await asyncio.sleep(1.0)
        remove()
    gaps = [
        after_t - reply_t
        for (got, reply_t), (sent, after_t) in itertools.pairwise(taps)
        if not got and sent
    ]
    assert len(gaps) > 100
    assert min(gaps) >= 3 * _BIT_S - 1e-9  # never sooner than the line allows
    soon = [gap for gap in gaps if gap < DEFAULT_GUARD_S / 2]
    assert len(soon) > len(gaps) / 2  # most go as soon as that
