"""`ofera.jit.Bound`: a kernel whose arguments numba holds as one object (`Fixed`), called past the dispatcher after
its first call: the same results as the kernel called plainly, on the caller's arrays (not copies)."""

from __future__ import annotations

import numba as nb
import numpy as np
from ofera.jit import Bound, Fixed


@nb.njit
def _scaled_sum(fixed):
    """out += x * scale + offset; returns the sum of x and the row count."""
    (scale, offset), x, out = fixed.args
    total = 0.0
    for i in range(x.shape[0]):
        out[i] += x[i] * scale[0] + offset
        total += x[i]
    return total, out.shape[0]


def test_bound_calls_equal_the_plain_kernel_on_the_callers_arrays() -> None:
    scale, x, out = np.array([2.0]), np.arange(4.0), np.zeros(4)
    fixed = ((scale, 0.5), x, out)
    bound = Bound(_scaled_sum, fixed)
    assert bound.call is None
    assert bound() == (6.0, 4)
    assert bound.call is not None  # the compiled function, taken after the first call
    x += 1  # the kernel reads the caller's arrays, not copies
    assert bound() == (10.0, 4) == _scaled_sum(Fixed(fixed))[:1] + (4,)
    np.testing.assert_array_equal(out, (2 * (x - 1) + 0.5) + 2 * (2 * x + 0.5))  # three calls wrote into out
    scale[0] = -1.0
    bound()
    np.testing.assert_array_equal(out, (2 * (x - 1) + 0.5) + 2 * (2 * x + 0.5) - x + 0.5)


def test_fixed_keeps_its_tuple() -> None:
    a, b = np.zeros(3, np.float32), np.ones((2, 2), np.int64)
    held = Fixed((True, (a, b), 7)).args
    assert held[0] is True and held[2] == 7
    held[1][0][1] = 5.0
    assert a[1] == 5.0  # the same memory
