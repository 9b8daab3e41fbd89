"""The CPU thread count under a time budget is chosen by measured samples per second."""

from __future__ import annotations

from anisdf.training.cpu_threads import ThreadTuner


def _machine(rates: dict[int, float]):
    """A fake CPU whose throughput depends on the thread count (a busy core makes 2 threads slower than 1)."""
    calls: list[int] = []
    tuner = ThreadTuner(2, probe=4, every=10, warmup=3, set_threads=calls.append)

    def step(n: int = 1) -> None:
        for _ in range(n):
            tuner.observe(1.0, int(rates[tuner.current]))
    return tuner, calls, step


def test_a_busy_core_makes_the_tuner_drop_to_one_thread_and_it_measures_again_later():
    rates = {2: 20_000, 1: 45_000}
    tuner, calls, step = _machine(rates)
    step(3 + 1 + 4)  # warm-up, the untimed first step, the current count's rate: then the probe switches
    assert calls == [1]
    step(1 + 4)  # untimed switch step, 4 steps at one thread: the faster, kept
    assert tuner.current == 1 and calls == [1] and tuner.interval == 10
    step(9)
    assert calls == [1]
    step(1)  # the 10th step at one thread: two threads are timed again
    assert tuner.current == 2 and calls == [1, 2]
    step(1 + 2)  # two steps are enough to see that two threads are still far slower: back to one
    assert tuner.current == 1 and calls == [1, 2, 1]
    assert tuner.interval == 20  # a probe that confirmed the choice: the next one comes later
    rates[2] = 90_000  # the other program ended
    step(1 + 20 + 1 + 4)
    assert tuner.current == 2 and calls == [1, 2, 1, 2] and tuner.interval == 10


def test_a_quiet_machine_keeps_all_threads_and_probes_less_and_less_often():
    tuner, calls, step = _machine({2: 60_000, 1: 35_000})
    step(3 + 1 + 4 + 1 + 2)  # one thread dropped after two steps
    assert tuner.current == 2 and calls == [1, 2]
    intervals = []
    for _ in range(5):
        step(1 + tuner.interval + 1 + 2)
        intervals.append(tuner.interval)
    assert tuner.current == 2 and intervals == [40, 80, 80, 80, 80]  # doubling, up to 8x the first


def test_one_core_has_nothing_to_tune():
    calls: list[int] = []
    tuner = ThreadTuner(1, set_threads=calls.append)
    for _ in range(100):
        tuner.observe(1.0, 1000)
    assert not tuner.enabled and calls == []
