"""implicit_cloth.rowwise against numpy's own axis-1 reductions (the same results exactly)."""

import numpy as np
import pytest

from implicit_cloth.rowwise import all1, max1, min1


@pytest.mark.parametrize("m", [1, 2, 3, 4])
def test_min_max_equal_numpys_with_nan(m):
    rng = np.random.default_rng(m)
    a = rng.standard_normal((500, m, 3))
    a[rng.random(a.shape) < 0.01] = np.nan
    np.testing.assert_array_equal(min1(a), a.min(axis=1))
    np.testing.assert_array_equal(max1(a), a.max(axis=1))
    b = a[..., 0]                                     # (K, m)
    np.testing.assert_array_equal(min1(b), b.min(axis=1))


@pytest.mark.parametrize("m", [1, 2, 3])
def test_all_equals_numpys(m):
    b = np.random.default_rng(7).random((400, m)) < 0.6
    np.testing.assert_array_equal(all1(b), np.all(b, axis=1))


def test_inputs_untouched_and_empty_axis_refused():
    a = np.arange(12.0).reshape(2, 2, 3)
    before = a.copy()
    out = min1(a)
    out[:] = -1.0
    np.testing.assert_array_equal(a, before)
    with pytest.raises(ValueError, match="zero-size"):
        min1(np.zeros((3, 0, 3)))
