#!/usr/bin/env bash
# Set up everything (scripts/setup.sh) and run the whole test suite, then the short benchmarks.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh "$@"
echo "== ruff"
.venv/bin/ruff check .
.venv/bin/ruff format --check .
echo "== pytest"
.venv/bin/python -m pytest -q
echo "== short benchmarks"
for b in benchmarks/*.py; do
  [ -e "$b" ] || continue
  echo "-- $b --short"
  timeout 600 .venv/bin/python "$b" --short
done
echo "-- benchmarks/mocap_latency.py --short --spread"
timeout 600 .venv/bin/python benchmarks/mocap_latency.py --short --spread
