"""One way to compile small numba kernels, shared by physics and I/O.

``numba.njit(cache=True)`` raises RuntimeError when numba finds no writable cache directory (a read-only install
without NUMBA_CACHE_DIR); the kernel is then compiled once per process instead."""

from __future__ import annotations

import numba
from llvmlite import ir
from numba.core import cgutils, types
from numba.extending import intrinsic


def jit(fn=None, **options):
    """``@jit`` or ``@jit(error_model="numpy")``: ``numba.njit(nogil=True, cache=True, **options)`` with the
    no-cache fallback."""
    def wrap(f):
        try:
            return numba.njit(cache=True, nogil=True, **options)(f)
        except RuntimeError:
            return numba.njit(nogil=True, **options)(f)

    return wrap(fn) if fn is not None else wrap


@intrinsic
def prefetch(typingctx, table, row, col):
    """``prefetch(table, row, col)`` in compiled code: ask the CPU to bring the cache line of the 2-D array's entry
    ``table[row, col]`` (indices ≥ 0, in bounds) in while other work goes on (``llvm.prefetch``: read, keep in all
    cache levels). Returns nothing and reads nothing: a hint, which hides the miss of a table read that is known some
    work before its value is needed."""
    def codegen(context, builder, signature, args):
        array_type = signature.args[0]
        array = context.make_array(array_type)(context, builder, args[0])
        index = [context.cast(builder, value, kind, types.intp) for value, kind in zip(args[1:], signature.args[1:])]
        pointer = cgutils.get_item_pointer2(context, builder, array.data, cgutils.unpack_tuple(builder, array.shape),
                                            cgutils.unpack_tuple(builder, array.strides), array_type.layout, index)
        i32 = ir.IntType(32)
        address = builder.bitcast(pointer, ir.PointerType(ir.IntType(8)))
        function_type = ir.FunctionType(ir.VoidType(), [address.type, i32, i32, i32])
        fn = builder.module.declare_intrinsic("llvm.prefetch", [address.type], function_type)   # p0 / p0i8
        builder.call(fn, [address, ir.Constant(i32, 0), ir.Constant(i32, 3), ir.Constant(i32, 1)])
        return context.get_dummy_value()

    return types.void(table, row, col), codegen
