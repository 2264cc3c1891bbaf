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

PY=${PYTHON:-python3}
if [ ! -x .venv/bin/python ]; then
  echo "== creating virtualenv .venv"
  "$PY" -m venv .venv
fi
echo "== installing hilswarm (editable) with dev tools"
.venv/bin/python -m pip install -q --upgrade pip >/dev/null
.venv/bin/python -m pip install -q -e ".[dev]"

if [ -f firmware/Makefile ]; then
  echo "== building firmware and simulator harness"
  make -s -C firmware all
fi
echo "== setup done: activate with 'source .venv/bin/activate'"
