"""FSE parallel driver: the rounds of the block plan one after the other, the tiles of a round on the
numba threads (dynamic scheduling by an atomic counter), each tile's quadtree leaves in order through the
block kernel (``kernel``). Tiles of one round are never adjacent (``plan.rounds``), so the result does not
depend on the thread count.
"""
from __future__ import annotations

import numpy as np
from llvmlite import ir as llvm_ir
from numba import njit, prange
from numba.core import cgutils, types
from numba.extending import intrinsic

from .kernel import Context, block16, block16_joint, block32, block_generic, block_joint, make_scratch

__all__ = ["run", "worker", "fetch_add", "prefetch_window"]


@intrinsic
def fetch_add(typingctx, counter, i):
    """counter[i] += 1 as one atomic operation; returns the value before (dynamic scheduling)."""
    sig = types.int64(counter, i)

    def codegen(context, builder, signature, args):
        aryty, ity = signature.args
        ary = context.make_array(aryty)(context, builder, args[0])
        idx = context.cast(builder, args[1], ity, types.intp)
        ptr = cgutils.get_item_pointer(context, builder, aryty, ary, [idx])
        return builder.atomic_rmw("add", ptr, context.get_constant(types.int64, 1), "monotonic")

    return sig, codegen


@intrinsic
def prefetch(typingctx, arr, y, x):
    """Hint the cache line of arr[y, x] into the cache (llvm.prefetch, read, high locality); y, x must
    be inside the array."""
    sig = types.void(arr, y, x)

    def codegen(context, builder, signature, args):
        aryty, yty, xty = signature.args
        ary = context.make_array(aryty)(context, builder, args[0])
        iy = context.cast(builder, args[1], yty, types.intp)
        ix = context.cast(builder, args[2], xty, types.intp)
        ptr = cgutils.get_item_pointer(context, builder, aryty, ary, [iy, ix])
        i32 = llvm_ir.IntType(32)
        p8 = builder.bitcast(ptr, llvm_ir.IntType(8).as_pointer())
        fnty = llvm_ir.FunctionType(llvm_ir.VoidType(), [p8.type, i32, i32, i32])
        fn = cgutils.get_or_insert_function(builder.module, fnty, "llvm.prefetch.p0")
        builder.call(fn, [p8, i32(0), i32(3), i32(1)])
        return context.get_dummy_value()

    return sig, codegen


@njit(cache=True, nogil=True, inline="always")
def prefetch_window(img, state, ay, ax, n):
    """Prefetch the n x n support area at (ay, ax) of img and state (first and last column of each row),
    issued one tile ahead: the gather of a block otherwise waits for its rows (measured ~0.9 us of its
    ~1.8 us per 8 x 8 block at 1080p, where the rounds sweep the whole frame)."""
    h, w = img.shape
    x0 = min(max(ax, 0), w - 1)
    x1 = min(max(ax + n - 1, 0), w - 1)
    for y in range(max(ay, 0), min(ay + n, h)):
        prefetch(img, y, x0)
        prefetch(img, y, x1)
        prefetch(state, y, x0)
        prefetch(state, y, x1)


@njit(cache=True, nogil=True)
def worker(ctx, noisy, r, counter):
    """The tiles of round r on one thread: each thread takes the next unprocessed tile of the round
    (``counter[r]``, atomic), so all threads stay busy whatever the tiles cost and however the OS
    schedules them (a static split waits for the slower thread). The scratch is owned by this call (a
    few kB): no views of arrays shared with the other threads in the per-block calls. ``noisy`` None: the
    plain kernels (numba prunes the joint branch for that signature, so the joint kernels are compiled
    only when used); (wp, mest): the joint kernels."""
    plan = ctx.plan
    sizes = ctx.tab.sizes
    round_tiles = plan.round_tiles
    leaf_ptr = plan.leaf_ptr
    leaf_y = plan.leaf_y
    leaf_x = plan.leaf_x
    leaf_lvl = plan.leaf_lvl
    img = ctx.frame.img
    state = ctx.frame.state
    n = ctx.tab.tw_c.shape[0]
    r0 = plan.round_ptr[r]
    cntr = plan.round_ptr[r + 1] - r0
    scr = make_scratch(n, ctx.par.iter_max + 2)
    dummy = np.zeros((1, 1), np.float32)
    plain = (dummy, dummy)
    while True:
        q = fetch_add(counter, r)
        if q >= cntr:
            return
        t = round_tiles[r0 + q]
        # the support areas of the next two tiles of the round (the likely next one of this thread)
        for qq in range(q + 1, min(q + 3, cntr)):
            l2 = leaf_ptr[round_tiles[r0 + qq]]
            o2 = (n - sizes[leaf_lvl[l2]]) // 2
            prefetch_window(img, state, leaf_y[l2] - o2, leaf_x[l2] - o2, n)
        for li in range(leaf_ptr[t], leaf_ptr[t + 1]):
            if noisy is not None:
                if n == 16:     # the common window: the kernel specialised for n = 16
                    block16_joint(ctx, noisy, li, scr)
                else:
                    block_joint(ctx, noisy, li, scr)
            elif n == 16:
                block16(ctx, plain, li, scr)
            elif n == 32:
                block32(ctx, plain, li, scr)
            else:
                block_generic(ctx, plain, li, scr)


@njit(cache=True, nogil=True, parallel=True)
def run(frame, plan, tab, par, noisy, nthreads):
    """Steps 1-6 of the block kernel on every leaf: the rounds one after the other; the tiles of a round on
    ``nthreads`` threads. The records of ``kernel.Context``, passed one by one (numba's parallel loops take
    no nested tuples); ``noisy``: None or (wp, mest)."""
    nround = plan.round_ptr.shape[0] - 1
    counter = np.zeros(max(nround, 1), np.int64)
    for r in range(nround):
        if nthreads == 1:
            worker(Context(frame, plan, tab, par), noisy, r, counter)
            continue
        for th in prange(nthreads):
            worker(Context(frame, plan, tab, par), noisy, r, counter)
