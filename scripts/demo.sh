#!/usr/bin/env bash
# The Quick start's first command: set up, then run the demo on the built-in simulator.
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
source "$root/scripts/setup.sh"
exec "$root/.venv/bin/ohmni" demo --port "${OHMNI_PORT:-sim://}" "$@"
