#!/usr/bin/env bash
# The Quick start's second command: set up, then run the test suite, in three worker
# processes (pytest-xdist; `-n 0` runs it in this one). Most of the wall time left is
# real-time tests waiting on subprocesses and ptys, so three workers overlap it on 2 cores.
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
source "$root/scripts/setup.sh"
cd "$root"
# pytest keeps the test modules it rewrote (for its assert messages) in __pycache__; with
# bytecode writing off it rewrites all of them again in every worker, every run.
export PYTHONDONTWRITEBYTECODE=
exec "$root/.venv/bin/python" -m pytest -n 3 --dist worksteal "$@"
