"""Griffe extension: splatzoo's docstrings are plain prose, not Markdown. Outside `code spans`, a `<label>` would be
swallowed as an HTML tag and a `**options` would start bold text, so those characters are escaped there."""
from __future__ import annotations

import re

import griffe

CODE = re.compile(r"(`+)(.+?)\1", re.S)
SPECIAL = re.compile(r"([>*_\\])")


def _escape(text: str) -> str:
    return SPECIAL.sub(r"\\\1", text).replace("<", "&lt;")


def plain(text: str) -> str:
    out, pos = [], 0
    for match in CODE.finditer(text):
        out += [_escape(text[pos:match.start()]), match.group(0)]
        pos = match.end()
    out.append(_escape(text[pos:]))
    return "".join(out)


class PlainDocstrings(griffe.Extension):
    def on_instance(self, *, obj: griffe.Object, **kwargs) -> None:
        if obj.docstring is not None and obj.path.startswith("splatzoo"):
            obj.docstring.value = plain(obj.docstring.value)
