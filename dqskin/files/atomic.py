"""The one output-writing path: every file dqskin writes appears under its final name only when
complete, and a failed or interrupted write leaves nothing behind.

* :class:`atomic_path`: a temporary file beside the target (``.STEM.XXXXXXXX/NAME``: a new private
  folder in the same folder, so the final rename is atomic), moved onto the target by
  :meth:`~atomic_path.commit`; removed with its folder by :meth:`~atomic_path.discard` (or the
  ``with`` block's exception). Errors name the target, never the temporary file.
  The temporary file does not exist until the writer creates it. Writers that save through their
  own temporary file and a rename (USD's ``Export``) would otherwise rename onto an existing empty
  file, and ext4 (``auto_da_alloc``) then writes the whole new file to disk before the rename
  returns, several times slower than the export itself. Their own temporary files land in the
  private folder too, so an error leaves nothing (:meth:`~atomic_path.discard` removes the
  folder) and a killed process one folder (clip bakes remove their own when they resume or
  finish). Replacing an existing target (``overwrite``) still pays the flush once, in the final
  rename.
* Exclusive claim (``overwrite=False``): the temporary file is put in place with ``os.link``,
  which fails if the target exists. Of two runs writing the same new file, the one that finishes
  second gets :class:`FileExistsError` instead of silently replacing the other's finished file,
  whichever started first; nothing to go stale (no lock files). With ``overwrite=True``
  (``--force``) the last writer wins through ``os.replace``: never a partial file.
* :class:`atomic_group`: several files (one per frame) committed together at the end, so a set is
  all there or not at all.
* :class:`atomic_folder`: a whole folder (a report) written in a private temporary folder and
  renamed into place, replacing an earlier one only when it is complete.
* Interrupts: a signal handler (the CLI's, :mod:`dqskin.cli`) calls :func:`interrupt` with the
  exception to raise. Inside :func:`critical` blocks (claiming, committing and removing temporary
  files) the exception is deferred to the end of the block, so those steps are never cut in
  half; once an interrupt happened nothing claims or commits a file any more
  (:func:`check_interrupted`), even if some library swallowed the exception.
"""

import abc
import contextlib
import errno
import os
import shutil
import tempfile
from collections.abc import Iterator
from pathlib import Path
from types import TracebackType
from typing import Literal, TypeVar

from ..errors import OutputExistsError, Param

__all__ = ["CommitOnSuccess", "atomic_folder", "atomic_group", "atomic_path", "check_interrupted",
           "check_parent", "critical", "finished", "interrupt", "named_error", "reset_interrupt"]

_Writer = TypeVar("_Writer", bound="CommitOnSuccess")


class _State:
    """Interrupt bookkeeping of the process: open :func:`critical` blocks, the interrupt to raise
    when the outermost ends, the interrupt :func:`interrupt` recorded."""

    depth: int = 0
    pending: BaseException | None = None
    interrupted: BaseException | None = None
    finished: bool = False


_state = _State()


def interrupt(exc: BaseException) -> None:
    """Record an interrupt and raise ``exc`` now, or at the end of the current :func:`critical`
    block; ignored once the run's output is in place (:func:`finished`). For signal handlers
    (main thread)."""
    if _state.finished:
        return
    _state.interrupted = exc
    if _state.depth:
        _state.pending = exc
        return
    raise exc


def reset_interrupt() -> None:
    """Forget a recorded interrupt and a finished output (a new run in the same process)."""
    _state.pending = _state.interrupted = None
    _state.finished = False


def finished() -> bool:
    """Whether the run's last output was committed (:meth:`atomic_path.commit` with ``final``):
    an interrupt from then on is ignored, so a run that leaves its complete output says it
    succeeded."""
    return _state.finished


def check_interrupted() -> None:
    """Raise the interrupt :func:`interrupt` was given, if any (some libraries, trimesh's
    exporters among them, catch ``BaseException`` and so swallow it): writers call this between
    steps, and nothing claims or commits a file after an interrupt."""
    exc = _state.interrupted
    if exc is not None:
        raise exc


@contextlib.contextmanager
def critical() -> Iterator[None]:
    """A block an interrupt does not cut: the exception :func:`interrupt` is given is raised when
    the outermost block ends."""
    _state.depth += 1
    try:
        yield
    finally:
        _state.depth -= 1
        if _state.depth == 0 and _state.pending is not None:
            exc, _state.pending = _state.pending, None
            raise exc


def _umask() -> int:
    """The process umask, read without changing it (Linux ``/proc``), else set-and-restore."""
    try:
        with open("/proc/self/status") as fh:
            for line in fh:
                if line.startswith("Umask:"):
                    return int(line.split()[1], 8)
    except OSError:
        pass
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def check_parent(path: str | os.PathLike) -> Path:
    """``path`` as a Path; NotADirectoryError when a folder above it exists but is not a folder
    (``--out in.glb/x.usdc``). Missing folders are fine (writers create them)."""
    path = Path(path)
    for anc in path.parents:
        if anc.exists():
            if not anc.is_dir():
                raise NotADirectoryError(errno.ENOTDIR, f"{anc} is not a directory", str(path))
            break
    if path.is_dir():
        raise IsADirectoryError(errno.EISDIR, "is a directory", str(path))
    return path


def _cannot_write(path: Path, exc: OSError) -> OSError:
    """``exc`` (an OSError about the temporary file) as an OSError naming ``path``, with its
    ``errno`` (the command line reports it as a system error, not as a bug)."""
    error = type(exc)(f"{path}: cannot write ({exc.strerror or exc})")
    error.errno = exc.errno
    return error


class atomic_path:
    """A temporary path beside ``path``, moved onto it when complete.

    As a context manager: yields the temporary path, commits on success, removes it on an
    exception (``path`` is then left as it was). Or call :meth:`open`, :meth:`commit` and
    :meth:`discard` yourself (a writer holding its claim over many steps).

    The temporary file keeps the target's name (in a private folder beside it), so
    format-sniffing writers (USD, trimesh) work; the writer creates it.

    Parameters
    ----------
    path : str or os.PathLike
    overwrite : bool
        True: replace an existing ``path`` (the last writer wins). False: exclusive; commit raises
        FileExistsError if ``path`` exists by then (created by another run meanwhile).
    final : bool
        The run's last output: :meth:`commit` marks the run finished (:func:`finished`).
    """

    def __init__(self, path: str | os.PathLike, *, overwrite: bool = True,
                 final: bool = False) -> None:
        self.path = Path(path)
        self.overwrite = overwrite
        self.final = final
        self.tmp: Path | None = None

    def open(self) -> Path:
        """Create the private temporary folder (and missing folders); returns the temporary
        file's path in it (not created: the writer creates it)."""
        if self.tmp is not None:
            return self.tmp
        check_interrupted()
        _state.finished = False  # (another output: the run goes on)
        path = check_parent(self.path)
        try:
            with critical():  # an interrupt here is raised after self.tmp is known
                self.tmp = _private_folder(path, f".{path.stem}.") / path.name
        except BaseException:
            self.discard()
            raise
        return self.tmp

    def commit(self, final: bool | None = None) -> Path:
        """Move the temporary file onto ``path`` (exclusively unless ``overwrite``). ``final``
        (default: the constructor's): the run's last output; an interrupt arriving from the
        moment this commit starts is dropped once the file is in place (:func:`finished`): the
        complete output stays, and the run ends as a success (an interrupt before it leaves
        nothing)."""
        final = self.final if final is None else final
        if self.tmp is None:
            raise RuntimeError(f"{self.path}: nothing to commit (open() first)")
        with critical():
            tmp, path = self.tmp, self.path
            try:
                check_interrupted()  # nothing commits after an interrupt
                if not tmp.exists():
                    raise OSError(errno.ENOENT, "the writer created no file")
                os.chmod(tmp, 0o666 & ~_umask())  # the usual file mode (USD's temporary is 0600)
                if self.overwrite:
                    os.replace(tmp, path)
                else:
                    _link_exclusive(tmp, path)
                _remove_folder(tmp.parent)
                if final:
                    _state.finished = True
                    _state.pending = _state.interrupted = None
            except FileExistsError:
                self.discard()
                raise OutputExistsError(f"{path}: exists (written by another run meanwhile?); "
                                        "use ", Param("force", True), " to overwrite") from None
            except OSError as exc:
                self.discard()
                raise _cannot_write(path, exc) from None
            except BaseException:
                self.discard()
                raise
            self.tmp = None
        return path

    def discard(self) -> None:
        """Remove the temporary file (if any)."""
        with critical():
            if self.tmp is not None:
                _remove_folder(self.tmp.parent)
                self.tmp = None

    def __enter__(self) -> Path:
        return self.open()

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> Literal[False]:
        if exc_type is None:
            self.commit()
            return False
        tmp = self.tmp
        self.discard()
        if (isinstance(exc, OSError) and exc.errno is not None and tmp is not None
                and exc.filename in (None, str(tmp))):
            raise _cannot_write(self.path, exc) from None
        return False


def _private_folder(path: Path, prefix: str) -> Path:
    """A new private folder beside ``path`` named ``prefix`` + random characters (the folders
    above it created first); errors name ``path``."""
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise type(exc)(f"{path}: cannot create folder {path.parent} "
                        f"({exc.strerror or exc})") from None
    try:
        return Path(tempfile.mkdtemp(prefix=prefix, dir=path.parent))
    except OSError as exc:
        raise _cannot_write(path, exc) from None


def _remove_folder(folder: Path) -> None:
    """Remove a temporary folder of :class:`atomic_path` and whatever a writer left in it."""
    shutil.rmtree(folder, ignore_errors=True)


def _link_exclusive(tmp: Path, path: Path) -> None:
    """Put ``tmp`` at ``path`` unless ``path`` exists (FileExistsError); ``tmp`` is gone after."""
    try:
        os.link(tmp, path)
    except FileExistsError:
        raise
    except OSError as exc:
        if exc.errno not in (errno.EPERM, errno.ENOTSUP, errno.EOPNOTSUPP, errno.EMLINK,
                             errno.ENOSYS):
            raise
        # no hard links here (FAT, some network file systems): claim the name, then replace it
        # (the claimed name is an empty file for the length of one rename)
        os.close(os.open(path, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o666))
        os.replace(tmp, path)
        return
    with contextlib.suppress(OSError):
        os.unlink(tmp)


class CommitOnSuccess(abc.ABC):
    """Context-manager protocol of the multi-file writers: ``commit()`` when the block ends
    normally, ``discard()`` on any exception (interrupts included). A system error that names no
    file (a full disk while writing) is raised naming :attr:`target` when a writer sets it."""

    target: Path | None = None
    """The file a writer of one output writes (named by its system errors)."""

    @abc.abstractmethod
    def commit(self) -> object:
        """Put what was written in place."""

    @abc.abstractmethod
    def discard(self) -> None:
        """Remove what was written."""

    def __enter__(self: _Writer) -> _Writer:
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> Literal[False]:
        try:
            if exc_type is None:
                self.commit()
            else:
                self.discard()
        except OSError as error:
            raise named_error(self.target, error) from None
        if isinstance(exc, OSError):
            named = named_error(self.target, exc)
            if named is not exc:
                raise named from None
        return False


def named_error(path: str | os.PathLike | None, exc: OSError) -> OSError:
    """``exc`` naming ``path`` when it is a system error that names no file (a full disk while
    writing ``path``), else ``exc`` itself."""
    if path is None or exc.errno is None or exc.filename is not None:
        return exc
    return _cannot_write(Path(path), exc)


class atomic_group(CommitOnSuccess):
    """Several files that appear together: :meth:`add` one temporary path per file, write them,
    then :meth:`commit` puts all in place (or, with the context manager, an exception removes
    them all).

    With ``overwrite=False`` a file that exists by commit time (another run) fails the commit and
    the files this group already put in place are taken back, so the set never mixes two runs.
    """

    def __init__(self, *, overwrite: bool = True) -> None:
        self.overwrite = overwrite
        self.members: list[atomic_path] = []

    def add(self, path: str | os.PathLike) -> Path:
        """Claim ``path``: returns the temporary path to write it to."""
        member = atomic_path(path, overwrite=self.overwrite)
        self.members.append(member)
        return member.open()

    def commit(self) -> list[Path]:
        """Put every file in place; returns their paths."""
        done: list[Path] = []
        with critical():
            try:
                for m in self.members:
                    done.append(m.commit())
            except BaseException:
                if not self.overwrite:  # ours alone: created exclusively by this group
                    for p in done:
                        with contextlib.suppress(OSError):
                            p.unlink()
                self.discard()
                raise
        self.members = []
        return done

    def discard(self) -> None:
        with critical():
            for m in self.members:
                m.discard()
            self.members = []



class atomic_folder(CommitOnSuccess):
    """A folder that appears whole: everything is written into a private temporary folder beside
    ``path`` (``.NAME.XXXXXXXX``), which :meth:`commit` renames onto ``path``; :meth:`discard`
    (or an exception in the ``with`` block, interrupts included) removes it, leaving ``path`` as
    it was.

    Parameters
    ----------
    path : str or os.PathLike
        The folder to write.
    overwrite : bool
        False: commit raises :class:`~dqskin.errors.OutputExistsError` if ``path`` exists by then
        and is not an empty folder (an empty one is replaced). True: an existing ``path`` is
        replaced whole (moved aside, the new folder renamed in, the old one removed); whether it
        may be replaced is the caller's to check first.
    """

    def __init__(self, path: str | os.PathLike, *, overwrite: bool = False) -> None:
        self.path = Path(os.path.abspath(path))  # ("." has no name to put a folder beside)
        self.overwrite = overwrite
        self.tmp: Path | None = None

    def open(self) -> Path:
        """Create the temporary folder (and missing folders above ``path``); returns it."""
        if self.tmp is not None:
            return self.tmp
        check_interrupted()
        path = self.path
        if not path.is_dir():
            check_parent(path)  # (a file above it)
        if path.exists() and not path.is_dir():
            raise NotADirectoryError(errno.ENOTDIR, "exists and is not a directory", str(path))
        try:
            with critical():
                self.tmp = _private_folder(path, f".{path.name}.")
        except BaseException:
            self.discard()
            raise
        return self.tmp

    def __enter__(self) -> "atomic_folder":  # (the folder is open once inside the block)
        self.open()
        return self

    def commit(self) -> Path:
        """Rename the temporary folder onto ``path`` (see ``overwrite``); returns ``path``."""
        if self.tmp is None:
            raise RuntimeError(f"{self.path}: nothing to commit (open() first)")
        with critical():
            tmp, path = self.tmp, self.path
            aside: Path | None = None
            try:
                check_interrupted()  # nothing commits after an interrupt
                os.chmod(tmp, 0o777 & ~_umask())  # the usual folder mode (mkdtemp's is 0700)
                if self.overwrite and path.is_dir() and any(path.iterdir()):
                    aside = Path(tempfile.mkdtemp(prefix=f".{path.name}.old.", dir=path.parent))
                    os.rename(path, aside / path.name)
                try:
                    os.rename(tmp, path)  # onto nothing or an empty folder
                except BaseException:
                    if aside is not None:  # put the old folder back
                        os.rename(aside / path.name, path)
                        _remove_folder(aside)
                        aside = None
                    raise
            except OSError as exc:
                self.discard()
                if exc.errno in (errno.ENOTEMPTY, errno.EEXIST):
                    raise OutputExistsError(f"{path}: exists (written by another run "
                                            "meanwhile?); use ", Param("force", True),
                                            " to overwrite") from None
                raise _cannot_write(path, exc) from None
            except BaseException:
                self.discard()
                raise
            self.tmp = None
            if aside is not None:
                _remove_folder(aside)
        return path

    def discard(self) -> None:
        """Remove the temporary folder and everything in it (if any)."""
        with critical():
            if self.tmp is not None:
                _remove_folder(self.tmp)
                self.tmp = None
