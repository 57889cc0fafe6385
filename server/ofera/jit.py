"""What the numba fast paths share: the njit options of every kernel (``NB``) and the intrinsics more than one of
them needs. Imported only by fast-path modules (it needs numba and llvmlite); any layer may import it."""

from __future__ import annotations

from llvmlite import ir
from numba.core import types
from numba.extending import intrinsic

NB = {"cache": True, "nogil": True, "fastmath": False, "error_model": "numpy", "boundscheck": False}
"""``numba.njit`` options of every kernel: cached on disk, no GIL, IEEE arithmetic (no fastmath), numpy error
semantics, no bounds checks (each kernel's caller checks shapes)."""


@intrinsic
def f16_bits_to_f32(typingctx, h):
    """uint16 bits of an IEEE binary16 -> float32 (exact; LLVM's fpext half -> float)."""
    if not isinstance(h, types.Integer) or h.bitwidth != 16:
        return None

    def codegen(context, builder, signature, args):
        return builder.fpext(builder.bitcast(args[0], ir.HalfType()), ir.FloatType())

    return types.float32(h), codegen


@intrinsic
def f32_to_f16_bits(typingctx, x):
    """float32 -> the uint16 bits of the nearest IEEE binary16 (round half to even; LLVM's fptrunc float -> half)."""
    if not isinstance(x, types.Float) or x.bitwidth != 32:
        return None

    def codegen(context, builder, signature, args):
        return builder.bitcast(builder.fptrunc(args[0], ir.HalfType()), ir.IntType(16))

    return types.uint16(x), codegen


F16_MAX = 65504.0
"""The largest finite IEEE binary16."""
