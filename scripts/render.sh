#!/usr/bin/env bash
# Render the default scene with bdpt to out/cornell-box.exr and out/cornell-box.png,
# installing what is missing first. Extra arguments go to `bdpt-jit render`.
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
bash "$root/scripts/bootstrap.sh"
mkdir -p "$root/out"
exec "$root/.venv/bin/bdpt-jit" render "$root/scenes/cornell-box.xml" -o "$root/out/cornell-box.exr" "$@"
