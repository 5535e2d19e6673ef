#!/usr/bin/env bash
# Set up instancing on a fresh Debian 12 machine (as root) with Python 3.11:
#   1. a system libLLVM >= 19 for Dr.Jit's LLVM backend (Debian 12's default
#      LLVM 15 aborts on Mitsuba 3.9's kernels, so we install libllvm19);
#   2. a virtual environment in .venv with the package and its test tools.
# Safe to run again: each step is skipped when already done.
set -euo pipefail
cd "$(dirname "$0")"
PYTHON=${PYTHON:-python3}

have_llvm() {
    local f
    for f in /usr/lib/*/libLLVM-{19,2[0-9]}.so* /usr/lib/*/libLLVM.so.{19,2[0-9]}* \
             /usr/lib/llvm-{19,2[0-9]}/lib/libLLVM*.so*; do
        [ -e "$f" ] && return 0
    done
    return 1
}

apt_install() {
    local runner=()
    if [ "$(id -u)" -ne 0 ]; then
        command -v sudo >/dev/null || { echo "setup.sh: need root (or sudo) to apt-get install $*" >&2; exit 1; }
        runner=(sudo)
    fi
    "${runner[@]}" apt-get update -qq
    DEBIAN_FRONTEND=noninteractive "${runner[@]}" apt-get install -y -qq "$@" >/dev/null
}

if ! have_llvm; then
    echo "setup.sh: installing libllvm19 for Dr.Jit's LLVM backend"
    apt_install libllvm19
fi

if [ ! -x .venv/bin/python ]; then
    if ! "$PYTHON" -m venv .venv 2>/dev/null; then
        echo "setup.sh: installing python3-venv"
        rm -rf .venv
        apt_install python3-venv
        "$PYTHON" -m venv .venv
    fi
fi

.venv/bin/python -m pip install -q --disable-pip-version-check -e ".[test]"
echo "setup.sh: ready (.venv/bin/python, .venv/bin/instancing)"
