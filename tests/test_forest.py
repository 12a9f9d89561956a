"""Parent-forest walks (handanno_core.forest) on a small hand-made forest."""

import numpy as np
import pytest

from handanno_core import forest

#      0 (ref)          5 (ref)
#     / \                |
#    1   3               6
#    |   |
#    2   4 -- 7
PARENT = np.array([-1, 0, 1, 0, 3, -1, 5, 4])


def test_roots_depths_and_validate():
    np.testing.assert_array_equal(forest.roots(PARENT), [0, 0, 0, 0, 0, 5, 5, 0])
    np.testing.assert_array_equal(forest.depths(PARENT), [0, 1, 2, 1, 2, 0, 1, 3])
    forest.validate(PARENT, np.array([0, 5]))
    with pytest.raises(ValueError, match="exactly at the references"):
        forest.validate(PARENT, np.array([0]))
    cyc = PARENT.copy()
    cyc[1], cyc[2] = 2, 1
    with pytest.raises(ValueError, match="cycle"):
        forest.roots(cyc)


def test_descendants_and_breadth_first_order():
    np.testing.assert_array_equal(forest.descendants(PARENT, [3]), [3, 4, 7])
    np.testing.assert_array_equal(forest.descendants(PARENT, [1, 5]), [1, 2, 5, 6])
    order = forest.propagation_order(PARENT, [0, 5])
    np.testing.assert_array_equal(order[0], [1, 3, 2, 4, 7])
    np.testing.assert_array_equal(order[1], [6])
    kids, start = forest.children_csr(PARENT)
    np.testing.assert_array_equal(kids[start[0] : start[1]], [1, 3])
