#!/usr/bin/env bash
# Run the test suite (the CI subset), installing what is missing first.
# Extra arguments go to pytest, e.g. `scripts/test.sh -m slow` for the long statistical runs.
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
bash "$root/scripts/bootstrap.sh"
cd "$root"
exec .venv/bin/python -m pytest -q "$@"
