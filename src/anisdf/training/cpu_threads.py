"""CPU thread count chosen by measurement while a time-budgeted run trains.

On a CPU that another process shares, torch's default of one thread per core is the slowest choice: every parallel
region waits for the thread whose core is taken (on 2 cores with one kept busy, cpu-quick ran 433 steps in 10
minutes against 1346 on the quiet machine). :class:`ThreadTuner` keeps the thread count with the most samples per
second: it times the other counts now and then against the current one's recent rate, drops a count after two steps
when it is clearly slower, and probes less often while the probes keep confirming its choice (other programs come and
go; a probe of the wrong count costs steps). It is used only under a time budget, whose schedule already follows the
clock: step-based runs keep one thread count and stay bit-exact.
"""

from __future__ import annotations

import logging
from collections import deque
from collections.abc import Callable, Sequence

import torch

log = logging.getLogger("anisdf")


class ThreadTuner:
    """Run at ``current`` threads; after ``warmup`` steps and then every ``interval`` steps, time each other candidate
    for ``probe`` steps (2 if even its best is under ``abort`` of the current count's recent median) and keep the
    fastest. ``interval`` starts at ``every`` and doubles, up to ``max_backoff`` times, while probes keep the count."""

    def __init__(self, max_threads: int, probe: int = 8, every: int = 200, warmup: int = 20,
                 set_threads: Callable[[int], None] = torch.set_num_threads, abort: float = 0.67,
                 max_backoff: int = 8) -> None:
        self.candidates = sorted({max_threads, max(1, max_threads // 2), 1}, reverse=True) if max_threads > 1 else []
        self.probe, self.every, self.warmup, self.abort = probe, every, warmup, abort
        self.max_interval = every * max_backoff
        self.set_threads = set_threads
        self.current = max_threads
        self.interval = every
        self._next = probe  # exploit steps before the next probe: the first comes once the current rate is known
        self._recent: deque[float] = deque(maxlen=probe)  # rates of the last exploit steps
        self._queue: list[int] = []  # candidates still to time in this probe
        self._rates: dict[int, list[float]] = {}
        self._home = max_threads  # the count the probe started from
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
        rate = samples / max(seconds, 1e-9)
        if not self._queue:  # exploiting
            self._recent.append(rate)
            self._count += 1
            if self._count >= self._next and len(self._recent) == self.probe:
                self._count, self._home, self._rates = 0, self.current, {}
                self._queue = [n for n in self.candidates if n != self.current]
                self._use(self._queue[0])
            return
        rates = self._rates.setdefault(self._queue[0], [])
        rates.append(rate)
        ref = _median(self._recent)
        if len(rates) < self.probe and (len(rates) < 2 or max(rates) >= self.abort * ref):
            return
        self._queue.pop(0)
        if self._queue:
            self._use(self._queue[0])
            return
        med = {n: _median(v) for n, v in self._rates.items()} | {self._home: ref}
        best = max(med, key=med.__getitem__)
        log.debug("cpu threads: %s samples/s -> %d threads", {k: round(v) for k, v in med.items()}, best)
        if best == self._home:  # confirmed: probe less often
            self.interval = min(2 * self.interval, self.max_interval)
        else:
            self.interval = self.every
            self._recent.clear()
        self._next = self.interval
        self._use(best)


def _median(values: Sequence[float]) -> float:
    return sorted(values)[len(values) // 2]
