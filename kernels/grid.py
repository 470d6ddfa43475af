"""How the kernel modules launch: one call on CUDA, chunks of the grid from a thread pool on the
CPU.

Warp runs a CPU launch on one thread but releases the GIL, so chunks launched from Python threads
use every core. The launchers beside each kernel (``skin.skin_points``, ``fk.forward_kinematics``,
``metrics.volumes``, ...) call :func:`launch_blocks` or :func:`launch_rows`; nothing outside
``dqskin.kernels`` calls ``wp.launch``.

Grids over frames are (frame block, row): a thread handles one row (vertex, vector) for
:data:`FRAME_BLOCK` frames, so its influences are read once per block and the block's joints stay
in cache. Kernels on such a grid take a :class:`FrameBlocks` after their inputs and loop over
:func:`block_frames`.
"""

import ctypes
import os
import threading
from concurrent.futures import ThreadPoolExecutor

import warp as wp

__all__ = ["CPU_ROW_BLOCK", "FRAME_BLOCK", "MIN_WORK", "FrameBlocks", "block_frames", "block_rows",
           "beside", "cpu_threads", "launch", "launch_blocks", "launch_rows"]

FRAME_BLOCK = 16
"""Frames one thread handles on a (frame block, row) grid: the joints of 16 frames stay in L1
while every vertex of the block is skinned, and influences are read once per block."""



@wp.struct
class FrameBlocks:
    """The part of a (frame block, row) grid one launch covers (:func:`launch_blocks` fills it)."""

    frame_block: int
    """Frames per thread."""
    block_offset: int
    """First frame block of the launch."""
    row_offset: int
    """First row of the launch."""
    row_block: int
    """Rows per thread (:func:`block_rows`; 0 or 1: one)."""
    row_end: int
    """End of the launch's rows (:func:`block_rows`; 0: the grid's)."""


@wp.func
def block_frames(blocks: FrameBlocks, block: int, frame_count: int):
    """``(first frame, end frame, row offset)`` of grid block ``block`` of a launch."""
    first = (block + blocks.block_offset) * blocks.frame_block
    return first, wp.min(first + blocks.frame_block, frame_count), blocks.row_offset


@wp.func
def block_rows(blocks: FrameBlocks, i: int, row_count: int):
    """``(first row, end row)`` of grid column ``i`` of a launch whose threads handle
    ``blocks.row_block`` rows each (``row_count``: the rows of the whole grid)."""
    n = wp.max(blocks.row_block, 1)
    start = blocks.row_offset + i * n
    end = row_count
    if blocks.row_end > 0:
        end = blocks.row_end
    return start, wp.min(start + n, end)


MIN_WORK = 32768
"""Row-frames below which :func:`launch_blocks` launches on one CPU thread (a pool round trip
costs more than it saves)."""


CPU_ROW_BLOCK = 64
"""Rows per thread of row-blocked kernels on the CPU: a Warp CPU launch calls the kernel once per
thread, copying every argument (array descriptors, structs) and splitting the thread index, which
costs as much as skinning a vertex; 64 rows per call amortize it. One row per thread on CUDA."""


_pool = None
_pool_lock = threading.Lock()
_CORES = os.cpu_count() or 1  # os.cpu_count() costs ~10 µs a call
_recorded = threading.local()
_RECORDED_MAX = 32
_RECORDED_GRID = 1 << 16  # larger grids: the packing cost is noise, and no arrays are kept alive


def cpu_threads():
    """Threads used for CPU launches (``DQSKIN_THREADS`` or the core count)."""
    return max(1, int(os.environ.get("DQSKIN_THREADS", _CORES)))


_warm = set()  # (kernel, device) launched at least once in this process
_warm_lock = threading.Lock()


def _launch(kernel, dim, args, device):
    """:func:`_replay`, but the first launch of a kernel on a device holds a lock: Warp's
    ``Module.load`` is not thread-safe, and two pool threads loading one module at once can
    unload the library the other is running (an intermittent segfault). A launch this thread
    recorded (its module loaded) is replayed straight away."""
    name = device if type(device) is str else str(device)
    launches = getattr(_recorded, "launches", None)
    hit = None if launches is None else launches.pop((kernel, dim, name), None)
    if hit is not None:
        hit.launch(args)
        launches[(kernel, dim, name)] = hit  # most recent last
        return
    key = (kernel, name)
    if key in _warm:
        _replay(kernel, dim, args, device)
        return
    with _warm_lock:
        _replay(kernel, dim, args, device)
        _warm.add(key)


class _Recorded:
    """A recorded ``wp.Launch`` and the arguments it was last given. On the CPU its ctypes
    argument block is built once and only arguments that changed are packed into it again, then
    the kernel's entry point is called directly (~0.3 µs; ``Launch.launch`` builds the block on
    every call, ~4 µs). A struct argument given again is re-copied each launch (it may have been
    changed in place). Without the Warp internals this needs, ``Launch.launch``."""

    __slots__ = ("cmd", "last", "block", "names", "structs", "call")

    def __init__(self, cmd, args):
        self.cmd, self.last, self.call = cmd, list(args), None
        try:
            if not cmd.device.is_cpu or cmd.adjoint or cmd.block_dim > 1:
                return
            params = cmd.params
            self.names = [a.label for a in cmd.kernel.adj.args]
            fields = [(n, type(params[1 + i])) for i, n in enumerate(self.names)]
            self.block = type("ArgsStruct", (ctypes.Structure,), {"_fields_": fields})()
            for i, n in enumerate(self.names):
                setattr(self.block, n, params[1 + i])
            self.structs = [i for i, a in enumerate(args) if hasattr(a, "_ctype")]
            forward, bounds, block = cmd.hooks.forward, ctypes.byref(params[0]), \
                ctypes.byref(self.block)
            self.call = lambda: forward(bounds, block)
        except (AttributeError, TypeError):  # another Warp: its own launch
            self.call = None

    def launch(self, args):
        cmd, last, call = self.cmd, self.last, self.call
        for i, a in enumerate(args):
            if a is not last[i]:
                cmd.set_param_at_index(i, a)
                last[i] = a
                if call is not None:
                    setattr(self.block, self.names[i], cmd.params[1 + i])
        if call is None:
            cmd.launch()
            return
        for i in self.structs:
            setattr(self.block, self.names[i], cmd.params[1 + i])
        call()


def _replay(kernel, dim, args, device):
    """One ``wp.launch`` of ``kernel`` on ``dim`` with ``args`` (inputs then outputs), replayed
    from a recorded launch of the same kernel, grid and device (per thread, :class:`_Recorded`):
    a few µs instead of ~40 µs of argument packing, which dominates small calls. Grids above
    :data:`_RECORDED_GRID` threads launch directly (a recorded launch keeps its arrays alive
    until it is replaced)."""
    size = 1
    for d in dim:
        size *= d
    if size > _RECORDED_GRID:
        wp.launch(kernel, dim=dim, inputs=args, device=device)
        return
    cache = getattr(_recorded, "launches", None)
    if cache is None:
        cache = _recorded.launches = {}
    key = (kernel, dim, str(device))
    hit = cache.pop(key, None)
    if hit is None:
        if len(cache) >= _RECORDED_MAX:
            cache.pop(next(iter(cache)))  # oldest first
        hit = _Recorded(wp.launch(kernel, dim=dim, inputs=args, device=device, record_cmd=True),
                        args)
        hit.cmd.launch()
    else:
        hit.launch(args)
    cache[key] = hit  # most recent last


def _get_pool():
    global _pool
    with _pool_lock:
        if _pool is None:
            _pool = ThreadPoolExecutor(max_workers=cpu_threads(), thread_name_prefix="dqskin")
    return _pool


def _pool_map(tasks):
    pool = _get_pool()
    for fut in [pool.submit(*t) for t in tasks]:
        fut.result()


def beside(fn, main):
    """``(fn(), main())`` with ``fn`` on a pool thread while ``main`` runs on this one (both
    release the GIL for the work that matters, e.g. NumPy reductions); sequential on one core or
    from a pool thread (no waiting on the pool from inside it). An exception of ``main`` is
    raised first, then one of ``fn``."""
    if cpu_threads() < 2 or threading.current_thread().name.startswith("dqskin"):
        return fn(), main()
    fut = _get_pool().submit(fn)
    try:
        second = main()
    finally:
        first = fut.exception()  # waits
    if first is not None:
        raise first
    return fut.result(), second


def _is_cpu(device):
    """Whether ``device`` (a ``wp.Device``, a name or None) is the CPU; a Device without a
    look-up."""
    cpu = getattr(device, "is_cpu", None)
    return wp.get_device(device).is_cpu if cpu is None else cpu


def _threads_for(work, device):
    """CPU threads for ``work`` pieces of at least the minimum size: one (the environment not
    read) when there are fewer than two pieces."""
    if work < 2 or not _is_cpu(device):
        return 1
    return min(cpu_threads(), work)


def launch(kernel, dim, inputs, outputs, device):
    """``wp.launch`` for grids that need no chunking (per joint, per frame, small images)."""
    if type(dim) is not tuple:
        dim = (dim,) if isinstance(dim, int) else tuple(int(d) for d in dim)
    if min(dim) > 0:
        _launch(kernel, dim, [*inputs, *outputs], device)


_parts = {}  # FrameBlocks by their fields: building a Warp struct costs ~10 µs a call


def _frame_blocks(block_offset, row_offset, row_block, row_end):
    """The :class:`FrameBlocks` of a launch, built once per distinct value (never modified)."""
    key = (block_offset, row_offset, row_block, row_end)
    part = _parts.get(key)
    if part is None:
        if len(_parts) >= 256:
            _parts.clear()
        part = FrameBlocks()
        part.frame_block, part.block_offset, part.row_offset = FRAME_BLOCK, block_offset, row_offset
        part.row_block, part.row_end = row_block, row_end
        _parts[key] = part
    return part


def launch_blocks(kernel, rows, frames, inputs, outputs, device, min_work=None,
                  row_blocks=False):
    """Launch ``kernel`` over ``ceil(frames / FRAME_BLOCK)`` frame blocks × ``rows``.

    ``kernel`` takes ``inputs``, then a :class:`FrameBlocks`, then ``outputs``. With
    ``row_blocks`` (a kernel looping over :func:`block_rows`) a CPU thread handles
    :data:`CPU_ROW_BLOCK` rows.
    On CUDA one launch covers the grid. On the CPU, above ``min_work`` row-frames
    (:data:`MIN_WORK` by default), the grid is split along its longer axis into one piece per
    core, launched from a thread pool.
    """
    if rows <= 0 or frames <= 0:
        return
    min_work = MIN_WORK if min_work is None else min_work
    blocks = -(-frames // FRAME_BLOCK)

    per_thread = CPU_ROW_BLOCK if row_blocks and _is_cpu(device) else 1

    def run(block_offset, block_count, row_offset, row_count):
        part = _frame_blocks(block_offset, row_offset, per_thread, row_offset + row_count)
        _launch(kernel, (block_count, -(-row_count // per_thread)), [*inputs, part, *outputs],
                device)

    chunks = _threads_for(rows * frames // min_work, device)
    if chunks <= 1:
        run(0, blocks, 0, rows)
    elif blocks >= chunks and blocks * FRAME_BLOCK >= rows:
        cut = [blocks * c // chunks for c in range(chunks + 1)]
        _pool_map([(run, cut[c], cut[c + 1] - cut[c], 0, rows) for c in range(chunks)])
    else:
        cut = [rows * c // chunks for c in range(chunks + 1)]
        _pool_map([(run, 0, blocks, cut[c], cut[c + 1] - cut[c]) for c in range(chunks)])


def launch_rows(kernel, count, inputs, outputs, device, min_chunk=4096, inner=()):
    """Launch ``kernel`` over ``range(count)`` rows, split in chunks on the CPU.

    ``kernel`` takes ``inputs``, then ``row_offset``, then ``outputs``; its grid is
    ``(rows of the chunk,) + inner``. On CUDA one launch covers everything.
    """
    if count <= 0 or any(int(d) <= 0 for d in inner):
        return

    def run(offset, n):
        _launch(kernel, (n, *inner), [*inputs, offset, *outputs], device)

    chunks = _threads_for(count // min_chunk, device)
    if chunks <= 1:
        run(0, count)
        return
    bounds = [count * c // chunks for c in range(chunks + 1)]
    _pool_map([(run, bounds[c], bounds[c + 1] - bounds[c]) for c in range(chunks)])
