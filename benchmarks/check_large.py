"""``hilswarm check`` on large swarms: how long checking N agents takes, and its peak memory.

A swarm of N simulated integrators under linear consensus on a two-way ring (graph file
``ring.edgelist``), each agent with its own initial state, is written to a temporary folder and
checked like ``hilswarm check FILE --max-agents N``. Each size runs in a fresh process (its
peak RSS is its own) and is paired with a baseline measured in the same process right before:
loading the file only (TOML, the schema, the graph), so a busy machine shows in both.

    python benchmarks/check_large.py            # N = 256, 1000, 10000
    python benchmarks/check_large.py --short    # N = 256, 1000 (well under a minute)
    python benchmarks/check_large.py --agents 5000

Each size prints one JSON line with stable keys:

    {"agents", "import_s", "load_s", "check_s", "check_cpu_s", "check_per_load", "ms_per_agent",
     "peak_rss_mb", "load_1min"}

(``import_s``: importing the checks and a 2-agent warm-up, paid once per command; ``check_s``
wall time and ``check_cpu_s`` this process's CPU time of the full check).

and the last line compares the largest size with the target (10,000 agents in < 10 s).
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

TARGET_AGENTS = 10_000
TARGET_S = 10.0


def write_swarm(folder: Path, n: int) -> Path:
    """The experiment file of ``n`` integrators on a two-way ring, beside its graph file."""
    names = [f"a{i}" for i in range(n)]
    ring = zip(names, names[1:] + names[:1], strict=True)
    (folder / "ring.edgelist").write_text("".join(f"{a} {b}\n{b} {a}\n" for a, b in ring))
    lines = [
        "[experiment]",
        'name = "large"',
        "rate_hz = 10",
        "duration_s = 1",
        "[graph]",
        'file = "ring.edgelist"',
        "[defaults]",
        'vehicle = "simulated"',
        'controller = "consensus"',
        'vehicle_params = { plant = "integrator", plant_params = { n_dims = 2 } }',
        "params = { gain = 0.5 }",
    ]
    for i, name in enumerate(names):
        lines += [f"[agents.{name}]", f"initial_state = [{float(i)}, 0.0]"]
    path = folder / "large.toml"
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")
    return path


def measure_one(n: int) -> dict[str, object]:
    """Baseline (load only) and full check of an ``n``-agent swarm, in this process."""
    start = time.perf_counter()
    from hilswarm.orchestrator.checks import check_file  # noqa: PLC0415 - timed apart
    from hilswarm.orchestrator.experiment import load_parts  # noqa: PLC0415

    with tempfile.TemporaryDirectory() as folder:
        path = write_swarm(Path(folder), n)
        check_file(write_swarm(Path(folder) / _tiny(folder), 2))  # imports vehicle, controller
        import_s = time.perf_counter() - start
        start = time.perf_counter()
        parts = load_parts(path, max_agents=n)
        load_s = time.perf_counter() - start
        if parts.problems:
            raise SystemExit(f"benchmark file has problems: {parts.problems[:3]}")
        start, cpu = time.perf_counter(), time.process_time()
        report = check_file(path, max_agents=n)
        check_s, cpu_s = time.perf_counter() - start, time.process_time() - cpu
        if not report.ok:
            raise SystemExit(f"benchmark file has problems: {report.problems[:3]}")
    return {
        "agents": n,
        "import_s": round(import_s, 3),
        "load_s": round(load_s, 3),
        "check_s": round(check_s, 3),
        "check_cpu_s": round(cpu_s, 3),
        "check_per_load": round(check_s / load_s, 2),
        "ms_per_agent": round(1000.0 * check_s / n, 3),
        "peak_rss_mb": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0, 1),
        "load_1min": round(os.getloadavg()[0], 2),
    }


def _tiny(folder: str) -> str:
    """A sub-folder for the 2-agent warm-up file."""
    Path(folder, "tiny").mkdir()
    return "tiny"


def main() -> int:
    """Run every size in its own process and print the figures."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--short", action="store_true", help="N = 256 and 1000 only (CI)")
    parser.add_argument("--agents", type=int, action="append", help="swarm size (repeatable)")
    parser.add_argument("--one", type=int, help=argparse.SUPPRESS)  # child: measure one size
    args = parser.parse_args()
    if args.one is not None:
        print(json.dumps(measure_one(args.one)))
        return 0
    sizes = args.agents or ([256, 1000] if args.short else [256, 1000, TARGET_AGENTS])
    print(f"uptime load (1, 5, 15 min): {', '.join(f'{v:.2f}' for v in os.getloadavg())}")
    results = []
    for n in sizes:
        child = subprocess.run(
            [sys.executable, __file__, "--one", str(n)],
            capture_output=True,
            text=True,
            check=False,
            timeout=600,
        )
        if child.returncode != 0:
            print(child.stdout + child.stderr, file=sys.stderr)
            return 1
        result = json.loads(child.stdout.strip().splitlines()[-1])
        results.append(result)
        print(json.dumps(result))
        print(
            f"{n:>6} agents: load {result['load_s']:.2f} s (baseline), check "
            f"{result['check_s']:.2f} s (cpu {result['check_cpu_s']:.2f} s) = "
            f"{result['check_per_load']:.1f} x load, "
            f"{result['ms_per_agent']:.2f} ms/agent, peak {result['peak_rss_mb']:.0f} MB"
        )
    largest = max(results, key=lambda r: int(r["agents"]))
    n, seconds = int(largest["agents"]), float(largest["check_cpu_s"])
    projected = seconds * TARGET_AGENTS / n
    verdict = "met" if projected < TARGET_S else "missed"
    print(
        f"target {TARGET_AGENTS} agents in < {TARGET_S:g} s: {verdict} "
        f"({n} agents in {seconds:.2f} s of CPU"
        + (f", {projected:.1f} s scaled linearly" if n != TARGET_AGENTS else "")
        + f"; load {largest['load_1min']})"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
