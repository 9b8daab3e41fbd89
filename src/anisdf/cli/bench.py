"""``anisdf bench``: speed benchmark (encoding, training step, memory, time to quality)."""

from __future__ import annotations

from anisdf.benchmarks.speed import BenchOptions

NAME = "bench"

Options = BenchOptions


def run(opts: Options) -> int:
    from anisdf.benchmarks.speed import run_bench

    run_bench(opts)
    return 0
