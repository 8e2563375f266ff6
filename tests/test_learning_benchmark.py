"""The learning benchmark's summary table: medians and ratios with pools that did not get there."""

import importlib.util
import os

SCRIPT = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "benchmarks", "learning.py")
spec = importlib.util.spec_from_file_location("learning_benchmark", SCRIPT)
learning = importlib.util.module_from_spec(spec)
spec.loader.exec_module(learning)


def _pool(size, iterations, steps=None, ran=60, error=None):
    out = {"size": size, "reached": iterations is not None, "iterations": iterations,
           "env_steps": steps if iterations is not None else None,
           "ran_iterations": iterations if iterations is not None else ran}
    return out | ({"error": error} if error else {})


def test_medians_and_ratios_against_the_first_size():
    results = [_pool(2, 45, 9_000_000), _pool(2, 24, 5_000_000), _pool(2, 16, 3_000_000),
               _pool(8, 10, 8_000_000), _pool(8, 7, 6_000_000), _pool(8, 14, 10_000_000)]
    assert learning.summary(results, [2, 8]) == [(2, "24", "1.00x", "5000000"), (8, "10", "2.40x", "8000000")]


def test_pools_that_did_not_get_there_give_bounds():
    results = [_pool(2, None), _pool(2, None), _pool(8, None), _pool(8, None),
               _pool(16, 24, 9_219_000), _pool(16, 31, 11_813_000)]
    # the 2-member median is more than 60, so 16 members needed more than 60 / 27.5 times fewer
    assert learning.summary(results, [2, 8, 16]) == [
        (2, ">60", "1.00x", "-"), (8, ">60", "-", "-"), (16, "27.5", ">2.18x", "10516000")]
    # half of an even number short of it: the median is more than (24 + 60) / 2
    rows = learning.summary([_pool(2, 10, 1), _pool(2, 12, 1), _pool(8, 24, 5), _pool(8, None)], [2, 8])
    assert rows == [(2, "11", "1.00x", "1"), (8, ">42", "<0.26x", "-")]
    # one of three short of it still has an exact median
    assert learning.summary([_pool(2, None), _pool(2, 20, 4), _pool(2, 30, 6)], [2]) == [(2, "30", "1.00x", "6")]


def test_a_pool_that_ran_fewer_iterations_bounds_with_what_it_ran_and_errors_are_left_out():
    results = [_pool(2, None, ran=11), _pool(2, None, ran=40), _pool(2, 50, 7, error=None),
               _pool(8, None, ran=3, error="Traceback ...")]
    assert learning.summary(results, [2, 8]) == [(2, ">40", "1.00x", "-"), (8, "-", "-", "-")]
    # nothing left of the first size: nothing to compare with
    assert learning.summary([_pool(2, None, error="x"), _pool(8, 5, 1)], [2, 8]) == [(2, "-", "-", "-"),
                                                                                     (8, "5", "-", "1")]
