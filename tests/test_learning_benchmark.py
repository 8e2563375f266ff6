"""The learning benchmark's summary table: medians and ratios with pools that did not get there."""

import importlib.util
import os

SCRIPT = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "benchmarks", "learning.py")
spec = importlib.util.spec_from_file_location("learning_benchmark", SCRIPT)
learning = importlib.util.module_from_spec(spec)
spec.loader.exec_module(learning)


def _pool(size, iterations, steps=None):
    return {"size": size, "reached": iterations is not None, "iterations": iterations,
            "env_steps": steps if iterations is not None else None}


def test_medians_and_ratios_against_the_first_size():
    results = [_pool(2, 45, 900), _pool(2, 24, 500), _pool(2, 16, 300),
               _pool(8, 10, 800), _pool(8, 7, 600), _pool(8, 14, 1000)]
    assert learning.summary(results, [2, 8], 60) == [(2, "24", "1.00x", "500"), (8, "10", "2.40x", "800")]


def test_pools_that_did_not_get_there():
    results = [_pool(2, None), _pool(2, None), _pool(8, None), _pool(8, None), _pool(16, 24, 9), _pool(16, 31, 12)]
    rows = learning.summary(results, [2, 8, 16], 60)
    # two seeds that never got there: no number, and ratios become lower bounds or nothing
    assert rows == [(2, ">60", "-", "-"), (8, ">60", "-", "-"), (16, "27.5", ">2.18x", "10.5")]
    # one of three seeds short of it still has a median
    rows = learning.summary([_pool(2, None), _pool(2, 20, 4), _pool(2, 30, 6)], [2], 60)
    assert rows == [(2, "30", "1.00x", "6")]
