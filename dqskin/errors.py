"""The errors dqskin raises on purpose: one base class, a few kinds a caller can tell apart.

* :class:`DqskinError`: the base of every error dqskin raises about its input, its outputs or
  its limits. Anything else that escapes dqskin is a bug (the CLI exits 70 for it).
* :class:`InputError` (also a ``ValueError``, so ``except ValueError`` keeps working): a file,
  prim, field or argument that cannot be used; :class:`LimitError`: an input beyond a size or
  count limit (raise the limit, or ask for less); :class:`UnknownNameError` (also a
  ``KeyError``, as a failed lookup by name is in Python): a name the input lacks (a mesh of a
  scene).
* :class:`OutputExistsError` (also a ``FileExistsError``): an output refused because something
  is already there (``force=True`` replaces what dqskin made; never an input).
* :class:`DqskinError` itself: what dqskin depends on failed, not the input (a Dask scheduler
  that cannot be reached, worker processes that keep dying).
* :class:`Interrupted`: SIGINT or SIGTERM. It is a ``KeyboardInterrupt``, not a
  :class:`DqskinError`, so that ``except Exception`` in any library lets it through.

Messages name what the caller typed: an argument is written as a :class:`Param`, which reads
``force=True`` in ``str(exc)`` (the Python API) and ``--force`` in :meth:`DqskinError.message`
with the command line's flag table (:mod:`dqskin.cli`).
"""

from __future__ import annotations

import enum
import os
from collections.abc import Callable
from dataclasses import dataclass

__all__ = ["DqskinError", "InputError", "Interrupted", "LimitError", "OutputExistsError",
           "Param", "UnknownNameError", "output_exists"]


class _Unset(enum.Enum):  # an enum member pickles as itself (a bare object() would not)
    NO_VALUE = 0


_NO_VALUE = _Unset.NO_VALUE


@dataclass(frozen=True)
class Param:
    """An API parameter (and optionally its value) named in an error message.

    ``str(Param("force", True))`` is ``force=True``; the CLI spells it with its flag table
    (``--force``).
    """

    name: str
    value: object = _NO_VALUE

    def __str__(self) -> str:
        if self.value is _NO_VALUE:
            return self.name
        value = os.fspath(self.value) if isinstance(self.value, os.PathLike) else self.value
        return f"{self.name}={value!r}"

    @property
    def has_value(self) -> bool:
        """Whether the message names a value, not only the parameter."""
        return self.value is not _NO_VALUE


Spelling = Callable[[Param], str]
"""How a front end writes a :class:`Param` (the CLI: as its flag)."""


class DqskinError(Exception):
    """Base of the errors dqskin raises on purpose.

    Parameters
    ----------
    *parts : str or Param
        The message, in pieces: text, and the parameters it names (:class:`Param`), joined
        without separators. ``str(exc)`` spells parameters as Python arguments.
    """

    def __init__(self, *parts: str | Param) -> None:
        self.parts: tuple[str | Param, ...] = parts
        super().__init__(self.message())

    def message(self, spell: Spelling = str) -> str:
        """The message with each :class:`Param` written by ``spell`` (default: ``name=value``)."""
        return "".join(p if isinstance(p, str) else spell(p) for p in self.parts)

    def __str__(self) -> str:  # not KeyError's repr() of the message (UnknownNameError)
        return self.message()

    def __reduce__(self):  # pickled across Dask workers: rebuilt from its parts
        return (type(self), self.parts)


class InputError(DqskinError, ValueError):
    """A file, prim, field or argument that cannot be used; the message names it."""


class LimitError(InputError):
    """An input beyond one of dqskin's size or count limits; the message names the limit."""


class UnknownNameError(InputError, KeyError):
    """A name (a mesh of a scene) that the input does not hold; the message lists those it does.

    Also a ``KeyError``, as a failed lookup by name is in Python (``except KeyError`` catches it).
    """


class OutputExistsError(DqskinError, FileExistsError):
    """An output refused because something is already there (and ``force`` was not given)."""


def output_exists(path: str | os.PathLike, param: str = "force") -> OutputExistsError:
    """The refusal of an existing output ``path``: "PATH: exists (use force=True to overwrite)",
    naming the boolean parameter ``param`` that allows it."""
    return OutputExistsError(f"{os.fspath(path)}: exists (use ", Param(param, True),
                             " to overwrite)")


class Interrupted(KeyboardInterrupt):
    """SIGINT or SIGTERM, raised in the main thread; ``exit_code`` is ``128 + signum``.

    A ``KeyboardInterrupt`` (not a :class:`DqskinError`): code that catches ``Exception`` lets
    it through, as it does Ctrl-C.
    """

    def __init__(self, signum: int) -> None:
        super().__init__(signum)
        self.signum = int(signum)
        self.exit_code = 128 + self.signum
