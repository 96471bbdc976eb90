"""The grouped numpy reductions behind the static averaging equal the per-group loops they
replace, to the last bit (identify/grouping.py; benchmarks/bench_identify.py times them)."""

import numpy as np

from elastocal.identify.grouping import combine, first_seen, group_sum, sums_per_group


def test_first_seen_numbers_values_in_order_of_first_appearance():
    values = np.array(["P3", "P1", "P3", "P2", "P1"])
    code, first = first_seen(values)
    assert list(values[first]) == list(dict.fromkeys(values)) == ["P3", "P1", "P2"]
    assert code.tolist() == [0, 1, 0, 2, 1]
    key_code, _ = first_seen(combine(code, np.array([0, 0, 1, 0, 0])))
    assert key_code.tolist() == [0, 1, 2, 3, 1]


def test_grouped_sums_equal_the_loops_bitwise():
    rng = np.random.default_rng(3)
    sizes = rng.integers(1, 7, 200)
    values = rng.normal(0, 1e-4, (int(sizes.sum()), 3))
    starts = np.concatenate([[0], np.cumsum(sizes)[:-1]])
    loop = [float((values[s:s + k] ** 2).sum()) for s, k in zip(starts, sizes)]
    assert sums_per_group(values ** 2, sizes).tolist() == loop
    code = np.repeat(np.arange(len(sizes)), sizes)
    assert np.array_equal(group_sum(code, values, len(sizes)),
                          np.array([values[s:s + k].sum(axis=0) for s, k in zip(starts, sizes)]))
