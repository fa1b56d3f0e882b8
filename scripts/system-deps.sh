#!/usr/bin/env sh
# System packages newtsim needs on Debian/Ubuntu: Python with venv and pip, and LLVM 19 for Mitsuba's
# llvm variant (LLVM 15/16 abort the process at the first ray intersection; LLVM 14 is refused).
# Installs only what is missing; needs root (or sudo) when something is missing.
set -eu
PKGS="python3 python3-venv python3-pip libllvm19"
missing=""
for p in $PKGS; do
    dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed" || missing="$missing $p"
done
# a Python that already has venv (pyenv, conda) does not need Debian's python3 packages
if python3 -c "import venv, ensurepip" 2>/dev/null; then
    missing=$(echo "$missing" | tr ' ' '\n' | grep -v '^python3' | tr '\n' ' ')
fi
missing=$(echo $missing)
[ -z "$missing" ] && { echo "system packages: all present"; exit 0; }
if ! command -v apt-get >/dev/null 2>&1; then
    echo "newtsim: please install: $missing (LLVM 17 or newer for Mitsuba; set DRJIT_LIBLLVM_PATH)" >&2
    exit 1
fi
SUDO=""
[ "$(id -u)" -ne 0 ] && SUDO="sudo"
echo "installing system packages:$missing"
$SUDO apt-get update -qq
DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq --no-install-recommends $missing
