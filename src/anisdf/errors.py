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
