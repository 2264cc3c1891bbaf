#!/usr/bin/env bash
# Set up hilswarm (scripts/setup.sh) and run the main job: a simulated swarm on the embedded bus,
# no hardware. Writes out/lead_follow.mcap (open it in Foxglove) and PNG plots in out/lead_follow/.
#
#   bash scripts/demo.sh [EXPERIMENT.toml]      # default graphs/lead_follow.toml
set -euo pipefail
cd "$(dirname "$0")/.."
experiment=${1:-graphs/lead_follow.toml}
name=$(basename "$experiment" .toml)
bash scripts/setup.sh
mkdir -p out
.venv/bin/hilswarm check "$experiment"
# --force: the demo replaces its own recording of an earlier demo run (hilswarm run never does
# that on its own)
.venv/bin/hilswarm run "$experiment" --out "out/$name.mcap" --force
.venv/bin/hilswarm plot "out/$name.mcap" --out "out/$name"
echo "== recording: out/$name.mcap   plots: out/$name/"
