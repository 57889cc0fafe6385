"""The map stage's fast path (the streaming pipeline's fast path runs it): the layout adapter's product
(:class:`FastLayout`) and the EPM (:class:`FastEpm`: an EPM program, :mod:`ofera.mapping.epm_program`, the Gemm, Relu
and Add nodes of the MLPs ``ofera epm export`` writes), each one numba call a frame.

The references: ``LayoutAdapter`` (numpy) and ONNX Runtime (:class:`ofera.mapping.runtime.Mapper`), which the tests
compare them with (the shipped EPM, and graphs of every shape a program takes); the pipeline runs ONNX Runtime for a
graph that has no program. On a cold CPU a frame's ``session.run`` cost 3x the EPM's kernel, the adapter's numpy
product and clamps 4x its kernel (benchmarks/README.md, round nineteen): their code paths are far longer than the
sums they do (the EPM: 150 thousand multiply-adds).

Sums are float32 in input order (``y[j] += x[i] * w[i, j]``, SIMD lanes over j; unsigned indices, no wrap-around
code, which keeps LLVM from vectorising: ofera.avatar.kernels); BLAS and ONNX Runtime's blocked products round
differently, so the values agree to about 1e-6 of their size, not bit for bit.
"""

from __future__ import annotations

import numba as nb
import numpy as np

from ..jit import NB, Bound
from .epm_program import GEMM, RELU, EpmProgram
from .layouts import LayoutAdapter


@nb.njit(inline="always", **NB)
def _add_products(x, w, w0, n_out, y):
    """y (n_out,) += x @ W, W (len(x), n_out) row by row in the flat float32 w from offset w0: input order, SIMD
    lanes over the outputs (the one product of both kernels here)."""
    for i in range(np.uint64(x.shape[0])):
        xi = x[i]
        row = w0 + i * n_out
        for j in range(n_out):
            y[j] += xi * w[row + j]


@nb.njit(**NB)
def epm_kernel(steps, weights, biases, scratch, output, x, out):
    """One frame through a program: x (n_in,) float32 clamped to [0, 1] (the identity BDA's clamp) into slot 0, the
    steps in order over scratch (slots, width) float32, slot ``output`` into out (n_out,)."""
    zero, one = np.float32(0.0), np.float32(1.0)
    for j in range(np.uint64(x.shape[0])):
        scratch[0, j] = min(max(x[j], zero), one)
    for k in range(np.uint64(steps.shape[0])):
        op, a, b, dst = steps[k, 0], np.uint64(steps[k, 1]), np.uint64(steps[k, 2]), np.uint64(steps[k, 3])
        n_in, n_out = np.uint64(steps[k, 6]), np.uint64(steps[k, 7])
        y = scratch[dst]
        if op == GEMM:
            b0 = np.uint64(steps[k, 5])
            for j in range(n_out):
                y[j] = biases[b0 + j]
            _add_products(scratch[a][:n_in], weights, np.uint64(steps[k, 4]), n_out, y)
        elif op == RELU:
            src = scratch[a]
            for j in range(n_out):
                y[j] = max(src[j], zero)
        else:
            u, v = scratch[a], scratch[b]
            for j in range(n_out):
                y[j] = u[j] + v[j]
    res = scratch[np.uint64(output)]
    for j in range(np.uint64(out.shape[0])):
        out[j] = res[j]


@nb.njit(**NB)
def layout_kernel(w, mt, out, keep, keep_too):
    """``LayoutAdapter``'s conversion: w (K,) float32 weights, mt (K * N,) float32 the conversion matrix (transposed,
    flat) -> out (N,) = clamp(w @ mt, 0, 1), copied into keep (N,) too if ``keep_too``."""
    zero, one = np.float32(0.0), np.float32(1.0)
    n = np.uint64(out.shape[0])
    for j in range(n):
        out[j] = zero
    _add_products(w, mt, np.uint64(0), n, out)
    for j in range(n):
        out[j] = min(max(out[j], zero), one)
    if keep_too:
        for j in range(n):
            keep[j] = out[j]


class FastLayout:
    """A ``LayoutAdapter``'s conversion in one numba call: ``layout(w)`` -> its ``out`` (N,) float32, overwritten by
    the next call (the adapter's own buffer and matrix); ``layout(w, keep=True)`` copies it into ``keep`` as well (the
    confidence hold's memory, ``RegionHold.last``: what the hold does with a frame that has no confidence, in the same
    call). w is copied into a buffer of its own first, so that the call always has one type (a decoded bs is a
    read-only view)."""

    def __init__(self, adapter: LayoutAdapter, keep: np.ndarray | None = None) -> None:
        self.adapter = adapter
        self.out = adapter.out
        self._w = np.zeros(adapter.layout.length, np.float32)
        keep = np.zeros_like(self.out) if keep is None else keep
        if keep.shape != self.out.shape or keep.dtype != np.float32 or not keep.flags.writeable:
            raise ValueError(f"keep must be a writable float32 array of {self.out.shape}")
        self._call = Bound(_layout_bound, (adapter.mt.reshape(-1), self.out, keep))

    def __call__(self, w: np.ndarray, keep: bool = False) -> np.ndarray:
        """w (K,) -> out (N,); ValueError naming the layout if w is not K values."""
        if getattr(w, "shape", None) != self._w.shape:  # (a slice assignment would broadcast one value)
            raise ValueError(f"expected {self._w.shape[0]} values for {self.adapter.layout.name!r}, got "
                             f"{np.shape(w)}")
        self._w[:] = w
        self._call(self._w, keep)
        return self.out


@nb.njit(**NB)
def _layout_bound(fixed, w, keep_too):
    """:func:`layout_kernel` with FastLayout's arguments (jit.Bound)."""
    mt, out, keep = fixed.args
    layout_kernel(w, mt, out, keep, keep_too)


@nb.njit(**NB)
def _epm_bound(fixed, x, out):
    """:func:`epm_kernel` with FastEpm's arguments (jit.Bound)."""
    steps, weights, biases, scratch, output = fixed.args
    epm_kernel(steps, weights, biases, scratch, output, x, out)


class FastEpm:
    """One stream's fast EPM: ``epm(x, out)`` writes the FLAME values (n_out,) float32 of arkit51 weights x (n_in,)
    float32 (clamped to [0, 1], as the mapper's identity BDA does) into ``out`` and returns it. Its scratch is its
    own: one per pipeline."""

    def __init__(self, program: EpmProgram) -> None:
        self.program = program
        p = program
        scratch = np.zeros((p.slots, p.width), np.float32)
        self._call = Bound(_epm_bound, (p.steps, p.weights, p.biases, scratch, p.output))

    def __call__(self, x: np.ndarray, out: np.ndarray) -> np.ndarray:
        """x (n_in,) float32 C-contiguous, out (n_out,) float32 writable (types and sizes are the caller's to keep:
        the compiled call checks nothing; :meth:`map` checks)."""
        self._call(x, out)
        return out

    def map(self, x: np.ndarray) -> np.ndarray:
        """x (n_in,) -> a new (n_out,) float32 array, with the shapes checked."""
        x = np.ascontiguousarray(x, np.float32).reshape(-1)
        if x.shape != (self.program.n_in,):
            raise ValueError(f"the EPM takes ({self.program.n_in},) weights, got {x.shape}")
        return self(x, np.zeros(self.program.n_out, np.float32))
