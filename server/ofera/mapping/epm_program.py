"""An EPM's ONNX graph as a program for the fast path (:mod:`ofera.mapping.map_fast`): Gemm, Relu and Add nodes, the
MLPs ``ofera epm export`` writes (linear layers with their batch norms folded in, ReLUs, residual sums). No numba
here: the mapper compiles the program when it loads a file, and only the fast path runs it.

The graph becomes a program of steps over vector slots (slot 0: the input; one slot per node's output)::

    step = (op, a, b, dst, weight offset, bias offset, n_in, n_out)    op: GEMM, RELU or ADD; b: ADD's second slot

A Gemm's weight is stored as (n_in, n_out), row by row: the kernel's inner loop (``y[j] += x[i] * w[i, j]``) reads
it in order.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import OferaError

GEMM, RELU, ADD = 0, 1, 2
_STEP = 8  # fields of a step: op, a, b, dst, w_off, b_off, n_in, n_out


@dataclass(frozen=True)
class EpmProgram:
    """A compiled EPM graph: ``steps`` (K, 8) int64 (see the module docstring), ``weights`` and ``biases`` float32
    (every Gemm's, flat), ``width`` the widest slot, ``slots`` how many, ``output`` the output's slot, and the graph's
    input and output widths."""

    steps: np.ndarray
    weights: np.ndarray
    biases: np.ndarray
    width: int
    slots: int
    output: int
    n_in: int
    n_out: int


class UnsupportedGraph(OferaError, ValueError):
    """A graph the fast path does not run (ONNX Runtime does): the message names the node or shape."""


def _attrs(node) -> dict:
    from onnx import helper

    return {a.name: helper.get_attribute_value(a) for a in node.attribute}


def compile_epm(model) -> EpmProgram:
    """An ``onnx.ModelProto`` of one input (B, n_in) and one output (B, n_out) float32 computed by Gemm (alpha =
    beta = 1, transA = 0, a constant weight, a constant bias or none), Relu and Add (of two computed vectors) nodes ->
    its program. UnsupportedGraph naming what is not so."""
    from onnx import TensorProto, numpy_helper

    g = model.graph
    consts = {t.name: numpy_helper.to_array(t) for t in g.initializer}
    inputs = [i for i in g.input if i.name not in consts]
    if len(inputs) != 1 or len(g.output) != 1:
        raise UnsupportedGraph(f"{len(inputs)} inputs and {len(g.output)} outputs (one of each is taken)")
    dims = [d.dim_value for d in inputs[0].type.tensor_type.shape.dim]
    if inputs[0].type.tensor_type.elem_type != TensorProto.FLOAT or len(dims) != 2 or dims[1] <= 0:
        raise UnsupportedGraph(f"input {inputs[0].name!r} is not a float32 (B, n) tensor")
    slot = {inputs[0].name: 0}
    width = {0: dims[1]}
    steps: list[list[int]] = []
    weights: list[np.ndarray] = []
    biases: list[np.ndarray] = []
    w_off = b_off = 0

    def vector(name: str, node) -> int:
        if name not in slot:
            raise UnsupportedGraph(f"node {node.name or node.op_type!r} reads {name!r}, which is not a computed vector")
        return slot[name]

    for node in g.node:
        if len(node.output) != 1:
            raise UnsupportedGraph(f"node {node.name or node.op_type!r} has {len(node.output)} outputs")
        dst = len(slot)
        if node.op_type == "Gemm":
            a = _attrs(node)
            if a.get("alpha", 1.0) != 1.0 or a.get("beta", 1.0) != 1.0 or a.get("transA", 0) != 0:
                raise UnsupportedGraph(f"Gemm {node.name!r}: alpha, beta or transA other than 1, 1, 0")
            if not 2 <= len(node.input) <= 3 or any(n not in consts for n in node.input[1:]):
                raise UnsupportedGraph(f"Gemm {node.name!r}: weight or bias is not a constant")
            src = vector(node.input[0], node)
            w = np.asarray(consts[node.input[1]], np.float32)
            w = w.T if a.get("transB", 0) else w  # (n_in, n_out)
            b = (np.asarray(consts[node.input[2]], np.float32).reshape(-1) if len(node.input) == 3
                 else np.zeros(w.shape[-1], np.float32))
            if w.ndim != 2 or w.shape[0] != width[src] or b.shape != (w.shape[1],):
                raise UnsupportedGraph(f"Gemm {node.name!r}: weight {w.shape} and bias {b.shape} do not fit an input "
                                       f"of {width[src]}")
            steps.append([GEMM, src, -1, dst, w_off, b_off, w.shape[0], w.shape[1]])
            weights.append(np.ascontiguousarray(w).reshape(-1))
            biases.append(b)
            w_off += w.size
            b_off += b.size
            width[dst] = w.shape[1]
        elif node.op_type == "Relu":
            src = vector(node.input[0], node)
            steps.append([RELU, src, -1, dst, 0, 0, width[src], width[src]])
            width[dst] = width[src]
        elif node.op_type == "Add":
            a_, b_ = (vector(n, node) for n in node.input)
            if width[a_] != width[b_]:
                raise UnsupportedGraph(f"Add {node.name!r}: vectors of {width[a_]} and {width[b_]}")
            steps.append([ADD, a_, b_, dst, 0, 0, width[a_], width[a_]])
            width[dst] = width[a_]
        else:
            raise UnsupportedGraph(f"node {node.name!r}: op {node.op_type} (Gemm, Relu and Add are taken)")
        slot[node.output[0]] = dst
    out = g.output[0].name
    if out not in slot or not steps:
        raise UnsupportedGraph(f"output {out!r} is not computed by the graph's nodes")
    return EpmProgram(np.array(steps, np.int64).reshape(-1, _STEP), np.concatenate(weights), np.concatenate(biases),
                      max(width.values()), len(slot), slot[out], dims[1], width[slot[out]])


def load_epm_program(path: str | Path) -> EpmProgram:
    """The program of an EPM ONNX file (UnsupportedGraph: see :func:`compile_epm`)."""
    import onnx

    return compile_epm(onnx.load(str(path)))
