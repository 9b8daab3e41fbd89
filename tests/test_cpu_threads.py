"""The CPU thread count under a time budget is chosen by measured samples per second."""

from __future__ import annotations

from anisdf.training.cpu_threads import ThreadTuner


def _machine(rates: dict[int, float]):
    """A fake CPU whose throughput depends on the thread count (a busy core makes 2 threads slower than 1)."""
    calls: list[int] = []
    tuner = ThreadTuner(2, probe=4, every=10, warmup=3, set_threads=calls.append)
    return tuner, calls, lambda: tuner.observe(1.0, int(rates[tuner.current]))


def test_a_busy_core_makes_the_tuner_drop_to_one_thread_and_it_measures_again_later():
    tuner, calls, step = _machine({2: 20_000, 1: 45_000})
    for _ in range(3 + 4 + 1 + 4):  # warm-up, probe 2 threads, untimed switch step, probe 1 thread
        step()
    assert tuner.current == 1 and calls == [1]
    for _ in range(1 + 10):  # untimed switch step, exploit, then the next probe starts from the largest count again
        step()
    assert tuner.current == 2 and calls == [1, 2]


def test_a_quiet_machine_keeps_all_threads():
    tuner, calls, step = _machine({2: 60_000, 1: 35_000})
    for _ in range(3 + 4 + 1 + 4 + 1):
        step()
    assert tuner.current == 2 and calls == [1, 2]


def test_one_core_has_nothing_to_tune():
    calls: list[int] = []
    tuner = ThreadTuner(1, set_threads=calls.append)
    for _ in range(100):
        tuner.observe(1.0, 1000)
    assert not tuner.enabled and calls == []
