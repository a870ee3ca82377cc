"""The dataset format registry: detection, forced formats, the unknown-layout message, and a layering without
import cycles inside splatzoo.data."""
from __future__ import annotations

import ast
import json
from pathlib import Path

import numpy as np
import pytest

import splatzoo.data as data
from splatzoo.data import DatasetFormat, detect_format, list_formats, load_scene, register_format
import splatzoo.data.formats as formats_module
from splatzoo.errors import DataError, DuplicateNameError, UnknownNameError

DATA_DIR = Path(data.__file__).parent


def _imports_within_data(path: Path) -> set[str]:
    """Modules of splatzoo.data that `path` imports anywhere (module level or inside functions)."""
    found = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom) and node.level == 1:
            if node.module:
                found.add(node.module.split(".")[0])
            else:
                found.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and node.module.startswith("splatzoo.data."):
            found.add(node.module.split(".")[2])
        elif isinstance(node, ast.Import):
            found.update(a.name.split(".")[2] for a in node.names if a.name.startswith("splatzoo.data."))
    return found


def test_data_modules_import_without_cycles():
    modules = {p.stem: p for p in DATA_DIR.glob("*.py") if p.stem != "__init__"}
    graph = {m: _imports_within_data(p) & set(modules) for m, p in modules.items()}
    assert "colmap" not in graph["scene"] and "blender" not in graph["scene"]
    assert "synthetic" not in graph["sfm"]
    # Depth-first search for a back edge.
    state: dict[str, int] = {}

    def visit(m, stack):
        state[m] = 1
        for n in sorted(graph[m]):
            assert state.get(n) != 1, f"import cycle: {' -> '.join(stack + [m, n])}"
            if n not in state:
                visit(n, stack + [m])
        state[m] = 2
    for m in sorted(graph):
        if m not in state:
            visit(m, [])


def test_builtin_formats_and_detection(tmp_path):
    assert [f.name for f in list_formats()] == ["blender", "colmap"]
    (tmp_path / "c" / "sparse" / "0").mkdir(parents=True)
    (tmp_path / "c" / "sparse" / "0" / "cameras.bin").write_bytes(b"")
    assert detect_format(tmp_path / "c") == "colmap"
    # transforms.json beside images/ (instant-ngp layout) is Blender, not COLMAP
    (tmp_path / "b" / "images").mkdir(parents=True)
    (tmp_path / "b" / "transforms.json").write_text("{}")
    assert detect_format(tmp_path / "b") == "blender"


def test_unknown_layout_names_every_format_and_what_it_needs(tmp_path):
    (tmp_path / "junk").mkdir()
    (tmp_path / "junk" / "notes.txt").write_text("hi")
    with pytest.raises(DataError) as e:
        load_scene(tmp_path / "junk")
    msg = str(e.value)
    assert "not a dataset folder" in msg and "splatzoo sfm" in msg
    for f in list_formats():
        assert f"{f.name} ({f.needs})" in msg
    assert "sparse/0/" in msg and "transforms_train.json" in msg
    with pytest.raises(DataError, match=r"is a file.*colmap \(images/"):
        load_scene(tmp_path / "junk" / "notes.txt")


def test_forced_and_unknown_format_names(tmp_path):
    with pytest.raises(UnknownNameError, match=r"unknown dataset format 'colmp'.*known: blender, colmap.*'colmap'"):
        load_scene(tmp_path, format="colmp")
    (tmp_path / "notes.txt").write_text("hi")
    with pytest.raises(DataError, match=r"no images/ folder"):   # forced: the COLMAP reader says what is missing
        load_scene(tmp_path, format="colmap")
    with pytest.raises(DataError, match=r"nope does not exist"):
        load_scene(tmp_path / "nope", format="colmap")


def test_register_a_format(tmp_path, monkeypatch):
    import torch

    from splatzoo.data import Scene, View
    from splatzoo.types import Camera

    monkeypatch.setattr(formats_module.FORMATS, "_entries", dict(formats_module.FORMATS._entries))

    def load(path, **options):
        meta = json.loads((path / "one.json").read_text())
        cam = Camera.look_at([0, 0, -3], [0, 0, 0], width=8, height=8)
        view = View.from_tensor(cam, torch.full((8, 8, 3), meta["grey"]), "v")
        return Scene("one", path, [view], [], torch.zeros(1, 3), torch.zeros(1, 3), 1.0,
                     background=options["background"])

    register_format(DatasetFormat("one", lambda p: (p / "one.json").is_file(), load, needs="one.json", priority=5))
    with pytest.raises(DuplicateNameError):
        register_format(DatasetFormat("one", lambda p: False, load, needs="x"))
    (tmp_path / "one.json").write_text(json.dumps({"grey": 0.5}))
    (tmp_path / "images").mkdir()                 # also looks like COLMAP: the lower priority number wins
    assert detect_format(tmp_path) == "one"
    scene = load_scene(tmp_path, background=(1, 1, 1))
    assert scene.name == "one" and scene.background == (1.0, 1.0, 1.0)
    assert np.allclose(scene.train[0].image_float().numpy(), 0.5, atol=1 / 255)
    (tmp_path / "other").mkdir()
    (tmp_path / "other" / "x.txt").write_text("")
    with pytest.raises(DataError, match=r"one \(one.json\)"):
        load_scene(tmp_path / "other")
