"""The EPM's fast path: an EPM program (:mod:`ofera.mapping.epm_program`: the Gemm, Relu and Add nodes of the MLPs
``ofera epm export`` writes) run for one frame by one numba kernel.

ONNX Runtime (:class:`ofera.mapping.runtime.Mapper`) is the reference: the tests compare the two on the shipped EPM
and on graphs of every shape a program takes, and the pipeline runs ONNX Runtime for a graph that has none. On a cold
CPU a frame's ``session.run`` cost 2-4x this kernel (benchmarks/README.md, round nineteen): its executor walks far
more code than the model's 150 thousand multiply-adds.

Sums are float32 in input order (``y[j] += x[i] * w[i, j]``, SIMD lanes over j); ONNX Runtime's blocked products
round differently, so the values agree to about 1e-6 of their size, not bit for bit.
"""

from __future__ import annotations

import numba as nb
import numpy as np

from ..jit import NB, Bound
from .epm_program import GEMM, RELU, EpmProgram


@nb.njit(**NB)
def epm_kernel(steps, weights, biases, scratch, output, x, out):
    """One frame through a program: x (n_in,) float32 clamped to [0, 1] (the identity BDA's clamp) into slot 0, the
    steps in order over scratch (slots, width) float32, slot ``output`` into out (n_out,). Unsigned indices (no
    wrap-around code, which keeps LLVM from vectorising the products: ofera.avatar.kernels)."""
    zero, one = np.float32(0.0), np.float32(1.0)
    for j in range(np.uint64(x.shape[0])):
        scratch[0, j] = min(max(x[j], zero), one)
    for k in range(np.uint64(steps.shape[0])):
        op, a, b, dst = steps[k, 0], np.uint64(steps[k, 1]), np.uint64(steps[k, 2]), np.uint64(steps[k, 3])
        n_in, n_out = np.uint64(steps[k, 6]), np.uint64(steps[k, 7])
        y = scratch[dst]
        if op == GEMM:
            w0, b0 = np.uint64(steps[k, 4]), np.uint64(steps[k, 5])
            src = scratch[a]
            for j in range(n_out):
                y[j] = biases[b0 + j]
            for i in range(n_in):
                xi = src[i]
                row = w0 + i * n_out
                for j in range(n_out):
                    y[j] += xi * weights[row + j]
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


def _fixed_epm_kernel(fixed, x, out):
    return epm_kernel(*fixed.args, x, out)


_epm_bound = nb.njit(**NB)(_fixed_epm_kernel)


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
