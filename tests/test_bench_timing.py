"""benchmarks.timing.median_seconds: warm-up calls are not counted, between() runs after every call."""
from benchmarks import timing


def test_median_of_the_counted_calls_with_warmup_and_between(monkeypatch):
    clock = {"t": 0.0}
    durations = iter([5.0, 1.0, 3.0, 2.0])        # the first call is the warm-up
    calls, resets = [], []

    def run():
        calls.append(len(resets))                 # how many between() calls preceded this one
        clock["t"] += next(durations)

    monkeypatch.setattr(timing.time, "perf_counter", lambda: clock["t"])
    median = timing.median_seconds(run, repeats=3, warmup=1, between=lambda: resets.append(1))
    assert calls == [0, 1, 2, 3] and len(resets) == 4
    assert median == 2.0                          # median of 1, 3, 2: the 5 s warm-up does not count
