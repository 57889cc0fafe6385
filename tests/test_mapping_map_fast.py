"""The map stage's fast path (mapping.map_fast) against its references: the layout's product against LayoutAdapter
(numpy), the EPM program (mapping.epm_program) against ONNX Runtime on the shipped EPM, an exported one, graphs of
every shape a program takes, and the graphs it leaves to ONNX Runtime."""

from __future__ import annotations

import numpy as np
import onnx
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from ofera.avatar import load_avatar
from ofera.mapping.epm_program import UnsupportedGraph, compile_epm
from ofera.mapping.layouts import LAYOUT_NAMES, LayoutAdapter
from ofera.mapping.map_fast import FastEpm, FastLayout
from ofera.mapping.runtime import Mapper
from ofera.streaming.pipeline import AvatarAssets, Pipeline
from onnx import TensorProto, helper, numpy_helper

ATOL = 2e-6  # relative to the largest value: float32 sums in another order than ONNX Runtime's


def _inputs(n: int, width: int = 51, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    x = rng.random((n, width), dtype=np.float32) ** 3
    x[rng.random((n, width)) < 0.4] = 0.0
    return x


def _agree(fast: np.ndarray, ref: np.ndarray) -> None:
    np.testing.assert_allclose(fast, ref, rtol=0, atol=ATOL * max(1.0, float(np.abs(ref).max())))


def _model(nodes, inits, n_in: int, n_out: int) -> onnx.ModelProto:
    graph = helper.make_graph(nodes, "g", [helper.make_tensor_value_info("x", TensorProto.FLOAT, ["B", n_in])],
                              [helper.make_tensor_value_info("y", TensorProto.FLOAT, ["B", n_out])],
                              [numpy_helper.from_array(a, name) for name, a in inits.items()])
    return helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])


def _mapper(tmp_path, model: onnx.ModelProto) -> Mapper:
    path = tmp_path / "epm.onnx"
    onnx.save(model, str(path))
    return Mapper.load(path)


@pytest.mark.parametrize("layout", sorted(LAYOUT_NAMES))
def test_the_layouts_product_is_the_adapters(layout):
    adapter = LayoutAdapter(layout)
    fast = FastLayout(LayoutAdapter(layout))
    k = adapter.layout.length
    x = _inputs(40, k, seed=k)
    x[:10] = x[:10] * 3 - 1  # outside [0, 1]: both clamp
    kept = np.zeros(51 if k != 52 else 52, np.float32)
    keeping = FastLayout(LayoutAdapter(layout), keep=kept[:adapter.out.shape[0]])
    for row in x:
        assert fast(row) is fast.out
        _agree(fast.out, adapter(row))
        before = kept.copy()
        keeping(row)
        assert np.array_equal(kept, before)  # (keep only when asked)
        keeping(row, True)
        assert np.array_equal(kept[:adapter.out.shape[0]], keeping.out)
    for bad in (np.zeros(k + 1, np.float32), np.zeros(1, np.float32), [0.5] * k):
        with pytest.raises(ValueError, match=f"expected {k} values for {layout!r}"):
            fast(bad)


def test_the_shipped_epm_runs_in_the_fast_path():
    mapper = Mapper.default()
    assert mapper.program is not None, mapper.program_note
    epm = FastEpm(mapper.program)
    x = _inputs(300, seed=1)
    x[:20] = x[:20] * 3 - 1  # outside [0, 1]: both clamp (the identity BDA)
    ref = mapper.map_batch(x)
    out = np.zeros(68, np.float32)
    for row, want in zip(x, ref):
        assert epm(np.ascontiguousarray(row), out) is out
        _agree(out, want)


def test_an_exported_epm_runs_in_the_fast_path(tmp_path):
    torch = pytest.importorskip("torch")
    from ofera.training.epm.export import export_onnx
    from ofera.training.epm.model import EPM

    torch.manual_seed(3)
    path = export_onnx(EPM(hidden=48), tmp_path / "epm.onnx")  # batch norms folded into the Gemms
    mapper = Mapper.load(path)
    assert mapper.program is not None, mapper.program_note
    epm = FastEpm(mapper.program)
    x = _inputs(50, seed=2)
    _agree(np.stack([epm.map(r) for r in x]), mapper.map_batch(x))


@settings(max_examples=25, deadline=None)
@given(widths=st.lists(st.integers(1, 40), min_size=1, max_size=4), trans=st.lists(st.booleans(), min_size=5,
       max_size=5), residual=st.booleans(), bias=st.sampled_from(["1d", "2d", "none"]), seed=st.integers(0, 99))
def test_graphs_of_every_taken_shape_agree_with_onnx_runtime(tmp_path_factory, widths, trans, residual, bias, seed):
    """Chains of Gemm (transB either way, bias (n,), (1, n) or none) and Relu, with a residual Add around a hidden
    layer's pair: the fast path's values are ONNX Runtime's."""
    rng = np.random.default_rng(seed)
    dims = [51, *widths, 68]
    nodes, inits, prev = [], {}, "x"
    for k in range(len(dims) - 1):
        w = rng.normal(0, 0.5, (dims[k + 1], dims[k])).astype(np.float32)
        tb = trans[k % len(trans)]
        inits[f"w{k}"] = w if tb else np.ascontiguousarray(w.T)
        ins = [prev, f"w{k}"]
        if bias != "none":
            b = rng.normal(0, 0.1, dims[k + 1]).astype(np.float32)
            inits[f"b{k}"] = b if bias == "1d" else b[None]
            ins.append(f"b{k}")
        last = k == len(dims) - 2
        nodes.append(helper.make_node("Gemm", ins, ["y" if last else f"g{k}"], transB=int(tb)))
        if not last:
            nodes.append(helper.make_node("Relu", [f"g{k}"], [f"r{k}"]))
            prev = f"r{k}"
            if residual and k > 0 and dims[k] == dims[k + 1]:
                nodes.append(helper.make_node("Add", [f"r{k - 1}", f"r{k}"], [f"a{k}"]))
                prev = f"a{k}"
    mapper = _mapper(tmp_path_factory.mktemp("g"), _model(nodes, inits, 51, 68))
    assert mapper.program is not None, mapper.program_note
    x = _inputs(8, seed=seed)
    _agree(np.stack([FastEpm(mapper.program).map(r) for r in x]), mapper.map_batch(x))


def _gemm_model(**attrs) -> onnx.ModelProto:
    w, b = np.ones((68, 51), np.float32), np.zeros(68, np.float32)
    return _model([helper.make_node("Gemm", ["x", "w", "b"], ["y"], transB=1, **attrs)], {"w": w, "b": b}, 51, 68)


@pytest.mark.parametrize(("model", "says"), [
    (lambda: _gemm_model(alpha=0.5), "alpha"),
    (lambda: _model([helper.make_node("Gemm", ["x", "w", "b"], ["h"], transB=1),
                     helper.make_node("Tanh", ["h"], ["y"])],
                    {"w": np.ones((68, 51), np.float32), "b": np.zeros(68, np.float32)}, 51, 68), "op Tanh"),
    (lambda: _model([helper.make_node("Gemm", ["x", "w", "b"], ["h"], transB=1),
                     helper.make_node("Add", ["h", "c"], ["y"])],
                    {"w": np.ones((68, 51), np.float32), "b": np.zeros(68, np.float32),
                     "c": np.ones(68, np.float32)}, 51, 68), "not a computed vector"),
    (lambda: _model([helper.make_node("Gemm", ["x", "w", "b"], ["y"], transB=1)],
                    {"w": np.ones((68, 50), np.float32), "b": np.zeros(68, np.float32)}, 51, 68), "do not fit"),
])
def test_graphs_it_does_not_take_are_left_to_onnx_runtime(tmp_path, model, says):
    with pytest.raises(UnsupportedGraph, match=says):
        compile_epm(model())
    if says != "do not fit":  # (ONNX Runtime refuses that one itself)
        mapper = _mapper(tmp_path, model())
        assert mapper.program is None and says in mapper.program_note
        assert mapper.map(_inputs(1)[0]).shape == (68,)


def test_the_pipelines_fast_path_maps_with_it_and_the_reference_with_onnx_runtime():
    avatar = load_avatar("default")
    mapper = Mapper.default()
    fast = Pipeline(AvatarAssets.create("default", avatar, mapper), "arkit52")
    ref = Pipeline(AvatarAssets.create("default", avatar, mapper, fast=False), "arkit52")
    assert fast.epm is not None and ref.epm is None
    for w in _inputs(20, 52, seed=5):
        got, stages = fast.map(w)
        want, _ = ref.map(w)
        _agree(got, want)
        assert set(stages) == {"layout", "bda", "epm"}
