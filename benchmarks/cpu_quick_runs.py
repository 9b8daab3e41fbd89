"""What the capture benchmarks share: train a cpu-quick run unless it is done, then score it under several eval
protocols, each score kept beside the run so that a second call reuses it."""

from __future__ import annotations

import json
import shutil
from pathlib import Path
from typing import Any

from anisdf.run_dir import RunDir


def train_and_score(data: Path, out: Path, steps: int, overrides: list[str],
                    evals: dict[str, dict[str, Any]], minutes: float | None = None) -> dict[str, dict]:
    """Train ``out`` from ``data`` for ``steps`` cpu-quick steps with ``overrides`` (unless it is done; with
    ``minutes``, the ``steps`` schedule laid on that time budget), then for each ``name: eval options`` of ``evals``
    run ``anisdf eval`` on the test split, kept as ``RUN/eval_<name>.json``. Returns ``{name: eval.json}``."""
    from anisdf.tasks.evaluate import evaluate
    from anisdf.tasks.train import train

    rd = RunDir(out)
    if rd.status() != "done":
        if out.exists():
            shutil.rmtree(out)
        train(data, out, preset="cpu-quick", max_steps=steps, max_minutes=minutes, overrides=overrides, progress=False)
    scores = {}
    for name, options in evals.items():
        kept = out / f"eval_{name}.json"
        if not kept.is_file():
            evaluate(out, split="test", progress=False, **options)
            shutil.copyfile(rd.eval_json, kept)
        scores[name] = json.loads(kept.read_text())
    return scores
