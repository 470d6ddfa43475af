"""The lock of a value-clip folder (``SHOT.clips/.lock``, :mod:`.usd_clips`): a bake holds it
exclusively while it writes (:func:`bake_lock`), a ``flatten`` shared while it reads
(:func:`reading_lock`), so that no run reads, removes or rewrites the files of another. A
``flock`` ends with its process, however it ends: a killed run leaves nothing held.
"""

import contextlib
import errno
import os
import time
from collections.abc import Iterator
from pathlib import Path

from ..errors import OutputExistsError, Param
from .usd_cache import clips_folder

__all__ = ["LOCK_FILE", "bake_lock", "reading_lock"]


LOCK_FILE = ".lock"
"""The file in a clip folder that the bake writing it holds locked (:func:`bake_lock`)."""

_BUSY = (errno.EWOULDBLOCK, errno.EAGAIN)
_NO_LOCKS = (errno.ENOLCK, errno.EOPNOTSUPP, errno.ENOSYS, errno.EINVAL)


@contextlib.contextmanager
def bake_lock(out: str | os.PathLike) -> Iterator[None]:
    """Hold ``out``'s clip folder (:func:`clips_folder`) for one bake: an exclusive ``flock`` on
    its :data:`LOCK_FILE`, released when the block ends or the process does (however it ends).
    A second bake of ``out`` (``resume`` and ``force`` included), or a :func:`flatten` of it,
    then fails at once with FileExistsError instead of reading, removing or rewriting the files
    of one still running (and a bake waits for no flatten reading the folder: it fails the same
    way). Creates the folder; removes the lock file at the end (still holding it: a run that
    opened it meanwhile finds it gone and locks the next one), and the folder when this call
    made it and it is left empty (a refused bake leaves nothing). Where the system or the file
    system has no such locks (Windows; ``ENOLCK``), nothing is locked."""
    folder = clips_folder(out)
    if folder.exists() and not folder.is_dir():
        raise NotADirectoryError(errno.ENOTDIR, "exists and is not a folder", str(folder))
    made = not folder.exists()
    folder.mkdir(parents=True, exist_ok=True)
    try:
        fd = _lock(folder / LOCK_FILE, out)
    except BaseException:
        if made:
            with contextlib.suppress(OSError):
                folder.rmdir()
        raise
    try:
        yield
    finally:
        _unlock(fd, folder / LOCK_FILE)
        if made:
            with contextlib.suppress(OSError):
                folder.rmdir()  # only when empty


@contextlib.contextmanager
def reading_lock(folder: str | os.PathLike, what: str | os.PathLike) -> Iterator[None]:
    """Hold the clip folder ``folder`` for reading (``what`` reads it: named in the refusal): a
    shared ``flock`` on its :data:`LOCK_FILE`, so that no bake writes or removes its files
    meanwhile (FileExistsError at once while a bake holds it, :func:`bake_lock`). Several
    readers may hold it together; the last one removes the lock file. A folder where no lock
    file can be made (read-only: no bake writes there either) is not locked."""
    path = Path(folder) / LOCK_FILE
    fd = _lock(path, what, shared=True)
    try:
        yield
    finally:
        _unlock(fd, path)


def _unlock(fd: int | None, path: Path) -> None:
    """Release the lock :func:`_lock` returned, removing the lock file when no other run holds
    it (still holding it: a run that opened it meanwhile finds it gone and locks the next)."""
    if fd is None:
        return
    try:
        import fcntl
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)  # (a reader: only when the last)
        if _same_inode(fd, path):
            os.unlink(path)
    except OSError:
        pass
    finally:
        os.close(fd)


def _same_inode(fd: int, path: Path) -> bool:
    st, now = os.fstat(fd), os.stat(path)
    return (st.st_dev, st.st_ino) == (now.st_dev, now.st_ino)


_READ_TRIES = 20
"""Tries of a shared lock (50 ms apart) while another run holds it for a moment (a reader
releasing it takes it exclusively to remove the lock file)."""


def _lock(path: Path, out: str | os.PathLike, shared: bool = False) -> int | None:
    """A descriptor of ``path`` holding its exclusive lock, or a shared one (None where locks do
    not exist, or, ``shared``, where no lock file can be made). ``out``: the file the run
    writes (or reads), named in the refusals."""
    try:
        import fcntl
    except ImportError:
        return None
    nofollow = getattr(os, "O_NOFOLLOW", 0)  # (a link there is not followed, nor truncated)
    for attempt in range(_READ_TRIES if shared else 8):
        try:  # made as the umask allows: another user's bake may lock it after this one
            fd = os.open(path, os.O_RDWR | os.O_CREAT | nofollow, 0o666)
        except PermissionError:  # another user's lock file (flock needs no write access)
            try:
                fd = os.open(path, os.O_RDONLY | nofollow)
            except FileNotFoundError:
                if shared:  # a folder nobody can write to: nothing to lock against
                    return None
                raise
        except FileNotFoundError:
            if shared:  # (no folder: no clips to read)
                return None
            if path.parent.is_dir():
                raise
            path.parent.mkdir(parents=True, exist_ok=True)  # the bake that made it removed it
            continue
        except OSError as exc:
            if exc.errno != errno.ELOOP:
                raise
            raise OutputExistsError(
                f"{path}: a symbolic link where dqskin keeps the lock of {Path(out).name}'s "
                "clip bake (dqskin never makes one); remove the link, then rerun (",
                Param("resume", True), " completes an interrupted bake)") from None
        try:
            fcntl.flock(fd, (fcntl.LOCK_SH if shared else fcntl.LOCK_EX) | fcntl.LOCK_NB)
        except OSError as exc:
            os.close(fd)
            if exc.errno in _NO_LOCKS:
                return None
            if exc.errno in _BUSY:
                if shared and attempt + 1 < _READ_TRIES:
                    time.sleep(0.05)
                    continue
                raise _busy(path, out, shared) from None
            raise
        try:
            if _same_inode(fd, path):
                if not shared:
                    with contextlib.suppress(OSError):  # (read-only: no pid to tell)
                        os.ftruncate(fd, 0)
                        os.write(fd, f"{os.getpid()}\n".encode())
                return fd
        except FileNotFoundError:
            pass
        os.close(fd)  # the run that held it removed it meanwhile: lock the next one
    raise OutputExistsError(f"{path}: removed and made again while locking it; rerun")


def _busy(path: Path, out: str | os.PathLike, shared: bool) -> OutputExistsError:
    """The refusal while another run holds the lock ``path`` of ``out``."""
    try:
        pid = f" (pid {int(path.read_text().strip())})"
    except (OSError, ValueError):
        pid = ""
    if shared:
        return OutputExistsError(f"{out}: a dqskin bake{pid} is writing its clips in "
                                 f"{path.parent}; let it finish, then rerun")
    return OutputExistsError(
        f"{out}: another dqskin run{pid} is writing it or reading its clips (it holds "
        f"{path}); let it finish or stop it, then rerun (", Param("resume", True),
        " completes a clip bake, ", Param("force", True), " starts over)")
