"""A griffe extension for the API pages: the docstrings' reStructuredText roles as Markdown.

The docstrings are written for reading in the source and in ``help()``: ``:math:`...` `` for
formulas, ``.. math::`` for displayed ones, ``:func:`` / ``:class:`` / ``:mod:`` / ``:meth:`` /
``:attr:`` for references. mkdocstrings renders docstrings as Markdown, so before rendering this
turns formulas into arithmatex's ``\\( \\)`` / ``\\[ \\]`` (typeset by MathJax in the browser) and
references into optional cross-references (a link where the target has a page, plain code where
it has none, e.g. a private module; never a warning). The source files are not changed.
"""

from __future__ import annotations

import html
import re

import griffe

_ROLE = re.compile(r":(?:py:)?(func|class|mod|meth|attr|data|obj|exc):`~?([^`]+)`")
_MATH = re.compile(r":math:`([^`]+)`")
_MATH_DIRECTIVE = re.compile(r"^([ \t]*)\.\. math::[ \t]*(.*)$")


def _ref(match: re.Match) -> str:
    target = match.group(2).strip()
    if "<" in target and target.endswith(">"):  # :func:`text <target>`
        text, target = target[:-1].split("<", 1)
        text, target = text.strip(), target.strip()
    else:
        text = target
    ident = target.rstrip("()")
    return f'<autoref identifier="{html.escape(ident)}" optional><code>{html.escape(text)}</code></autoref>'


def _display_math(text: str) -> str:
    lines, out, i = text.split("\n"), [], 0
    while i < len(lines):
        m = _MATH_DIRECTIVE.match(lines[i])
        if not m:
            out.append(lines[i])
            i += 1
            continue
        indent, body = m.group(1), [m.group(2)] if m.group(2).strip() else []
        i += 1
        while i < len(lines) and (not lines[i].strip() or len(lines[i]) - len(lines[i].lstrip()) > len(indent)):
            if lines[i].strip() or body:
                body.append(lines[i].strip())
            i += 1
        while body and not body[-1]:
            body.pop()
        out += ["", f"{indent}\\[", *(f"{indent}{b}" for b in body), f"{indent}\\]", ""]
    return "\n".join(out)


def convert(text: str) -> str:
    """The docstring ``text`` with its reStructuredText roles and math as Markdown."""
    text = _display_math(text)
    text = _MATH.sub(lambda m: f"\\({m.group(1)}\\)", text)
    return _ROLE.sub(_ref, text)


class RstRoles(griffe.Extension):
    def on_object(self, *, obj: griffe.Object, **kwargs) -> None:  # every object, once loaded
        if obj.docstring is not None:
            obj.docstring.value = convert(obj.docstring.value)
