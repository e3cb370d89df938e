#!/usr/bin/env bash
# Run the test suite (the CI subset), installing what is missing first.
# Extra arguments go to pytest, e.g. `scripts/test.sh -m slow` for the long statistical runs.
# Two pytest-xdist workers (BDPT_TEST_WORKERS to change; 0 runs in one process): Dr.Jit compiles
# a kernel on one thread, so with an empty kernel cache one core would idle while the other compiles.
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
bash "$root/scripts/bootstrap.sh"
cd "$root"
workers="${BDPT_TEST_WORKERS:-2}"
if [ "$workers" = "0" ]; then
    exec .venv/bin/python -m pytest -q "$@"
fi
exec .venv/bin/python -m pytest -q -n "$workers" --dist loadgroup "$@"
