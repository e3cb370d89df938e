#!/usr/bin/env bash
# Installs what bdpt_jit needs, once: a system libLLVM >= 16 (Dr.Jit's LLVM backend aborts
# with Debian 12's default LLVM 15) and a virtual environment at .venv with the package.
# Quick when everything is already there. Sourced by scripts/render.sh and scripts/test.sh.
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$root"

have_llvm() {   # libLLVM-16.so ... or libLLVM.so.19.1 ...
    ldconfig -p 2>/dev/null | grep -Eq 'libLLVM(-|\.so\.)(1[6-9]|[2-9][0-9])'
}
if [ -z "${DRJIT_LIBLLVM_PATH:-}" ] && ! have_llvm; then
    echo "bootstrap: installing libllvm19 (Dr.Jit's LLVM backend needs libLLVM >= 16)" >&2
    SUDO=""; [ "$(id -u)" -ne 0 ] && SUDO="sudo"
    export DEBIAN_FRONTEND=noninteractive
    $SUDO apt-get update -qq >/dev/null
    $SUDO apt-get install -y -qq libllvm19 >/dev/null
fi

stamp=".venv/.bdpt_jit-installed"
if [ ! -x .venv/bin/python ]; then
    echo "bootstrap: creating .venv" >&2
    python3 -m venv .venv
fi
if [ ! -f "$stamp" ] || [ pyproject.toml -nt "$stamp" ]; then
    echo "bootstrap: installing bdpt_jit and its dependencies into .venv" >&2
    .venv/bin/python -m pip install -q --upgrade pip >/dev/null
    .venv/bin/python -m pip install -q -e ".[test]"
    touch "$stamp"
fi
