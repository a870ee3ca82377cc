"""The reference: `splatzoo models -v` states each option once, and the docs site builds without a warning."""
from __future__ import annotations

import dataclasses
import importlib.util
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest
from typer.testing import CliRunner

from splatzoo.cli import app, option_groups
from splatzoo.registry import MODELS

runner = CliRunner()
REPO = Path(__file__).parents[1]
HAVE_MKDOCS = all(importlib.util.find_spec(m) is not None for m in ("mkdocs", "mkdocstrings", "mkdocstrings_handlers"))


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
    waves = next(names for names, rows in sections.items() if any(r.startswith("--wave-l1-per-count ") for r in rows))
    assert {"gabor", "gabor-adaptive", "beta-gabor", "baseline-a", "baseline-b", "baseline-c"} <= set(waves)
    assert sum(line.startswith("--wave-l1-per-count ") for line in lines) == 1
    # an option whose default differs (beta-gabor's per-wave colours, its twice-as-strong wave penalty) is stated
    # apart, under its own model
    for option in ("--color-param ", "--wave-l1 "):
        blocks = [names for names, rows in sections.items() if any(r.startswith(option) for r in rows)]
        assert len(blocks) == 2 and ("beta-gabor",) in blocks, option
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


def test_the_docs_build_without_a_warning(tmp_path):
    """`mkdocs build --strict`: a docstring that breaks the build, a reference to a function that moved, a command
    whose --help fails, or a broken link between pages fails here. CI sets SPLATZOO_REQUIRE_DOCS, so there a missing
    mkdocs fails too (the docs extra is part of the dev install)."""
    if not HAVE_MKDOCS:
        if os.environ.get("SPLATZOO_REQUIRE_DOCS"):
            pytest.fail("mkdocs is not installed but SPLATZOO_REQUIRE_DOCS is set: pip install -e .[docs]")
        pytest.skip("mkdocs is not installed (pip install -e .[docs])")
    site = tmp_path / "site"
    r = subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict", "--config-file", str(REPO / "mkdocs.yml"),
                        "--site-dir", str(site)], cwd=REPO, capture_output=True, text=True, timeout=600,
                       env={**os.environ, "OMP_NUM_THREADS": os.environ.get("OMP_NUM_THREADS", "1")})
    assert r.returncode == 0, r.stderr[-4000:]
    assert "WARNING" not in r.stderr, r.stderr[-4000:]
    api = (site / "api" / "models" / "index.html").read_text()
    assert "create_model" in api and "load_model" in api and "save_model" in api
    commands = (site / "commands" / "index.html").read_text()
    assert "Usage: splatzoo train" in commands and "Usage: splatzoo export" in commands  # quoted from --help
    models = (site / "models" / "index.html").read_text()
    assert "beta-gabor" in models and "--color-param" in models and "&lt;!-- splatzoo:" not in models


def test_readme_links_reach_pages_that_exist():
    readme = (REPO / "README.md").read_text()
    links = re.findall(r"\]\(((?:docs/|BENCHMARKS)[^)#]*)", readme)
    assert any(link.startswith("docs/") for link in links), "README.md links to no reference page"
    assert [link for link in links if not (REPO / link).is_file()] == []


def test_every_page_is_in_the_site_navigation():
    nav = (REPO / "mkdocs.yml").read_text()
    pages = [p.relative_to(REPO / "docs").as_posix() for p in (REPO / "docs").rglob("*.md")]
    assert [p for p in pages if f": {p}" not in nav] == []


def test_the_python_on_the_reference_pages_runs(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)  # the quick tour writes model.pt
    blocks = [(page.name, code) for page in sorted((REPO / "docs").rglob("*.md"))
              for code in re.findall(r"```python\n(.*?)```", page.read_text(), re.S)]
    assert {name for name, _ in blocks} >= {"getting-started.md", "plugins.md"}
    for name, code in blocks:
        exec(compile(code, name, "exec"), {})
