"""Append throughput of a telemetry Channel versus a naive ``np.append`` loop.

The thesis' DynamicArray exists because growing a matrix one row at a time copies the whole
history on every append (O(n^2) in total); Channel doubles its capacity instead (amortised
O(1)). Both run in this process on the same rows; the script prints rows/s of each and the
ratio.

    python benchmarks/telemetry_append.py            # 50 000 rows
    python benchmarks/telemetry_append.py --short    # CI size, a few seconds
"""

from __future__ import annotations

import argparse
import time

import numpy as np
from hilswarm.agents.telemetry import Channel

N_FIELDS = 6


def channel_rate(rows: np.ndarray) -> float:
    """Rows per second appended to a Channel (wall time, monotonic clock)."""
    channel = Channel("bench", [f"f{i}" for i in range(rows.shape[1])])
    start = time.perf_counter()
    for k, row in enumerate(rows):
        channel.append(k, 0.01 * k, row)
    elapsed = time.perf_counter() - start
    if len(channel) != rows.shape[0]:
        raise RuntimeError("channel lost rows")
    return rows.shape[0] / elapsed


def naive_rate(rows: np.ndarray) -> float:
    """Rows per second with ``np.append`` growing the arrays one row at a time."""
    k_values = np.empty(0, dtype=np.int64)
    t_values = np.empty(0)
    values = np.empty((0, rows.shape[1]))
    start = time.perf_counter()
    for k, row in enumerate(rows):
        k_values = np.append(k_values, k)
        t_values = np.append(t_values, 0.01 * k)
        values = np.append(values, row[np.newaxis, :], axis=0)
    elapsed = time.perf_counter() - start
    if values.shape[0] != rows.shape[0]:
        raise RuntimeError("naive loop lost rows")
    return rows.shape[0] / elapsed


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description="Channel.append vs np.append throughput")
    parser.add_argument("--short", action="store_true", help="CI-sized run (< 20 s)")
    parser.add_argument("--rows", type=int, default=None, help="rows to append")
    args = parser.parse_args(argv)
    n_rows = args.rows if args.rows is not None else (20_000 if args.short else 50_000)
    rows = np.random.default_rng(0).normal(size=(n_rows, N_FIELDS))
    channel = channel_rate(rows)
    naive = naive_rate(rows)
    print(f"rows appended          : {n_rows} x {N_FIELDS} fields")
    print(f"Channel.append         : {channel:12,.0f} rows/s")
    print(f"np.append loop (naive) : {naive:12,.0f} rows/s")
    print(f"ratio Channel / naive  : {channel / naive:12.1f} x")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
