#!/usr/bin/env bash
# Run the test suite (the CI subset), installing what is missing first.
# Extra arguments go to pytest, e.g. `scripts/test.sh -m slow` for the long statistical runs.
# The tests run in pytest-xdist workers, one per core up to 2 (BDPT_TEST_WORKERS=N sets N; 1 runs
# one process), each test file on one worker (--dist loadfile), so that a file's kernels are
# compiled once: Dr.Jit compiles a kernel on one thread, and a second worker renders meanwhile.
# Measured on 2 cores with an empty kernel cache and no tests/.refcache (a fresh clone): 13 min 21 s at 781fe4f, 14 min 9 s at 58b052a (with the media tests), 13 min 25 s at 1f6b9f2 (4371 tests), 17 min 4 s at 3b8289d (4683 tests; 15 min 49 s here at 8420284, whose suite the CI service ran in 690 s), 16 min 23 s at 3d15d79 (4686 tests, pytest's own 15 min 45 s), 16 min 57 s at cf85ad3 (4984 tests, pytest's 16 min 31 s), 17 min 42 s at 96dbc6a (pytest's 17 min 12 s), 16 min 26 s at 52e07fc (pytest's 15 min 59 s), 16 min 59 s at 1c3912c (pytest's 16 min 30 s), 16 min 42 s at da75fdc (pytest's 16 min 14 s), 13 min 43 s at 4b01e46 with the references stored in tests/references (pytest's 13 min 18 s), 13 min 52 s at 76909b9 (5011 tests, pytest's 13 min 27 s), 13 min 42 s at 70f9a27 (5018 tests, pytest's 13 min 10 s), 13 min 51 s at e9413f6 (5021 tests, pytest's 13 min 24 s), 13 min 46 s at 1367906 (5022 tests, pytest's 13 min 19 s), 13 min 30 s at 173cada (5025 tests, pytest's 13 min 1 s), 13 min 28 s at 377232d (5026 tests, pytest's 12 min 55 s), 13 min 39 s at 4d5c5e6 (pytest's 13 min 10 s), 13 min 4 s at 3c0d0a6 (5033 tests, pytest's 12 min 37 s), 13 min 26 s at 7196e5a (5037 tests, pytest's 12 min 59 s), 14 min 12 s at d2583a3 (5038 tests, pytest's 13 min 42 s); the twenty-sixth session's runs on one machine: 14 min 12 s (user 26 min 30 s) at 8a05e8d (d2583a3's tests), 15 min 28 s (user 29 min 12 s) at b4a6511 (+13 s of tests), 16 min 17 s (user 30 min 51 s) at e2fe857 (19 s of them moved to slow), 16 min 49 s (user 31 min 44 s) at 32a0905 (14 s more moved): the machine slowed, not the suite; the twenty-seventh session's: 16 min 12 s (user 30 min 43 s) at 551585e (5054 tests), 17 min 5 s (user 32 min 6 s) at f81f273, 17 min 29 s (user 32 min 50 s) at 303067d (5058 tests), 16 min 37 s (user 30 min 34 s) at 4c646bc (the CI service ran the twenty-sixth session's 5037 in 847 s, the twenty-seventh's 5058 in 763 s); the twenty-eighth session's: 17 min 58 s (user 33 min 48 s) at 7519405 (5070 tests, pytest's 17 min 30 s; its new tests take 10 s cold), 16 min 53 s (user 31 min 52 s) at a49dcb6 (5072 tests, pytest's 16 min 26 s), 17 min 37 s (user 33 min 3 s) at 876f7f1 (5073 tests, pytest's 17 min 9 s), 17 min 38 s (user 33 min 22 s) at 3db4144 (5075 tests, pytest's 17 min 10 s); the twenty-ninth session's: 17 min 42 s (user 33 min 24 s) at 19958f5 (34 media references rendered: their keys held the test sources' hash), 16 min 52 s (user 31 min 44 s) at 2e69972 (references stored), 16 min 44 s (user 31 min 26 s) at d539c04 (5088 tests, pytest's 16 min 6 s; none rendered), 16 min 44 s (user 31 min 35 s) at d0998e3 (5089 tests, pytest's 16 min 15 s, by .ci/run), 16 min 34 s (user 31 min 13 s) at 18e665d (5091 tests, pytest's 16 min 8 s)
# with two workers, against 20 min 40 s in one process (docs/performance.md, sixth session).
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
bash "$root/scripts/bootstrap.sh"
cd "$root"
cores="$(nproc 2>/dev/null || echo 1)"
workers="${BDPT_TEST_WORKERS:-$(( cores < 2 ? 1 : 2 ))}"
if [ "$workers" = "0" ] || [ "$workers" = "1" ]; then
    exec .venv/bin/python -m pytest -q "$@"
fi
# --max-worker-restart 0: a worker that dies ends the run with its test named (pytest-xdist 3.8
# replaces a dead worker under --dist loadfile and can then wait forever: its issue #784)
exec .venv/bin/python -m pytest -q -n "$workers" --dist loadfile --max-worker-restart 0 "$@"
