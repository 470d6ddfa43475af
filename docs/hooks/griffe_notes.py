"""Griffe extension for the API reference: prose after a docstring's sections is a Notes section.

dqskin's docstrings often close with a paragraph after ``Parameters`` / ``Returns`` /
``Attributes``; NumPy style would read it as more items of that section. This extension gives
such a paragraph (a blank line, then unindented text that does not start a new section) a
``Notes`` heading before the docstring is parsed. The docstrings themselves are unchanged.
"""

import re

import griffe

_HEADER = re.compile(r"^[A-Z][A-Za-z ]+$")


def _is_dashes(line):
    return bool(line.strip()) and set(line.strip()) == {"-"}


def add_notes_heading(text):
    """``text`` with a ``Notes`` heading before prose that follows a section's items."""
    lines = text.split("\n")
    out, in_section, notes = [], False, False
    for i, line in enumerate(lines):
        nxt = lines[i + 1] if i + 1 < len(lines) else ""
        if line.strip() and _is_dashes(nxt) and _HEADER.match(line.strip()):
            in_section = True
            notes = line.strip().lower() in ("notes", "examples", "references", "see also")
        elif (in_section and not notes and line.strip() and not line.startswith(" ")
              and i > 0 and not lines[i - 1].strip()):
            out += ["Notes", "-----"]
            notes = True
        out.append(line)
    return "\n".join(out)


class ProseAsNotes(griffe.Extension):
    """Apply :func:`add_notes_heading` to every docstring griffe loads."""

    def on_instance(self, *, obj, **kwargs):
        if obj.docstring is not None:
            obj.docstring.value = add_notes_heading(obj.docstring.value)
