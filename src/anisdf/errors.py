"""User-facing errors. Anything raised as :class:`AnisdfError` ends the CLI with exit code 2 and one line."""

from __future__ import annotations

from pathlib import Path


class AnisdfError(Exception):
    """An error caused by the user's input or environment (not a bug)."""


class DataError(AnisdfError):
    """A dataset file is missing, unreadable or malformed.

    The message always names the offending file: ``DataError(path, "what is wrong")``.
    """

    def __init__(self, path: str | Path, problem: str) -> None:
        self.path = Path(path)
        self.problem = problem
        super().__init__(f"{path}: {problem}")


class TrainingDiverged(AnisdfError):
    """Training produced a non-finite or exploding loss."""


def surface_vanished(step: int, pace: float = 1.0) -> TrainingDiverged:
    """The error of a run whose SDF has no zero level near any occupancy-grid cell at ``step``. ``pace``: schedule steps
    an optimiser step under a time budget; above 2 the message says how compressed the schedule was and what gives
    it more steps."""
    msg = (f"step {step}: the surface vanished (the SDF has no zero level near any occupancy-grid cell), so no ray has "
           "samples left to train on. Start again with another train.seed, or a lower optim.lr or optim.lr_variance "
           "(the NeuS sharpness growing too fast can set it off).")
    if pace > 2:
        msg += (f" This time budget ran {pace:.0f} schedule steps an optimiser step, so the levels and the sharpness "
                "moved that much faster a step: a longer --max-minutes gives them more steps (benchmarks/RESULTS.md, "
                "\"Short budgets\").")
    return TrainingDiverged(msg)
