"""Load FLAME 2020 / 2023 pickles safely: a class whitelist, no chumpy, no code execution.

A pickle is a program. This unpickler resolves only the classes a FLAME file needs: numpy arrays and
dtypes (under ``numpy.core`` and ``numpy._core``), scipy sparse matrices (old and new module paths),
and chumpy objects, which become plain arrays. Anything else (``os.system``, ``builtins.eval``, ...) is
refused before it can run.
"""

from __future__ import annotations

import codecs
import io
import pickle
from pathlib import Path

import numpy as np
import scipy.sparse as sp

from .model import HeadModel, HeadModelError

MAX_PICKLE_BYTES = 512 * 1024 * 1024


class UnsafePickleError(HeadModelError):
    """The pickle asks for a class outside the whitelist; nothing from it was executed."""


class _ChumpyArray:
    """Stands in for any ``chumpy`` object: keeps the array its state carries."""

    def __init__(self, *args, **kwargs) -> None:
        self.value: np.ndarray | None = None

    def __setstate__(self, state) -> None:
        if isinstance(state, tuple) and state and isinstance(state[0], dict):
            state = state[0]  # (dict state, slot state)
        if not isinstance(state, dict):
            raise HeadModelError("chumpy object with a non-dict state")
        if "x" in state and state["x"] is not None:
            self.value = np.asarray(state["x"])
        elif "a" in state:  # a view: rebuild from the parent array and indices
            base = _as_array(state["a"])
            idxs = state.get("idxs")
            self.value = base.reshape(-1)[np.asarray(idxs)] if idxs is not None else base
        else:
            raise HeadModelError(f"chumpy object without an array (state keys {sorted(state)})")


_SPARSE = {
    "csc_matrix": sp.csc_matrix,
    "csr_matrix": sp.csr_matrix,
    "coo_matrix": sp.coo_matrix,
}
_SPARSE_MODULES = ("scipy.sparse", "scipy.sparse.csc", "scipy.sparse._csc", "scipy.sparse.csr",
                   "scipy.sparse._csr", "scipy.sparse.coo", "scipy.sparse._coo")


def _numpy_class(module: str, name: str):
    from numpy._core import multiarray  # numpy >= 2

    allowed = {
        "_reconstruct": multiarray._reconstruct,
        "scalar": multiarray.scalar,
        "ndarray": np.ndarray,
        "dtype": np.dtype,
    }
    if module in ("numpy", "numpy.core.multiarray", "numpy._core.multiarray", "numpy.core.numeric",
                  "numpy._core.numeric") and name in allowed:
        return allowed[name]
    if module in ("numpy.core.numeric", "numpy._core.numeric") and name == "_frombuffer":
        return _frombuffer
    if module == "numpy" and name in ("float64", "float32", "int64", "int32", "uint32", "uint64", "bool_"):
        return getattr(np, name)
    if module == "numpy.dtypes" and name.endswith("DType"):
        return getattr(np.dtypes, name)
    return None


def _frombuffer(buf, dtype, shape, order):
    return np.frombuffer(buf, dtype=dtype).reshape(shape, order=order).copy()


class _WhitelistUnpickler(pickle.Unpickler):
    def find_class(self, module: str, name: str):
        if module.split(".")[0] == "chumpy":
            return _ChumpyArray
        if module in _SPARSE_MODULES and name in _SPARSE:
            return _SPARSE[name]
        if module.startswith("numpy"):
            cls = _numpy_class(module, name)
            if cls is not None:
                return cls
        if module in ("copy_reg", "copyreg") and name == "_reconstructor":
            return _reconstructor
        if module in ("__builtin__", "builtins") and name in ("object", "set", "frozenset"):
            return {"object": object, "set": set, "frozenset": frozenset}[name]
        if module == "_codecs" and name == "encode":  # how protocol 2 stores bytes written by Python 3
            return codecs.encode
        raise UnsafePickleError(f"refused to load class {module}.{name}: not on the FLAME whitelist")


def _reconstructor(cls, base, state):
    if cls is _ChumpyArray or (isinstance(cls, type) and issubclass(cls, _ChumpyArray)):
        return _ChumpyArray()
    if cls is np.ndarray or (isinstance(cls, type) and issubclass(cls, np.ndarray)):
        return np.ndarray.__new__(cls, state) if state is not None else np.ndarray.__new__(cls, (0,))
    raise UnsafePickleError(f"refused to reconstruct {cls!r}")


def _as_array(obj) -> np.ndarray:
    if isinstance(obj, _ChumpyArray):
        if obj.value is None:
            raise HeadModelError("chumpy object without a value")
        return obj.value
    if sp.issparse(obj):
        return obj.toarray()
    return np.asarray(obj)


def read_flame_pickle(path: str | Path) -> dict:
    """The raw dict of a FLAME pickle, every value a plain numpy array (sparse -> dense)."""
    path = Path(path)
    size = path.stat().st_size
    if size > MAX_PICKLE_BYTES:
        raise HeadModelError(f"{path}: {size} bytes is larger than any FLAME file ({MAX_PICKLE_BYTES} max)")
    data = path.read_bytes()
    try:
        raw = _WhitelistUnpickler(io.BytesIO(data), encoding="latin1").load()
    except UnsafePickleError as exc:
        raise UnsafePickleError(f"{path}: {exc}") from None
    except HeadModelError as exc:
        raise HeadModelError(f"{path}: {exc}") from None
    except Exception as exc:  # a corrupt pickle can raise nearly anything
        raise HeadModelError(f"{path}: not a readable FLAME pickle ({type(exc).__name__}: {exc})") from None
    if not isinstance(raw, dict):
        raise HeadModelError(f"{path}: pickle holds a {type(raw).__name__}, expected a dict of arrays")
    return {k: _as_array(v) if k != "bs_style" and k != "bs_type" else v for k, v in raw.items()}


def load_flame_pickle(path: str | Path, n_shape: int = 300, n_expr: int = 100) -> HeadModel:
    """A FLAME 2020 (``generic_model.pkl``) or 2023 (``flame2023.pkl``) file -> :class:`HeadModel`."""
    raw = read_flame_pickle(path)
    need = ["v_template", "f", "shapedirs", "posedirs", "J_regressor", "kintree_table", "weights"]
    missing = [k for k in need if k not in raw]
    if missing:
        raise HeadModelError(f"{path}: not a FLAME model, missing keys {missing}")
    v_template = np.asarray(raw["v_template"], np.float64)
    v = v_template.shape[0]
    shapedirs = np.asarray(raw["shapedirs"], np.float64)
    if shapedirs.ndim != 3 or shapedirs.shape[:2] != (v, 3) or shapedirs.shape[2] < 300:
        raise HeadModelError(f"{path}: shapedirs has shape {shapedirs.shape}, expected ({v}, 3, >=300)")
    n_expr = min(n_expr, shapedirs.shape[2] - 300)
    posedirs = np.asarray(raw["posedirs"], np.float64)
    if posedirs.shape != (v, 3, 36):
        raise HeadModelError(f"{path}: posedirs has shape {posedirs.shape}, expected ({v}, 3, 36)")
    parents = np.asarray(raw["kintree_table"], np.int64)[0].copy()
    parents[0] = -1  # FLAME stores a huge sentinel for the root
    return HeadModel(
        v_template=v_template,
        shapedirs=shapedirs[:, :, :n_shape],
        exprdirs=shapedirs[:, :, 300 : 300 + n_expr],
        posedirs=posedirs.reshape(3 * v, 36).T.copy(),
        j_regressor=np.asarray(raw["J_regressor"], np.float64),
        parents=parents,
        weights=np.asarray(raw["weights"], np.float64),
        faces=np.asarray(raw["f"], np.int64),
        name=Path(path).stem,
    )
