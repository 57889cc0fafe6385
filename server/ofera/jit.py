"""What the numba fast paths share: the njit options of every kernel (``NB``), the intrinsics more than one of
them needs, and a cheap call of a kernel whose many arguments stay the same (``Bound``). Imported only by fast-path
modules (it needs numba and llvmlite); any layer may import it."""

from __future__ import annotations

from typing import Any

from llvmlite import ir
from numba import njit
from numba.core import cgutils, types
from numba.core.typing.typeof import Purpose, typeof
from numba.experimental import structref
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


@intrinsic
def atomic_add(typingctx, array, index, value):
    """array[index] += value as one atomic read-modify-write (LLVM atomicrmw add, sequentially consistent) on an int64
    array; returns the value before. For threads of one parallel loop sharing a counter (numba has no atomics)."""
    if not (isinstance(array, types.Array) and array.dtype == types.int64 and isinstance(index, types.Integer)
            and isinstance(value, types.Integer)):
        return None

    def codegen(context, builder, signature, args):
        aryty = signature.args[0]
        ary = context.make_array(aryty)(context, builder, args[0])
        idx = context.cast(builder, args[1], signature.args[1], types.intp)
        ptr = cgutils.get_item_pointer(context, builder, aryty, ary, [idx], wraparound=False)
        val = context.cast(builder, args[2], signature.args[2], types.int64)
        return builder.atomic_rmw("add", ptr, val, "seq_cst")

    return types.int64(array, index, value), codegen


@njit(inline="always", **NB)
def wait_done(claims, parts):
    """Spin until claims[1] (work items done, counted by the threads of one parallel loop that claim them through
    claims[0]) reaches ``parts``. A thread waits only for items other running threads claimed (it claimed what was
    left first), so a loop whose iterations run one after another on one thread never waits for itself."""
    while atomic_add(claims, 1, 0) < parts:
        pass


@intrinsic
def cycle_counter(typingctx):
    """The processor's cycle counter (LLVM readcyclecounter: rdtsc on x86-64; 0 where a target has none), uint64. For
    splitting a kernel's time between its parts by the kernel's own clock; compiled into the kernel, so cacheable
    (a ctypes clock_gettime is not)."""

    def codegen(context, builder, signature, args):
        fn = builder.module.declare_intrinsic("llvm.readcyclecounter", fnty=ir.FunctionType(ir.IntType(64), []))
        return builder.call(fn, [])

    return types.uint64(), codegen


@intrinsic
def os_thread_id(typingctx):
    """The calling thread's Linux thread id (glibc's ``gettid``), int32: which OS thread runs an iteration of a parallel
    loop (``ofera.thread_placement``). Linux only; a symbol, not an address, so cacheable."""

    def codegen(context, builder, signature, args):
        fn = cgutils.get_or_insert_function(builder.module, ir.FunctionType(ir.IntType(32), []), "gettid")
        return builder.call(fn, [])

    return types.int32(), codegen


@structref.register
class _FixedType(types.StructRef):
    """numba type of :class:`Fixed`."""

    def preprocess_fields(self, fields):
        return tuple((name, types.unliteral(typ)) for name, typ in fields)


class Fixed(structref.StructRefProxy):
    """A kernel's fixed arguments (one tuple, ``fixed.args`` in the kernel) held by numba as one object. Every call
    with arguments in tuples types them in Python and unboxes each array again: entering and leaving the delta kernel
    took 72-81 us p50 a frame with its 55 arrays in tuples, 37-42 with them in one of these called through
    :class:`Bound` (benchmarks/README.md, round fifteen)."""

    def __new__(cls, args: tuple) -> Fixed:
        return _new_fixed(args)

    @property
    def args(self) -> tuple:
        return _fixed_args(self)


structref.define_constructor(Fixed, _FixedType, ["args"])
structref.define_boxing(_FixedType, Fixed)


@njit(cache=True)
def _new_fixed(args):
    return Fixed(args)


@njit(cache=True)
def _fixed_args(fixed):
    return fixed.args


class Bound:
    """``kernel(fixed, *args)`` with every argument but a few per call in ``fixed`` (a tuple, held as one
    :class:`Fixed`). The first call goes through numba's dispatcher (compiling or loading the kernel); later ones go
    straight to the compiled function it chose (``Dispatcher.get_overload``), which skips the dispatcher's typing of
    the arguments (about 18 us on a cold CPU). ``fixed`` never changes type, nor may ``args``: the compiled function
    itself checks nothing."""

    def __init__(self, kernel: Any, fixed: tuple) -> None:
        self.kernel, self.fixed, self.call = kernel, Fixed(fixed), None

    def __call__(self, *args: Any) -> Any:
        """``kernel(fixed, *args)``; ``args`` (per call: a message buffer, say) must keep their types from call to
        call, as ``fixed`` does."""
        if self.call is not None:
            return self.call(self.fixed, *args)
        result = self.kernel(self.fixed, *args)
        self.call = self.kernel.get_overload(tuple(typeof(a, Purpose.argument) for a in (self.fixed, *args)))
        return result
