"""The numba intrinsics the fast paths share (`ofera.jit`), against plain Python and numpy: half-float conversions and
the atomic counter the threaded delta kernel's blocks are claimed through."""

from __future__ import annotations

import numba as nb
import numpy as np
from ofera.jit import atomic_add, f16_bits_to_f32, f32_to_f16_bits


@nb.njit
def _halves(x, bits, back):
    for i in range(x.shape[0]):
        bits[i] = f32_to_f16_bits(x[i])
        back[i] = f16_bits_to_f32(bits[i])


def test_half_conversions_are_numpys() -> None:
    x = np.array([0.0, -0.0, 1.0, 1e-8, 65504.0, 65520.0, 7e4, np.inf, -np.inf, 0.1, 3.14159, -2.5e-5], np.float32)
    bits, back = np.zeros(x.size, np.uint16), np.zeros(x.size, np.float32)
    _halves(x, bits, back)
    with np.errstate(over="ignore"):  # (7e4 and the infinities: numpy warns of what it rounds to infinity)
        half = x.astype(np.float16)
    np.testing.assert_array_equal(bits, half.view(np.uint16))
    np.testing.assert_array_equal(back, half.astype(np.float32))


@nb.njit(parallel=True)
def _claims(counter, threads, per_thread, seen):
    """Each of ``threads`` loop iterations claims ``per_thread`` numbers; seen[k] counts the claims that got k."""
    for _t in nb.prange(threads):
        for _ in range(per_thread):
            k = atomic_add(counter, 1, 1)
            seen[k] += 1  # (each k is claimed once: no two iterations write one slot)


def test_atomic_add_gives_every_claim_its_own_number() -> None:
    """Concurrent claims on numba's threads: the counter ends at the total, each value before an add is returned to
    exactly one claim (a plain += would lose some), and the other elements are untouched."""
    counter = np.array([7, 0, -3], np.int64)
    seen = np.zeros(4 * 20000, np.int64)
    _claims(counter, 4, 20000, seen)
    assert counter.tolist() == [7, 80000, -3]
    assert (seen == 1).all()
