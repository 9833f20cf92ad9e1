"""Codec throughput: encode and decode in bytes/s, as a multiple of the wire's 11,520 B/s.

Run: ``python bench/codec.py`` (``--seconds`` per measurement, ``--chunk`` bytes per feed).

The stream mixes the bus's real traffic shapes (9-byte read requests, 15-byte wheel-count
replies, 16-byte jogs, 31-byte status blocks) with junk between 5 % of the packets, and is
fed in chunks the size a serial read returns. The best of several runs is reported, since
a shared machine only ever makes a run slower.

The decoder is timed next to ``BaselineDecoder`` (``bench/_baseline_decoder.py``, the
previous implementation) on the same chunks, their runs interleaved so that a slow spell
of the machine hits both alike; the ratio of their best runs is the speed-up.
"""

from __future__ import annotations

import argparse
import os
import platform
import random
import sys
import time
from collections.abc import Callable

from _baseline_decoder import BaselineDecoder
from ohmni_tb.protocol import Command, Packet, PacketDecoder, encode_packet

#: 115200 baud, 8N1: ten bits a byte.
WIRE_BYTES_PER_S = 115_200 / 10


def make_packets(n: int, rng: random.Random) -> list[Packet]:
    """A mix of the bus's real request and reply shapes."""
    shapes: list[tuple[int, int]] = [
        (Command.RAM_READ, 2),
        (Command.RAM_READ | 0x40, 8),
        (Command.S_JOG, 9),
        (Command.RAM_READ | 0x40, 22),
        (Command.STAT | 0x40, 2),
    ]
    out = []
    for _ in range(n):
        cmd, size = rng.choice(shapes)
        data = bytes(rng.randrange(256) for _ in range(size))
        out.append(Packet(rng.choice((0, 1, 3, 20)), cmd, data))
    return out


def make_stream(packets: list[Packet], rng: random.Random, junk_ratio: float) -> bytes:
    """Encoded packets with junk (never 0xFF, so it cannot fake a header) in between."""
    parts = []
    for p in packets:
        if rng.random() < junk_ratio * 10:
            parts.append(bytes(rng.randrange(255) for _ in range(rng.randrange(1, 4))))
        parts.append(encode_packet(p))
    return b"".join(parts)


def best_rates(
    fns: dict[str, Callable[[], None]], nbytes: int, seconds: float
) -> tuple[dict[str, float], int]:
    """Best bytes/s of each function, and the runs each got, taking turns for ``seconds``."""
    best = dict.fromkeys(fns, 0.0)
    deadline = time.perf_counter() + seconds * len(fns)
    runs = 0
    while runs < 3 or time.perf_counter() < deadline:
        for name, fn in fns.items():
            t0 = time.perf_counter()
            fn()
            dt = time.perf_counter() - t0
            best[name] = max(best[name], nbytes / dt)
        runs += 1
    return best, runs


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--packets", type=int, default=20_000)
    parser.add_argument("--chunk", type=int, default=64, help="bytes per feed() call")
    parser.add_argument("--seconds", type=float, default=3.0, help="time per measurement")
    args = parser.parse_args()

    rng = random.Random(1)
    packets = make_packets(args.packets, rng)
    stream = make_stream(packets, rng, junk_ratio=0.005)
    chunks = [stream[i : i + args.chunk] for i in range(0, len(stream), args.chunk)]
    encoded_bytes = sum(p.size for p in packets)

    # A speed-up only counts if both decoders say the same thing about the stream.
    new, old = PacketDecoder(), BaselineDecoder()
    for c in chunks:
        if new.feed(c) != old.feed(c):
            raise SystemExit("the decoder and the baseline disagree on the packets")
    if new.stats != old.stats or new.stats.packets != len(packets):
        raise SystemExit(f"stats differ or packets lost:\n{new.stats}\n{old.stats}")

    def decoding(factory: Callable[[], PacketDecoder | BaselineDecoder]) -> Callable[[], None]:
        def decode() -> None:
            decoder = factory()
            n = 0
            for c in chunks:
                n += len(decoder.feed(c))
            if n != len(packets):
                raise SystemExit(f"decoded {n} packets, expected {len(packets)}")

        return decode

    def encode() -> None:
        for p in packets:
            encode_packet(p)

    decode_bps, runs = best_rates(
        {"decode": decoding(PacketDecoder), "baseline": decoding(BaselineDecoder)},
        len(stream),
        args.seconds,
    )
    encode_bps = best_rates({"encode": encode}, encoded_bytes, args.seconds)[0]["encode"]

    cpu = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo", encoding="utf-8") as f:
            cpu = next(line.split(":", 1)[1].strip() for line in f if "model name" in line)
    except (OSError, StopIteration):
        pass
    print(f"python {platform.python_version()} on {cpu}, {os.cpu_count()} cores")
    print(
        f"stream: {len(packets)} packets, {len(stream)} bytes "
        f"({len(stream) - encoded_bytes} junk), fed in {args.chunk}-byte chunks"
    )
    print(f"{'':8} {'bytes/s':>12} {'packets/s':>11} {'x wire (11,520 B/s)':>20}")
    avg = len(stream) / len(packets)
    rows = (*decode_bps.items(), ("encode", encode_bps))
    for name, bps in rows:
        print(f"{name:8} {bps:12,.0f} {bps / avg:11,.0f} {bps / WIRE_BYTES_PER_S:19,.0f}x")
    ratio = decode_bps["decode"] / decode_bps["baseline"]
    print(f"decode / baseline: {ratio:.2f}x (best of {runs} interleaved runs each)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
