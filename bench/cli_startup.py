"""How fast ``ohmni`` starts: ``--help`` of the program and of every command.

Run: ``python bench/cli_startup.py`` (``--runs N``, 15 by default).

Each row runs a fresh ``python -m ohmni_tb ... --help`` process ``--runs`` times and
prints the wall time (min and median; a process start is what a user waits for). The
last row is the simple alternative beside it: the same ``ohmni --help`` with every
command's module imported first, as a CLI that registers its commands eagerly does; the
ratio is printed. Target (issue 11): every row <= 0.35 s here (the robot's Atom is ~3x
slower).
"""

from __future__ import annotations

import argparse
import statistics
import subprocess
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).parent))
from ohmni_tb.cli import COMMANDS
from schedule import machine

EAGER = (
    "import importlib, sys\n"
    "from ohmni_tb.cli import COMMANDS, app\n"
    "for module, _, _ in COMMANDS.values():\n"
    "    importlib.import_module(module)\n"
    "sys.argv = ['ohmni', '--help']\n"
    "app()\n"
)


def timed(argv: list[str], runs: int) -> list[float]:
    times = []
    for _ in range(runs):
        start = time.perf_counter()
        subprocess.run(argv, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, check=False)
        times.append(time.perf_counter() - start)
    return times


def main() -> int:
    parser = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    parser.add_argument("--runs", type=int, default=15)
    args = parser.parse_args()
    print(machine())
    print(f"{'command':<28} {'min':>7} {'median':>7}  (s, {args.runs} runs each)")
    rows: dict[str, list[float]] = {}
    program = [sys.executable, "-m", "ohmni_tb"]
    rows["ohmni --help"] = timed([*program, "--help"], args.runs)
    for name in COMMANDS:
        rows[f"ohmni {name} --help"] = timed([*program, name, "--help"], args.runs)
    rows["eager: ohmni --help"] = timed([sys.executable, "-c", EAGER], args.runs)
    for label, times in rows.items():
        flag = "" if min(times) <= 0.35 else "  > 0.35 s"
        print(f"{label:<28} {min(times):7.3f} {statistics.median(times):7.3f}{flag}")
    lazy, eager = rows["ohmni --help"], rows["eager: ohmni --help"]
    ratio = statistics.median(eager) / statistics.median(lazy)
    print(f"ohmni --help, eager imports / lazy table: {ratio:.2f}x (median)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
