"""Third-party models through the `splatzoo.models` entry-point group: installed out of tree, no edit to splatzoo."""
import subprocess
import sys
from pathlib import Path

import pytest

from conftest import install_plugin

PLUGIN = Path(__file__).parent / "plugins" / "splatzoo_checker"


@pytest.fixture(scope="module")
def plugin_env(tmp_path_factory):
    return install_plugin(tmp_path_factory, PLUGIN)


def run(env, *args):
    return subprocess.run(args, capture_output=True, text=True, env=env, timeout=120)


def test_models_command_lists_plugin_and_reports_broken_ones(plugin_env):
    out = run(plugin_env, sys.executable, "-m", "splatzoo.cli", "models")
    assert out.returncode == 0, out.stderr
    lines = {line.split()[0]: line for line in out.stdout.splitlines() if line.strip()}
    assert "plugin (splatzoo-checker)" in lines["checker"] and "checkerboard" in lines["checker"]
    assert "BROKEN" in lines["broken-plugin"] and "splatzoo_missing_dependency" in lines["broken-plugin"]
    # a plugin cannot take a built-in's name; the built-in keeps working
    assert lines["gabor"].split()[1] == "built-in"
    for name in ("2dgs", "baseline-a", "baseline-b", "baseline-c"):
        assert "BROKEN" not in lines[name]


def test_plugin_renders_through_the_same_rasterizer(plugin_env):
    code = """
import torch, splatzoo
from splatzoo import Camera, rasterize
from splatzoo.errors import PluginError
assert "checker" in splatzoo.list_models()
pts = torch.randn(64, 3); pts = pts / pts.norm(dim=1, keepdim=True)
cam = Camera.look_at([0, 0, -3.5], [0, 0, 0], width=32, height=32)
m = splatzoo.create_model("checker", pts, torch.rand(64, 3), cells=2.0)
with torch.no_grad():
    m.logit_opacity.fill_(2.0)
out = rasterize(m.surfels(cam), cam, backend="reference")
assert out.rgb.sum() > 0 and out.alpha.max() > 0.5
out.rgb.sum().backward()
assert m.color_light.grad.abs().sum() > 0
try:
    splatzoo.create_model("broken-plugin")
    raise SystemExit("broken plugin did not raise")
except PluginError as e:
    assert "broken" in str(e)
g = splatzoo.create_model("gabor", pts, torch.rand(64, 3))
assert type(g).__module__ == "splatzoo.models.gabor"
print("ok")
"""
    out = run(plugin_env, sys.executable, "-c", code)
    assert out.returncode == 0 and out.stdout.strip() == "ok", out.stderr


def test_a_plugins_source_is_part_of_its_runs_code_fingerprint(plugin_env):
    """compare tells runs made by other code apart: for a plugin model its own source file counts too."""
    code = """
from splatzoo.runs import code_fingerprint
assert code_fingerprint("checker") != code_fingerprint("gabor") == code_fingerprint("2dgs")
print("ok")
"""
    out = run(plugin_env, sys.executable, "-c", code)
    assert out.returncode == 0 and out.stdout.strip() == "ok", out.stderr


def test_duplicate_builtin_registration_is_an_error():
    from splatzoo.errors import DuplicateNameError
    from splatzoo.registry import MODELS, ModelSpec

    spec = MODELS.get("gabor")
    with pytest.raises(DuplicateNameError, match="gabor"):
        MODELS.register("gabor", ModelSpec("gabor", spec.cls, spec.config_cls))
