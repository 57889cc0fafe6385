"""Run a block with one BLAS thread.

Data generation does many small matrix products. With OpenBLAS's default thread pool they get much
slower, not faster, on a shared machine (threads spin waiting for cores that other processes hold):
measured here 48 s single-threaded against 290 s with the pool, for the same benchmark. Uses
threadpoolctl when it is installed, else OpenBLAS's own setter through ctypes (Linux), else nothing.
"""

from __future__ import annotations

import ctypes
import re
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

_SYMBOLS = (
    ("scipy_openblas_set_num_threads64_", "scipy_openblas_get_num_threads64_"),
    ("scipy_openblas_set_num_threads", "scipy_openblas_get_num_threads"),
    ("openblas_set_num_threads64_", "openblas_get_num_threads64_"),
    ("openblas_set_num_threads", "openblas_get_num_threads"),
)


def _openblas() -> list[tuple[object, object]]:
    """(setter, getter) of every OpenBLAS loaded in this process (read from /proc/self/maps)."""
    maps = Path("/proc/self/maps")
    if not maps.exists():
        return []
    out = []
    for path in sorted(set(re.findall(r"(/\S*openblas\S*\.so\S*)", maps.read_text()))):
        try:
            lib = ctypes.CDLL(path)
        except OSError:
            continue
        for setter, getter in _SYMBOLS:
            if hasattr(lib, setter) and hasattr(lib, getter):
                out.append((getattr(lib, setter), getattr(lib, getter)))
                break
    return out


@contextmanager
def single_blas_thread() -> Iterator[None]:
    try:
        from threadpoolctl import threadpool_limits
    except ImportError:
        threadpool_limits = None
    if threadpool_limits is not None:
        with threadpool_limits(limits=1, user_api="blas"):
            yield
        return
    try:
        libs = _openblas()
        before = [int(get()) for _, get in libs]
        for set_threads, _ in libs:
            set_threads(1)
    except (OSError, AttributeError, ValueError):
        libs, before = [], []
    try:
        yield
    finally:
        for (set_threads, _), n in zip(libs, before):
            set_threads(n)
