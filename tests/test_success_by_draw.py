"""benchmarks/success_by_draw.py's binning and its chance of a gap, on made-up episodes."""

from __future__ import annotations

import numpy as np
import pytest
from script_module import load_script


@pytest.fixture
def sbd(monkeypatch):
    return load_script("benchmarks/success_by_draw.py", monkeypatch)


def test_a_factor_that_decides_success_has_a_full_gap_and_no_chance(sbd):
    values = [float(v) for v in np.linspace(0.0, 0.3, 100)]
    passed = np.array([v < 0.15 for v in values], dtype=float)
    labels, which = sbd.bins(values)
    assert len(labels) == 4 and np.bincount(which).tolist() == [25, 25, 25, 25]
    observed = sbd.gap(which, passed, len(labels))
    assert observed == 1.0
    assert sbd.chance(which, passed, len(labels), observed, np.random.default_rng(0)) < 0.001


def test_a_factor_unrelated_to_success_is_often_matched_by_chance(sbd):
    rng = np.random.default_rng(3)
    values = [float(v) for v in rng.uniform(0, 1, 100)]
    passed = (rng.uniform(0, 1, 100) < 0.5).astype(float)
    labels, which = sbd.bins(values)
    observed = sbd.gap(which, passed, len(labels))
    assert sbd.chance(which, passed, len(labels), observed, np.random.default_rng(0)) > 0.05


def test_names_counts_and_lists_are_binned_by_value_and_by_their_smallest_element(sbd):
    assert sbd.scalar([0.9, 1.1]) == 0.9 and sbd.scalar(True) == "True"
    assert sbd.scalar("wood") == "wood" and sbd.scalar(None) == "none"
    assert sbd.scalar({"a": 1}) is None
    labels, which = sbd.bins(["wood", "tiles", "wood", "rug"])
    assert labels == ["rug", "tiles", "wood"] and which.tolist() == [2, 1, 2, 0]
    lamps = [0.0, 1.0, 2.0, 3.0] * 10  # a count: one bin a value, not quartiles
    labels, which = sbd.bins(lamps)
    assert labels == ["0.0", "1.0", "2.0", "3.0"] and which.tolist() == [0, 1, 2, 3] * 10
