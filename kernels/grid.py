"""How the kernel modules launch: one call on CUDA, chunks of the grid from a thread pool on the
CPU.

Warp runs a CPU launch on one thread but releases the GIL, so chunks launched from Python threads
use every core. The launchers beside each kernel (``skin.skin_points``, ``fk.forward_kinematics``,
``metrics.volumes``, ...) call :func:`launch` or :func:`launch_rows`; nothing outside
``dqskin.kernels`` calls ``wp.launch``.

Grids over frames (the flat point, vector and velocity kernels of :mod:`.skin` and
:mod:`.velocity`) have one thread per row for a single frame, else one per (block of
:data:`FRAME_BLOCK` frames, row), so a row's influences are read once per block and the block's
joints stay in cache; they are launched as rows through :func:`launch_rows`.
Small grids replay a recorded launch (:class:`_Recorded`) instead of paying Warp's argument
packing on every call, which dominates small calls.
"""

import ctypes
import os
import threading
import weakref
from collections.abc import Callable, Iterable, Sequence
from concurrent.futures import ThreadPoolExecutor
from typing import Any, TypeVar

import warp as wp
import warp._src.context as _context

from .._warp import Device

__all__ = ["FRAME_BLOCK", "MIN_WORK", "beside", "cpu_threads", "is_cpu", "launch", "launch_rows",
           "run_tasks"]

FRAME_BLOCK = 16
"""Frames one thread handles on a (frame block, row) grid: the joints of 16 frames stay in L1
while every vertex of the block is skinned, and influences are read once per block."""


PIECES_PER_THREAD = 4
"""A large CPU launch is cut into pieces that the threads take in turn, each
``1 / (PIECES_PER_THREAD · threads)`` of the rows left: a thread the system slows (another
process on its core) leaves the later pieces to the others instead of the launch waiting for its
fixed share, and the last pieces are small, so the threads finish together."""


MIN_WORK = 32768
"""Row-frames below which a frame-grid launch runs on one CPU thread (a pool round trip
costs more than it saves)."""


_pool = None
_pool_lock = threading.Lock()
_A = TypeVar("_A")
_B = TypeVar("_B")

_CORES = os.cpu_count() or 1  # os.cpu_count() costs ~10 µs a call
_recorded = threading.local()
_RECORDED_MAX = 32
_RECORDED_GRID = 1 << 16  # larger grids: the packing cost is noise


def cpu_threads() -> int:
    """Threads used for CPU launches (``DQSKIN_THREADS`` or the core count)."""
    return max(1, int(os.environ.get("DQSKIN_THREADS", _CORES)))


_warm: set[tuple[wp.Kernel, str]] = set()  # (kernel, device) launched at least once in this process
_warm_lock = threading.Lock()


def _launch(kernel: wp.Kernel, dim: tuple[int, ...], args: list[Any], device: Device) -> None:
    """Replay this thread's recorded launch of ``kernel`` on ``dim`` and ``device``, else
    :func:`_record` one; the first launch of a kernel on a device holds a lock: Warp's
    ``Module.load`` is not thread-safe, and two pool threads loading one module at once can
    unload the library the other is running (an intermittent segfault). A launch this thread
    recorded (its module loaded) is replayed straight away."""
    name = device if type(device) is str else str(device)
    launches = getattr(_recorded, "launches", None)
    hit = None if launches is None else launches.pop((kernel, dim, name), None)
    if launches is not None and hit is not None:
        launches[(kernel, dim, name)] = hit  # most recent last
        if _capturing():
            wp.launch(kernel, dim=dim, inputs=args, device=device)
        else:
            hit.launch(args)
        return
    key = (kernel, name)
    if key in _warm:
        _record(kernel, dim, args, device)
        return
    with _warm_lock:
        _record(kernel, dim, args, device)
        _warm.add(key)


class _Value:
    """A by-value argument (int, float) held like a weak reference: ``held()`` returns it."""

    __slots__ = ("value",)

    def __init__(self, value):
        self.value = value

    def __call__(self):
        return self.value


def _held(a):
    """A weak reference to argument ``a`` (arrays, structs), or ``a`` itself when it cannot have
    one: a recorded launch must not keep a caller's arrays alive."""
    try:
        return weakref.ref(a)
    except TypeError:
        return _Value(a)


_DIRECT = wp.__version__.split(".")[:2] == ["1", "19"]
"""The direct entry-point call of :class:`_Recorded` copies Warp 1.19's private ``invoke``; other
Warp versions take ``Launch.launch`` (correct, a little slower a launch)."""


def _capturing():
    """Whether a Warp graph capture is active (it records launches instead of running them:
    those go through ``wp.launch``)."""
    return getattr(getattr(_context, "runtime", None), "_apic_capture", None) is not None


class _Recorded:
    """A recorded ``wp.Launch`` and (weak references to) the arguments it was last given. On the
    CPU with Warp 1.19 its ctypes argument block is built once and only arguments that changed
    are packed into it again, then the kernel's entry point is called directly
    (``Launch.launch`` builds the block on every call). A struct argument given again is
    re-copied each launch (it may have been changed in place). The record keeps no argument
    alive: the launch's own argument list is dropped, and an argument whose object died is
    packed again. Elsewhere, ``Launch.launch``."""

    __slots__ = ("cmd", "last", "block", "names", "structs", "call")

    def __init__(self, cmd, args):
        self.cmd, self.last, self.call = cmd, [_held(a) for a in args], None
        cmd.fwd_args = cmd.adj_args = None  # only a capture reads them (none is active)
        try:
            if not _DIRECT or not cmd.device.is_cpu or cmd.adjoint or cmd.block_dim > 1:
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
        except (AttributeError, TypeError):  # internals moved: its own launch
            self.call = None

    def launch(self, args):
        cmd, last, call = self.cmd, self.last, self.call
        for i, a in enumerate(args):
            if a is None or a is not last[i]():  # (a dead argument's weakref gives None too)
                cmd.set_param_at_index(i, a)
                last[i] = _held(a)
                if call is not None:
                    setattr(self.block, self.names[i], cmd.params[1 + i])
        if call is None:
            cmd.launch()
            return
        for i in self.structs:
            setattr(self.block, self.names[i], cmd.params[1 + i])
        call()


def _record(kernel, dim, args, device):
    """One ``wp.launch`` of ``kernel`` on ``dim`` with ``args`` (inputs then outputs), recorded
    for this thread (:class:`_Recorded`) so that :func:`_launch` replays the next one of the same
    kernel, grid and device without Warp's argument packing, which dominates small calls. Grids
    above :data:`_RECORDED_GRID` threads (the packing is noise there) and
    launches during a graph capture go through ``wp.launch`` unrecorded."""
    size = 1
    for d in dim:
        size *= d
    if size > _RECORDED_GRID or _capturing():
        wp.launch(kernel, dim=dim, inputs=args, device=device)
        return
    cache = getattr(_recorded, "launches", None)
    if cache is None:
        cache = _recorded.launches = {}
    if len(cache) >= _RECORDED_MAX:
        cache.pop(next(iter(cache)))  # oldest first
    hit = _Recorded(wp.launch(kernel, dim=dim, inputs=args, device=device, record_cmd=True), args)
    hit.cmd.launch()
    cache[(kernel, dim, str(device))] = hit  # most recent last


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


def run_tasks(tasks: Sequence[Callable[[], None]]) -> None:
    """Run ``tasks`` at once on the CPU thread pool and wait for them all (one task, or from a
    pool thread: in turn on this thread)."""
    if len(tasks) <= 1 or threading.current_thread().name.startswith("dqskin"):
        for t in tasks:
            t()
        return
    _pool_map([(t,) for t in tasks])


def beside(fn: Callable[[], _A], main: Callable[[], _B]) -> tuple[_A, _B]:
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


def is_cpu(device: Device) -> bool:
    """Whether ``device`` (a ``wp.Device``, a name or None) is the CPU; a Device without a
    look-up."""
    cpu = getattr(device, "is_cpu", None)
    return wp.get_device(device).is_cpu if cpu is None else cpu


def _threads_for(work, device):
    """CPU threads for ``work`` pieces of at least the minimum size: one (the environment not
    read) when there are fewer than two pieces."""
    if work < 2 or not is_cpu(device):
        return 1
    return min(cpu_threads(), work)


def launch(kernel: wp.Kernel, dim: int | Iterable[int], inputs: Sequence[Any],
           outputs: Sequence[Any], device: Device) -> None:
    """``wp.launch`` for grids that need no chunking (per joint, per frame, small images)."""
    if type(dim) is tuple:
        grid = dim
    else:
        grid = (dim,) if isinstance(dim, int) else tuple(int(d) for d in dim)
    if min(grid) > 0:
        _launch(kernel, grid, [*inputs, *outputs], device)


def launch_rows(kernel: wp.Kernel, count: int, inputs: Sequence[Any], outputs: Sequence[Any],
                device: Device, min_chunk: int = 4096, inner: tuple[int, ...] = ()) -> None:
    """Launch ``kernel`` over ``range(count)`` rows, split in chunks on the CPU: one per thread,
    or, when there is work for it, pieces that the threads take in turn, each a share of what
    is left (:func:`_guided`).

    ``kernel`` takes ``inputs``, then ``row_offset``, then ``outputs``; its grid is
    ``(rows of the chunk,) + inner``. On CUDA one launch covers everything.
    """
    if count <= 0 or any(int(d) <= 0 for d in inner):
        return

    def run(offset: int, n: int) -> None:
        _launch(kernel, (n, *inner), [*inputs, offset, *outputs], device)

    threads = _threads_for(count // min_chunk, device)
    if threads <= 1:
        run(0, count)
        return
    if count // min_chunk // threads < 2:
        bounds = [count * c // threads for c in range(threads + 1)]
        _pool_map([(run, bounds[c], bounds[c + 1] - bounds[c]) for c in range(threads)])
        return
    _pool_map([(_guided(run, count, threads, min_chunk),)] * threads)


def _guided(run: Callable[[int, int], None], count: int, threads: int,
            min_chunk: int) -> Callable[[], None]:
    """The loop each of ``threads`` threads runs over ``range(count)`` rows: take the next piece,
    ``1 / (PIECES_PER_THREAD · threads)`` of what is left but at least
    ``count / (PIECES_PER_THREAD · threads)`` rows up to ``4 · min_chunk`` (and ``min_chunk``),
    run it, until none is left. A launch of up to ``4 · min_chunk`` rows a piece is cut in
    ``PIECES_PER_THREAD`` equal pieces per thread; a larger one in pieces that shrink to
    ``4 · min_chunk`` rows as it ends, so a thread that another process slows holds it back by one
    small piece at most, at the cost of a launch a piece."""
    lock = threading.Lock()
    taken = [0]
    share = PIECES_PER_THREAD * threads
    least = max(min_chunk, min(4 * min_chunk, count // share))

    def work() -> None:
        while True:
            with lock:
                start = taken[0]
                left = count - start
                if left <= 0:
                    return
                n = max(least, left // share)
                n = left if left - n < min_chunk else n  # (no sliver left for last)
                taken[0] = start + n
            run(start, n)

    return work
