"""Griffe extension for the API reference: dqskin's docstrings as mkdocstrings' NumPy parser
reads them. The docstrings themselves are unchanged; each is rewritten before it is parsed:

* Prose after a docstring's sections (a blank line, then unindented text that does not start a
  new section) gets a ``Notes`` heading; NumPy style would read it as more items of the section.
* A parameter typed ``name : {"a", "b"} or None`` reads ``one of {...}``: the NumPy parser takes
  a leading ``{...}`` as choices whose first is the default, which dqskin's docstrings do not
  mean (the default shown is then the signature's).
* Sphinx roles (``:func:`dqskin.load```, ``:class:`~.scene.Scene```) become inline code.
"""

import re

import griffe

_HEADER = re.compile(r"^[A-Z][A-Za-z ]+$")
_CHOICES = re.compile(r"^(\s*\*{0,2}\w+(?:, \*{0,2}\w+)* : )\{")
_ROLE = re.compile(r":(?:py:)?[a-z]+:`(~?)([^`]+)`")
_PARAMETER_SECTIONS = ("parameters", "other parameters", "attributes")


def _is_dashes(line):
    return bool(line.strip()) and set(line.strip()) == {"-"}


def _code(match):
    target = match[2].split("<")[0].strip() if "<" in match[2] else match[2]
    if match[1]:
        target = target.rsplit(".", 1)[-1]
    return f"``{target.lstrip('.')}``"


def rewrite(text):
    """``text`` with the three rewrites of this module applied."""
    lines = _ROLE.sub(_code, text).split("\n")
    out, section = [], None
    for i, line in enumerate(lines):
        nxt = lines[i + 1] if i + 1 < len(lines) else ""
        if line.strip() and _is_dashes(nxt) and _HEADER.match(line.strip()):
            section = line.strip().lower()
        elif (section not in (None, "notes", "examples", "references", "see also")
              and line.strip() and not line.startswith(" ") and i > 0 and not lines[i - 1].strip()):
            out += ["Notes", "-----"]
            section = "notes"
        elif section in _PARAMETER_SECTIONS:
            line = _CHOICES.sub(r"\1one of {", line)
        out.append(line)
    return "\n".join(out)


class NumpyDocstrings(griffe.Extension):
    """Apply :func:`rewrite` to every docstring griffe loads."""

    def on_instance(self, *, obj, **kwargs):
        if obj.docstring is not None:
            obj.docstring.value = rewrite(obj.docstring.value)
