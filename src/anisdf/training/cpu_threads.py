"""CPU thread count chosen by measurement while a time-budgeted run trains.

On a CPU that another process shares, torch's default of one thread per core is the slowest choice: every parallel
region waits for the thread whose core is taken (on 2 cores with one kept busy, cpu-quick ran 433 steps in 10
minutes against 1346 on the quiet machine). :class:`ThreadTuner` times a few steps at each candidate count, keeps the
fastest (samples per second), and measures again every ``every`` steps, since other programs come and go. It is
used only under a time budget, whose schedule already follows the clock: step-based runs keep one thread count and
stay bit-exact.
"""

from __future__ import annotations

import logging
from collections.abc import Callable

import torch

log = logging.getLogger("anisdf")


class ThreadTuner:
    """Cycle: ``probe`` steps at each candidate thread count, then ``every`` steps at the fastest one."""

    def __init__(self, max_threads: int, probe: int = 8, every: int = 200, warmup: int = 20,
                 set_threads: Callable[[int], None] = torch.set_num_threads) -> None:
        self.candidates = sorted({max_threads, max(1, max_threads // 2), 1}, reverse=True) if max_threads > 1 else []
        self.probe, self.every, self.warmup = probe, every, warmup
        self.set_threads = set_threads
        self.current = max_threads
        self._rates: dict[int, list[float]] = {}
        self._probing = 0  # index into candidates while probing, -1 while exploiting
        self._count = 0
        self._skip = True  # the first step after a switch pays for waking threads up: not timed
        self._steps = 0

    @property
    def enabled(self) -> bool:
        return bool(self.candidates)

    def _use(self, n: int) -> None:
        if n != self.current:
            self.set_threads(n)
            self.current = n
            self._skip = True

    def observe(self, seconds: float, samples: int) -> None:
        """Record one training step (its wall time and the samples it processed); switch threads when due."""
        if not self.enabled:
            return
        self._steps += 1
        if self._steps <= self.warmup:
            return
        if self._skip:
            self._skip = False
            return
        self._count += 1
        if self._probing >= 0:
            n = self.candidates[self._probing]
            self._rates.setdefault(n, []).append(samples / max(seconds, 1e-9))
            if self._count >= self.probe:
                self._count = 0
                self._probing += 1
                if self._probing < len(self.candidates):
                    self._use(self.candidates[self._probing])
                else:
                    self._probing = -1
                    med = {k: sorted(v)[len(v) // 2] for k, v in self._rates.items()}
                    best = max(med, key=med.get)
                    log.debug("cpu threads: %s samples/s -> %d threads",
                              {k: round(v) for k, v in med.items()}, best)
                    self._use(best)
                    self._rates.clear()
        elif self._count >= self.every:
            self._count = 0
            self._probing = 0
            self._use(self.candidates[0])
