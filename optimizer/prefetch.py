"""A cache hint for compiled kernels: start loading memory that a later step of a loop will read.

The SGD pass visits constraints in their stored order; a loop closure reads a far pose's block and its
path in the tree, which at 10⁶ poses are out of cache. Knowing which constraints come next, the pass asks
for their memory a few constraints ahead, so the loads overlap the work in between. A prefetch changes
no value and never faults (an address past an array's end is only a wasted hint).
"""

from __future__ import annotations

from llvmlite import ir
from numba import types
from numba.core import cgutils
from numba.core.errors import TypingError
from numba.extending import intrinsic

_READ = 0
_KEEP_IN_ALL_CACHES = 3
_DATA_CACHE = 1


@intrinsic
def prefetch(typingctx, array, offset):  # type: ignore[no-untyped-def]  # numba's intrinsic protocol
    """Hint that the item `offset` items past the start of `array`'s buffer (as if the array were flat and
    C-contiguous) will be read soon; x86's `prefetcht0`."""
    if not isinstance(array, types.Array) or not isinstance(offset, types.Integer):
        raise TypingError("prefetch(array, integer offset)")
    signature = types.void(array, offset)

    def codegen(context, builder, signature, args):  # type: ignore[no-untyped-def]
        data = context.make_array(signature.args[0])(context, builder, args[0]).data
        address = builder.gep(data, [args[1]])
        int32 = ir.IntType(32)
        hint = cgutils.get_or_insert_function(
            builder.module, ir.FunctionType(ir.VoidType(), [address.type, int32, int32, int32]),
            "llvm.prefetch.p0")
        builder.call(hint, [address, int32(_READ), int32(_KEEP_IN_ALL_CACHES), int32(_DATA_CACHE)])
        return context.get_dummy_value()

    return signature, codegen
