#!/usr/bin/env bash
# Run the test suite (the CI subset), installing what is missing first.
# Extra arguments go to pytest, e.g. `scripts/test.sh -m slow` for the long statistical runs.
# BDPT_TEST_WORKERS=N runs N pytest-xdist workers (default: one process): a cold run with two
# workers took 22 min on 2 cores shared with other jobs, not measured side by side with one
# process (20 min quiet, 31 min loaded before this session). (Its failures then,
# "Texture::sample_spectrum(): not implemented", were the Context cycle fixed in 08aa4e8.)
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
bash "$root/scripts/bootstrap.sh"
cd "$root"
workers="${BDPT_TEST_WORKERS:-0}"
if [ "$workers" = "0" ] || [ "$workers" = "1" ]; then
    exec .venv/bin/python -m pytest -q "$@"
fi
exec .venv/bin/python -m pytest -q -n "$workers" --dist loadgroup "$@"
