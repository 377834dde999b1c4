"""``copy(dst, dst_at, src, src_at, n)`` for compiled code: ``dst[dst_at:dst_at + n] =
src[src_at:src_at + n]`` as one ``memcpy``.

numba compiles a slice assignment to a general array assignment that first checks whether
the two sides may overlap: ~30 ns for a 100-byte item, where the ``memcpy`` takes a few. The
caller keeps both ranges in bounds, and ``dst`` and ``src`` distinct contiguous 1-d arrays of
one dtype (others are refused when compiling).

numba's on-disk cache of a kernel is checked against the kernel's own file only: after editing
this one, delete the ``__pycache__`` folders' ``*.nbi``/``*.nbc`` files (a new install writes
every file anew, so installs are not affected).
"""

from typing import TYPE_CHECKING

from numba import types
from numba.core import cgutils
from numba.extending import intrinsic

__all__ = ["copy"]


if TYPE_CHECKING:
    import numpy as np

    # numba's stubs give an intrinsic its typing function's signature, typing context and all,
    # and a call that never returns (it does, in compiled code): the signature callers see.
    def copy(dst: np.ndarray, dst_at: int, src: np.ndarray, src_at: int, n: int) -> None: ...

else:

    @intrinsic
    def copy(typingctx, dst, dst_at, src, src_at, n):  # numba passes the typing context first
        arrays = (dst, src)
        if not all(isinstance(a, types.Array) and a.ndim == 1 and a.layout == "C" for a in arrays):
            return None  # numba then reports no matching signature: one memcpy needs contiguous rows
        if dst.dtype != src.dtype:
            return None

        def codegen(context, builder, signature, args):
            dst, dst_at, src, src_at, n = args
            to = context.make_array(signature.args[0])(context, builder, dst)
            of = context.make_array(signature.args[2])(context, builder, src)
            size = context.get_abi_sizeof(context.get_data_type(signature.args[0].dtype))
            to_ptr, of_ptr = builder.gep(to.data, [dst_at]), builder.gep(of.data, [src_at])
            cgutils.raw_memcpy(builder, to_ptr, of_ptr, n, size)
            return context.get_dummy_value()

        return types.void(dst, dst_at, src, src_at, n), codegen
