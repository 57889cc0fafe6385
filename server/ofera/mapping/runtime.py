"""The run-time mapper: arkit51 blendshapes -> BDA -> EPM (ONNX Runtime) -> 68 FLAME values.

No torch here: the server imports numpy, onnxruntime and onnx (which reads the graph for its program). The session
is single-threaded (``intra_op_num_threads = 1``: for a 51 -> 128 -> 68 MLP, thread hand-offs cost more than they
save, and each streaming session owns one mapper). Per frame, ``map`` writes into preallocated buffers
(the aligned input is written in place; ``session.run`` with a ready float32 array was faster than
IOBinding here, about 45 us against 90 us per call).

BDA is folded into the mapper: ``map(x) = EPM(clamp(x @ W.T + b, 0, 1))``; an identity BDA skips the
matrix product and only clamps.

ONNX Runtime is the reference and runs any graph. A graph of Gemm, Relu and Add nodes (every EPM ``ofera epm export``
writes) also gets a program (``program``: :mod:`ofera.mapping.epm_program`), which the streaming pipeline's fast path
runs in one numba call (:mod:`ofera.mapping.map_fast`); ``program_note`` says why a graph has none.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import onnxruntime as ort

from ..errors import OferaError
from .bda import BDA, load_bda
from .epm_program import EpmProgram, UnsupportedGraph, load_epm_program
from .layouts import ARKIT51_NAMES

N_IN = 51
N_OUT = 68
_ZERO, _ONE = np.float32(0.0), np.float32(1.0)


class MapperError(OferaError, ValueError):
    """An EPM ONNX file that cannot serve as a mapper; the message says why and what to do."""


def session_options(threads: int = 1) -> ort.SessionOptions:
    """Low-latency CPU options: ``threads`` intra-op threads, sequential execution, full graph optimisation."""
    opts = ort.SessionOptions()
    opts.intra_op_num_threads = threads
    opts.inter_op_num_threads = 1
    opts.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
    opts.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    opts.add_session_config_entry("session.intra_op.allow_spinning", "0")
    opts.log_severity_level = 3
    return opts


class Mapper:
    """arkit51 (51,) -> FLAME values (68,) float32; see the module docstring."""

    def __init__(self, session: ort.InferenceSession, bda: BDA | None = None, source: str = "",
                 program: EpmProgram | None = None, program_note: str = "") -> None:
        inputs, outputs = session.get_inputs(), session.get_outputs()
        if len(inputs) != 1 or len(outputs) < 1:
            raise MapperError(f"{source}: an EPM has one input (B, 51) and one output (B, 68), "
                              f"this model has {len(inputs)} inputs and {len(outputs)} outputs")
        shape_in, shape_out = inputs[0].shape, outputs[0].shape
        if len(shape_in) != 2 or shape_in[1] != N_IN or len(shape_out) != 2 or shape_out[1] != N_OUT:
            raise MapperError(f"{source}: EPM input {shape_in} / output {shape_out}; expected (B, {N_IN}) / "
                              f"(B, {N_OUT})")
        if inputs[0].type != "tensor(float)":
            raise MapperError(f"{source}: EPM input type {inputs[0].type}; expected float32")
        meta = session.get_modelmeta().custom_metadata_map
        if "input_names" in meta and json.loads(meta["input_names"]) != list(ARKIT51_NAMES):
            raise MapperError(f"{source}: the EPM's input names are not arkit51 (metadata input_names)")
        self.session = session
        self.source = source
        if program is not None and (program.n_in, program.n_out) != (N_IN, N_OUT):
            program, program_note = None, f"the program maps {program.n_in} -> {program.n_out} values"
        self.program = program  # the same graph for the fast path (map_fast.FastEpm), or None: program_note says why
        self.program_note = program_note
        self.input_name, self.output_name = inputs[0].name, outputs[0].name
        self.fixed_batch = isinstance(shape_in[0], int)
        self.bda = bda if bda is not None else BDA.identity()
        self._wt = np.ascontiguousarray(self.bda.W.T)
        self._b = self.bda.b
        self._identity = self.bda.is_identity
        # Batch-1 hot path: the aligned frame is written into one preallocated input buffer.
        self._x1 = np.zeros((1, N_IN), np.float32)
        self._feed = {self.input_name: self._x1}
        self._fetch = [self.output_name]

    # ----- construction ----------------------------------------------------------------------------

    @classmethod
    def load(cls, epm_onnx_path: str | Path, bda: BDA | str | Path | None = None, threads: int = 1) -> Mapper:
        """Load an EPM ONNX file; ``bda`` is a BDA, a BDA ``.npz`` path, or None (identity)."""
        path = Path(epm_onnx_path)
        if not path.is_file():
            raise MapperError(f"{path}: no such EPM ONNX file (export one with `ofera epm export epm.pt -o "
                              f"{path.name}`, or use the default)")
        try:
            sess = ort.InferenceSession(str(path), sess_options=session_options(threads),
                                        providers=["CPUExecutionProvider"])
        except Exception as exc:  # noqa: BLE001 - onnxruntime raises its own exception types
            raise MapperError(f"{path}: cannot load as ONNX: {exc}") from exc
        program, note = None, ""
        try:
            program = load_epm_program(path)
        except UnsupportedGraph as exc:
            note = f"ONNX Runtime only: {exc}"
        except ImportError:  # the onnx package reads the graph (a dependency of the server; absent: ORT alone)
            note = "ONNX Runtime only: the onnx package is not installed"
        return cls(sess, load_bda(bda), source=str(path), program=program, program_note=note)

    @classmethod
    def default(cls, bda: BDA | str | Path | None = None, threads: int = 1) -> Mapper:
        """The shipped EPM (``ofera/assets/epm_default.onnx``) with an identity BDA unless one is given."""
        from ..assets import default_epm_path

        return cls.load(default_epm_path(), bda, threads)

    # ----- mapping ---------------------------------------------------------------------------------

    def align(self, x: np.ndarray, out: np.ndarray) -> np.ndarray:
        """BDA into ``out``: ``clamp(x @ W.T + b, 0, 1)`` (clamp only for the identity)."""
        if self._identity:
            np.maximum(x, _ZERO, out=out)
        else:
            np.dot(x, self._wt, out=out)
            out += self._b
            np.maximum(out, _ZERO, out=out)
        return np.minimum(out, _ONE, out=out)

    def map(self, x51: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
        """One frame (51,) -> (68,) float32 FLAME values (a new array, or ``out`` filled)."""
        x = np.asarray(x51, dtype=np.float32)
        if x.shape != (N_IN,) and x.shape != (1, N_IN):
            raise ValueError(f"Mapper.map expects ({N_IN},) arkit51 weights, got {x.shape} (use map_batch for (B, 51))")
        self.align(x.reshape(1, N_IN), self._x1)
        y = self.session.run(self._fetch, self._feed)[0][0]
        if out is None:
            return y
        out[...] = y
        return out

    def map_batch(self, x: np.ndarray) -> np.ndarray:
        """Frames (B, 51) -> (B, 68) float32."""
        x = np.asarray(x, dtype=np.float32)
        if x.ndim != 2 or x.shape[1] != N_IN:
            raise ValueError(f"Mapper.map_batch expects (B, {N_IN}) arkit51 weights, got {x.shape}")
        if len(x) == 0:
            return np.zeros((0, N_OUT), np.float32)
        aligned = self.align(x, np.empty_like(x))
        if self.fixed_batch:  # a model exported with a fixed batch of 1: run frame by frame
            return np.concatenate([self.session.run([self.output_name], {self.input_name: row[None]})[0]
                                   for row in aligned])
        return self.session.run([self.output_name], {self.input_name: aligned})[0]

    __call__ = map_batch

    def epm_only(self, x: np.ndarray) -> np.ndarray:
        """The EPM on (B, 51) without BDA or clamping (for evaluation)."""
        return self.session.run([self.output_name], {self.input_name: np.ascontiguousarray(x, np.float32)})[0]
