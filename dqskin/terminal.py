"""Text from inputs made safe to print: names (joints, prims, meshes, clips, files) come from the
files dqskin reads, and a control character in one (an escape sequence, a carriage return, a
newline) would otherwise act on the terminal: clear it, retitle it, or forge a line of output.

:func:`printable` is the one helper every line the command line prints from input data passes
through (``dqskin info``, the ``dqskin: error: ...`` line).
"""

__all__ = ["printable"]


def printable(text: object) -> str:
    """``str(text)`` with every non-printable character (control characters, line and
    paragraph separators, format characters such as bidirectional overrides) written as a Python
    escape (``\\x1b``, ``\\n``, ``\\u202e``); printable text, non-ASCII letters included, is
    returned unchanged."""
    s = str(text)
    if s.isprintable():
        return s
    return "".join(c if c.isprintable() else repr(c)[1:-1] for c in s)
