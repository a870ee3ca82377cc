"""mkdocs hook: the reference pages quote the program itself, so they cannot fall behind it.

A page line `<!-- splatzoo: help COMMAND -->` becomes `splatzoo COMMAND --help` in a code block,
`<!-- splatzoo: models -->` the table of models, `<!-- splatzoo: model-options -->` their options (those several
models share once, then each model's own, as `splatzoo models -v` lists them) and
`<!-- splatzoo: export-formats -->` `splatzoo export --list` and `<!-- splatzoo: fields module.Class -->` a table of
a settings dataclass's fields. An unknown command or a failing one fails the build.
"""
from __future__ import annotations

import os
import re

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
MARKER = re.compile(r"^<!-- splatzoo: ([\w-]+)(?: ([\w.-]+))? -->$", re.M)
WIDTH = 110  # help text wrapped for a code block of this many columns


def _run(*args: str) -> str:
    from typer.testing import CliRunner

    from splatzoo.cli import app

    result = CliRunner().invoke(app, list(args), prog_name="splatzoo", terminal_width=WIDTH,
                                max_content_width=WIDTH)
    if result.exit_code != 0:
        raise RuntimeError(f"splatzoo {' '.join(args)} failed (exit {result.exit_code}): {result.output}")
    return result.output.rstrip()


def _cell(text) -> str:
    return str(text).replace("|", "\\|").replace("\n", " ")


def _options_table(rows) -> str:
    lines = ["| option | type | default | what |", "|---|---|---|---|"]
    lines += [f"| `{flag}` | {typ} | `{default}` | {_cell(hlp)} |" for flag, typ, default, hlp in rows]
    return "\n".join(lines)


def _models() -> str:
    from splatzoo.registry import MODELS

    lines = ["| name | origin | what |", "|---|---|---|"]
    for entry in MODELS.entries():
        what = f"BROKEN: {entry.error}" if entry.broken else entry.spec.description
        lines.append(f"| `{entry.name}` | {entry.origin} | {_cell(what)} |")
    return "\n".join(lines)


def _model_options() -> str:
    from splatzoo.cli import option_groups
    from splatzoo.registry import MODELS

    shared, own = option_groups({e.name: e.spec.config_cls for e in MODELS.entries() if not e.broken})
    parts = []
    for names, rows in shared:
        parts += [f"#### Shared by {', '.join(f'`{n}`' for n in names)}", "", _options_table(rows), ""]
    for name, rows in own.items():
        if rows:
            parts += [f"#### `{name}`'s own", "", _options_table(rows), ""]
    bare = [name for name, rows in own.items() if not rows]
    if bare:
        parts.append(f"No options of their own: {', '.join(f'`{n}`' for n in bare)}.")
    return "\n".join(parts)


def _fields(path: str) -> str:
    import dataclasses
    import importlib

    module, _, name = path.rpartition(".")
    cls = getattr(importlib.import_module(module), name)
    rows = []
    for f in dataclasses.fields(cls):
        default = f.default if f.default is not dataclasses.MISSING else "(computed)"
        typ = f.type if isinstance(f.type, str) else getattr(f.type, "__name__", str(f.type))
        rows.append((f.name, typ, default, f.metadata.get("help", "")))
    lines = ["| field | type | default | what |", "|---|---|---|---|"]
    lines += [f"| `{n}` | {_cell(t)} | `{d}` | {_cell(h)} |" for n, t, d, h in rows]
    return "\n".join(lines)


def _replace(match: re.Match) -> str:
    what, arg = match.group(1), match.group(2)
    if what == "help" and arg:
        return f"```text\n{_run(arg, '--help')}\n```"
    if what == "models":
        return _models()
    if what == "model-options":
        return _model_options()
    if what == "fields" and arg:
        return _fields(arg)
    if what == "export-formats":
        return f"```text\n{_run('export', '--list')}\n```"
    raise ValueError(f"unknown splatzoo marker {match.group(0)!r} (help COMMAND, models, model-options, "
                     "export-formats, fields module.Class)")


def on_page_markdown(markdown: str, page, config, files) -> str:
    return MARKER.sub(_replace, markdown)
