"""The service's rolling timings: what status and the benchmarks read back."""

from service.stats import Rolling


def test_rolling_keeps_the_newest_samples_in_order():
    r = Rolling(size=3)
    assert r.latest() is None and r.values() == [] and r.summary()["n"] == 0
    for v in (0.001, 0.002, 0.003, 0.004):
        r.add(v)
    assert r.values() == [0.002, 0.003, 0.004]  # the oldest fell out
    assert r.values(last=2) == [0.003, 0.004]
    assert r.latest() == 0.004
    s = r.summary(last=2)  # ms by default
    assert s["n"] == 2 and s["max"] == 4.0 and s["p50"] == 3.5
