#!/usr/bin/env bash
# Set up hilswarm on a Debian machine: system packages (only if missing), a virtualenv in .venv
# with hilswarm and its dev tools, and the firmware + AVR-simulator harness build.
#
#   bash scripts/setup.sh            # everything (needs root or sudo for missing apt packages)
#   bash scripts/setup.sh --no-apt   # skip system packages (you installed them yourself)
set -euo pipefail
cd "$(dirname "$0")/.."

want_apt=1
for arg in "$@"; do
  case "$arg" in
    --no-apt) want_apt=0 ;;
    -h|--help) sed -n '2,7p' "$0"; exit 0 ;;
    *) echo "setup.sh: unknown option $arg" >&2; exit 2 ;;
  esac
done

APT_PACKAGES=(python3 python3-venv python3-dev build-essential pkg-config make
              gcc-avr avr-libc binutils-avr arduino-core-avr
              simavr libsimavr-dev libsimavrparts1 libelf-dev)

if [ "$want_apt" = 1 ]; then
  missing=()
  for p in "${APT_PACKAGES[@]}"; do
    dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed" || missing+=("$p")
  done
  if [ "${#missing[@]}" -gt 0 ]; then
    echo "== installing system packages: ${missing[*]}"
    SUDO=""; [ "$(id -u)" = 0 ] || SUDO="sudo"
    $SUDO apt-get update -qq
    DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq --no-install-recommends "${missing[@]}" >/dev/null
  fi
fi

# The interpreter: Debian's own python3 (installed above; built with profile-guided and
# link-time optimisation), not whichever python3 comes first on PATH (pyenv, a self-built
# CPython). Measured on the same machine, an agent's tick costs 10-25 % less CPU on it
# (docs/running.md, Levers). PYTHON=/path/to/python3 chooses another (3.11 or newer).
PY=${PYTHON:-/usr/bin/python3}
if ! "$PY" -c 'import sys; sys.exit(sys.version_info < (3, 11))' 2>/dev/null; then
  found=$("$PY" -c 'import sys; print(sys.version.split()[0])' 2>/dev/null || echo "not found")
  echo "setup.sh: hilswarm needs Python 3.11 or newer; $PY is $found" >&2
  echo "          (set PYTHON=/path/to/python3.11 or newer)" >&2
  exit 1
fi
if [ ! -x .venv/bin/python ]; then
  echo "== creating virtualenv .venv ($("$PY" -c 'import sys; print(sys.executable, sys.version.split()[0])'))"
  "$PY" -m venv .venv
else
  made_with=$(sed -n 's/^executable = //p' .venv/pyvenv.cfg 2>/dev/null || true)
  wanted=$(readlink -f "$(command -v "$PY")")
  if [ -n "$made_with" ] && [ "$(readlink -f "$made_with")" != "$wanted" ]; then
    echo "== note: .venv runs $made_with, not $wanted; kept as it is"
    echo "   (to switch: rm -rf .venv && bash scripts/setup.sh)"
  fi
fi
echo "== installing hilswarm (editable) with dev tools"
.venv/bin/python -m pip install -q --upgrade pip >/dev/null
.venv/bin/python -m pip install -q -e ".[dev]"

if [ -f firmware/Makefile ]; then
  echo "== building firmware and simulator harness"
  make -s -C firmware all
fi
echo "== setup done: activate with 'source .venv/bin/activate'"
