"""Software prefetch for the njit walkers: ``prefetch(array, row)`` (LLVM ``llvm.prefetch``).

A crossing reads the next tet's records, whose address is known only once the current tet's
exit face is found: a cache miss per crossing, in series with the exit-face arithmetic. Asking
for the records of every neighbour a photon may enter next, as soon as it enters a tet, overlaps
the two (the technique of pointer-chasing codes; a prefetch never faults and changes no result).
"""

from llvmlite import ir
from numba import types
from numba.core import cgutils
from numba.extending import intrinsic

#: Bytes per cache line, and the most bytes of a row that are prefetched.
CACHE_LINE = 64
MAX_ROW_BYTES = 128


@intrinsic
def prefetch(typingctx, array, row):
    """Hint the CPU to load ``array[row]`` (up to :data:`MAX_ROW_BYTES`) into all cache levels.

    ``row`` must be a valid index of a C-contiguous array (no bounds check, no wrap-around).
    """
    if not isinstance(array, types.Array) or not isinstance(row, types.Integer):
        return None
    sig = types.void(array, row)

    def codegen(context, builder, signature, args):
        ary = context.make_array(signature.args[0])(context, builder, args[0])
        stride = cgutils.unpack_tuple(builder, ary.strides, signature.args[0].ndim)[0]
        idx = context.cast(builder, args[1], signature.args[1], types.intp)
        base = builder.add(builder.ptrtoint(ary.data, cgutils.intp_t),
                           builder.mul(idx, stride))
        i8p = ir.IntType(8).as_pointer()
        i32 = ir.IntType(32)
        fn = cgutils.get_or_insert_function(
            builder.module, ir.FunctionType(ir.VoidType(), [i8p, i32, i32, i32]),
            "llvm.prefetch.p0")
        for offset in range(0, MAX_ROW_BYTES, CACHE_LINE):
            with builder.if_then(builder.icmp_signed("<", cgutils.intp_t(offset), stride)):
                addr = builder.add(base, cgutils.intp_t(offset))
                # read (0), keep in all cache levels (3), data cache (1)
                builder.call(fn, [builder.inttoptr(addr, i8p), i32(0), i32(3), i32(1)])
        return context.get_dummy_value()

    return sig, codegen
