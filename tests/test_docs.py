"""The reference: `splatzoo models -v` states each option once, and the docs site builds without a warning."""
from __future__ import annotations

import dataclasses

from typer.testing import CliRunner

from splatzoo.cli import app, option_groups
from splatzoo.registry import MODELS

runner = CliRunner()


def _option_sections(output: str) -> dict[tuple[str, ...], list[str]]:
    """`models -v`'s option part: {(model, ...): [option line, ...]} by the header line above each block."""
    sections, current = {}, None
    for line in output.split("\nModel options:", 1)[1].splitlines():
        if line.startswith("  --"):
            sections[current].append(line.strip())
        elif line.endswith(":") and not line.startswith(("(", " ")) and " " not in line.replace(", ", ","):
            current = tuple(line[:-1].split(", "))
            sections[current] = []
    return sections


def test_models_verbose_states_shared_options_once():
    result = runner.invoke(app, ["models", "-v"])
    assert result.exit_code == 0, result.output
    sections = _option_sections(result.output)
    lines = [line for rows in sections.values() for line in rows]
    assert len(lines) == len(set(lines)), "an option is printed twice with the same meaning"
    # the wave models' common options come once, under one header naming them all
    waves = next(names for names, rows in sections.items() if any(r.startswith("--color-param ") for r in rows))
    assert {"gabor", "gabor-adaptive", "beta-gabor", "baseline-a", "baseline-b", "baseline-c"} <= set(waves)
    assert sum(line.startswith("--wave-l1 ") for line in lines) == 1
    # and nothing is lost: every model's options are its own block plus the shared blocks that name it
    for entry in MODELS.entries():
        if entry.broken:
            continue
        flags = {f"--{f.name.replace('_', '-')}" for f in dataclasses.fields(entry.spec.config_cls)}
        shown = [row.split()[0] for names, rows in sections.items() if entry.name in names for row in rows]
        assert sorted(shown) == sorted(flags), entry.name
    assert "(only shared options:" in result.output and "2dgs" in result.output.rsplit("(only shared options:")[1]


def test_option_groups_keep_differing_defaults_apart():
    @dataclasses.dataclass
    class A:
        n_waves: int = 4
        shared: float = 0.5

    @dataclasses.dataclass
    class B:
        n_waves: int = 8  # the same flag with another default is another option
        shared: float = 0.5

    @dataclasses.dataclass
    class C:
        alone: bool = False

    shared, own = option_groups({"a": A, "b": B, "c": C})
    assert [(names, [row[0] for row in rows]) for names, rows in shared] == [(("a", "b"), ["--shared"])]
    assert [row[:3] for row in own["a"]] == [("--n-waves", "int", 4)]
    assert [row[:3] for row in own["b"]] == [("--n-waves", "int", 8)]
    assert [row[0] for row in own["c"]] == ["--alone"]
