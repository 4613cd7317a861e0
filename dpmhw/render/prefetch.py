"""A software prefetch for numba kernels (LLVM's `llvm.prefetch`), which numba does not expose.

The shading kernel reads one 96-byte row of the triangle table per path vertex; after a bounce
the rows are in random order and the table (13 MB for two bunnies) is far larger than the L2
cache, so without a prefetch each vertex waited on that load. Prefetching never faults and
never changes a result.
"""

from __future__ import annotations

from llvmlite import ir
from numba import types
from numba.core import cgutils
from numba.extending import intrinsic


@intrinsic
def prefetch_row(typingctx, array, row):
    """Ask the CPU to bring the cache lines of array[row, 0] and array[row, -1] (a C-contiguous
    2-D array) into cache, for reading. `row` must be a valid index (it is not checked)."""
    if not (isinstance(array, types.Array) and array.ndim == 2 and array.layout == "C" and isinstance(row, types.Integer)):
        return None
    sig = types.void(array, row)

    def codegen(context, builder, signature, args):
        aryty, rowty = signature.args
        ary = context.make_array(aryty)(context, builder, args[0])
        i64 = ir.IntType(64)
        r = context.cast(builder, args[1], rowty, types.intp)
        ncols = builder.extract_value(ary.shape, 1)
        fnty = ir.FunctionType(ir.VoidType(), [ir.PointerType(ir.IntType(8)), ir.IntType(32), ir.IntType(32), ir.IntType(32)])
        fn = cgutils.get_or_insert_function(builder.module, fnty, "llvm.prefetch.p0")
        for col in (ir.Constant(i64, 0), builder.sub(ncols, ir.Constant(i64, 1))):
            ptr = cgutils.get_item_pointer2(context, builder, ary.data, cgutils.unpack_tuple(builder, ary.shape),
                                            cgutils.unpack_tuple(builder, ary.strides), aryty.layout, [r, col])
            # read, high temporal locality, data cache
            builder.call(fn, [builder.bitcast(ptr, ir.PointerType(ir.IntType(8))), ir.Constant(ir.IntType(32), 0),
                              ir.Constant(ir.IntType(32), 3), ir.Constant(ir.IntType(32), 1)])
        return context.get_dummy_value()

    return sig, codegen
