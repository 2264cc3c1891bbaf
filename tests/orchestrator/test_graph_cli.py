"""``hilswarm graph --json``: its keys are stable and documented, and a reader that closes the
pipe early (``| head -1``) gets no traceback."""

from __future__ import annotations

import json
import re
import subprocess
import sys
from pathlib import Path

import pytest
from hilswarm.orchestrator.cli import BROKEN_PIPE, main

REPO = Path(__file__).resolve().parents[2]
DOCS = REPO / "docs" / "experiments.md"

#: The keys of ``hilswarm graph --json``, in order: scripts read them (docs/experiments.md,
#: "Graph facts"). Add keys at the end; never rename or remove one.
JSON_KEYS = (
    "names",
    "adjacency",
    "n_edges",
    "symmetric",
    "weakly_connected",
    "strongly_connected",
    "has_spanning_tree",
    "roots",
    "leaders",
    "isolated",
    "in_degree",
    "out_degree",
    "algebraic_connectivity",
    "consensus_rate",
    "components",
)


def write_ring(folder: Path, n: int) -> Path:
    """An experiment of ``n`` simulated integrators on a two-way ring (graph file)."""
    names = [f"a{i}" for i in range(n)]
    ring = zip(names, names[1:] + names[:1], strict=True)
    (folder / "ring.edgelist").write_text("".join(f"{a} {b}\n{b} {a}\n" for a, b in ring))
    lines = [
        "[experiment]",
        'name = "ring"',
        "rate_hz = 10",
        "duration_s = 1",
        "[graph]",
        'file = "ring.edgelist"',
        "[defaults]",
        'vehicle = "simulated"',
        'controller = "consensus"',
        'vehicle_params = { plant = "integrator", plant_params = { n_dims = 1 } }',
    ]
    for i, name in enumerate(names):
        lines += [f"[agents.{name}]", f"initial_state = [{float(i)}]"]
    path = folder / "ring.toml"
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")
    return path


def test_graph_json_keys_are_stable_and_documented(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["graph", str(write_ring(tmp_path, 4)), "--json"]) == 0
    data = json.loads(capsys.readouterr().out)
    assert tuple(data) == JSON_KEYS
    assert data["names"] == ["a0", "a1", "a2", "a3"] and data["n_edges"] == 8
    assert data["in_degree"] == {"a0": 2, "a1": 2, "a2": 2, "a3": 2}
    assert data["components"] == [["a0", "a1", "a2", "a3"]]
    assert data["algebraic_connectivity"] == pytest.approx(2.0)  # 2(1 - cos(2 pi / 4))
    text = DOCS.read_text(encoding="utf-8")
    section = text[text.index("## Graph facts") :]
    section = section[: section.index("\n## ", 1)]
    documented = re.findall(r"^\| `(\w+)` \|", section, flags=re.MULTILINE)
    assert tuple(documented) == JSON_KEYS, documented


def test_graph_json_into_a_pipe_closed_early_prints_no_traceback(tmp_path: Path) -> None:
    """``hilswarm graph x.toml --json | head -1``: a real pipe whose reader closes it after the
    first line while the command still writes (400 agents: over 1 MB of JSON, more than a
    pipe holds, so the writer is blocked when the pipe closes)."""
    experiment = write_ring(tmp_path, 400)
    process = subprocess.Popen(
        [sys.executable, "-m", "hilswarm.orchestrator.cli", "graph", str(experiment), "--json",
         "--max-agents", "400"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, cwd=tmp_path,
    )  # fmt: skip
    try:
        assert process.stdout is not None
        first = process.stdout.readline()
        process.stdout.close()  # what `head -1` does
        _, err = process.communicate(timeout=120)
    finally:
        if process.poll() is None:
            process.kill()
            process.wait(10)
    assert first == b"{\n"
    stderr = err.decode(errors="replace")
    assert "Traceback" not in stderr and "BrokenPipeError" not in stderr, stderr
    assert process.returncode == BROKEN_PIPE, (process.returncode, stderr)
