#!/usr/bin/env bash
# Run the test suite (the CI subset), installing what is missing first.
# Extra arguments go to pytest, e.g. `scripts/test.sh -m slow` for the long statistical runs.
# BDPT_TEST_WORKERS=N runs N pytest-xdist workers (default: one process). Not the default: with
# two workers, test_coverage's Mitsuba ptracer references fail now and then with "Texture::
# sample_spectrum(): not implemented" (reproduced with `-n 2 tests/test_coverage.py`; cause not
# found), and a cold run took 22 min with two workers on 2 busy cores, no faster than one process.
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
bash "$root/scripts/bootstrap.sh"
cd "$root"
workers="${BDPT_TEST_WORKERS:-0}"
if [ "$workers" = "0" ] || [ "$workers" = "1" ]; then
    exec .venv/bin/python -m pytest -q "$@"
fi
exec .venv/bin/python -m pytest -q -n "$workers" --dist loadgroup "$@"
