#!/usr/bin/env bash
# The whole numerical-stability suite (tests/test_stability.py and the fuzzer tests/test_fuzz.py),
# the parts marked slow included: long statistical agreement runs, every technique/weighting
# combination, and the larger fuzzer. Installs what is missing first. Extra arguments go to
# pytest (e.g. -x, -k sphere); BDPT_FUZZ_SEEDS=a:b runs fuzz seeds a..b-1.
# The CI subset is `bash scripts/test.sh tests/test_stability.py tests/test_fuzz.py`.
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
bash "$root/scripts/bootstrap.sh"
cd "$root"
exec .venv/bin/python -m pytest -q -m "slow or not slow" tests/test_stability.py tests/test_fuzz.py "$@"
