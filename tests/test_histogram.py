import numpy as np
import pytest

from jetbot_rt.runtime.histogram import Histogram


def test_percentiles_within_one_percent_of_numpy():
    rng = np.random.default_rng(0)
    values = rng.lognormal(mean=2.5, sigma=0.6, size=20000)  # tick times around 12 ms
    histogram = Histogram()
    for value in values:
        histogram.add(float(value))
    for q in (50, 90, 99):
        exact = float(np.percentile(values, q))
        assert histogram.percentile(q) == pytest.approx(exact, rel=0.011)
    assert histogram.max == pytest.approx(values.max())
    assert histogram.count == values.size


def test_empty_tiny_and_huge_values():
    histogram = Histogram()
    assert np.isnan(histogram.percentile(50))
    histogram.add(0.0)
    histogram.add(-1.0)  # a tick that started early cannot happen, but must not break
    histogram.add(1e9)
    assert histogram.percentile(100) == 1e9
    assert histogram.percentile(1) <= 1e-3


def test_memory_is_constant():
    histogram = Histogram()
    size = histogram.counts.nbytes
    for value in np.linspace(0.01, 500, 50000):
        histogram.add(float(value))
    assert histogram.counts.nbytes == size < 20_000
