"""Appearance kinds as units: each kind of the Surfels table has one section of csrc/surfel_math.h, its rows in the
table and its twin in rasterizers/reference.py, and nothing else names it; a research kind starts in Python (a plugin's
`splatzoo.appearance_kinds` entry point), which the reference backend renders and differentiates and the native
backends refuse by name.

The Python kinds under test (tests/plugins/splatzoo_wavekind) say again what the wave bank and the texture say: the
same renders and gradients as the built-ins on the reference backend, a gradcheck, and `splatzoo compare` of gabor
through the Python wave bank against gabor itself.
"""
from __future__ import annotations

import importlib.util
import json
import math
import re
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from splatzoo.errors import PluginError, ShapeError, SplatzooError, UnknownNameError
from splatzoo.rasterizers import fields as field_header
from splatzoo.rasterizers import rasterize
from splatzoo.rasterizers.common import ANTIALIASED, SETTINGS
from splatzoo.rasterizers.reference import KIND_TWINS
from splatzoo.registry import APPEARANCE_KINDS, AppearanceKindSpec, register_appearance_kind
from splatzoo.testing import sphere_and_wall
from splatzoo.types import BUILTIN_KINDS, SURFEL_FIELDS, Surfels, surfel_field
from conftest import install_plugin

CSRC = Path(__file__).resolve().parents[1] / "splatzoo" / "csrc"
PLUGIN = Path(__file__).parent / "plugins" / "splatzoo_wavekind"
FIELDS = ("rgb", "alpha", "depth", "median_depth", "normal", "distortion")


def _code(path: Path) -> str:
    """A C++ source without its comments and string literals (what the code itself names)."""
    text = path.read_text()
    text = re.sub(r"//[^\n]*", "", text)
    text = re.sub(r"/\*.*?\*/", "", text, flags=re.S)
    return re.sub(r'"(\\.|[^"\\])*"', '""', text)


# ---- kinds as units -------------------------------------------------------------------------------------------------

def test_every_kind_of_the_table_has_its_header_section_and_its_twin():
    header = (CSRC / "surfel_math.h").read_text()
    assert BUILTIN_KINDS == ("wave_bank", "texture")
    assert tuple(KIND_TWINS) == BUILTIN_KINDS, "every kind of the table has its twin in reference.KIND_TWINS"
    for kind in BUILTIN_KINDS:
        struct = field_header.kind_struct(kind)
        section = rf"\nstruct {struct} {{\n    SZ_KIND_FIELD_MEMBERS\(SZ_KIND_FIELDS_{kind.upper()}\)"
        assert re.search(section, header), (
            f"csrc/surfel_math.h has no section for the kind {kind!r} (struct {struct} over its generated fields)")
        # its section holds every member the composition calls
        body = header[header.index(f"struct {struct} {{"):]
        body = body[:body.index("\n};\n")]
        for member in ("dense_slots", "scatter_slots", "prepared_width", "fold_values", "fold_factors", "has_gain",
                       "gain(", "bind(", "prepare(", "fold(", "unfold(", "add_colour(", "backward(", "finalize(",
                       "struct Cache"):
            assert member in body, f"{struct} declares no {member}"


def test_the_generator_emits_each_kinds_fields_and_the_kind_list():
    text = field_header.header_text()
    assert "#define SZ_KIND_FIELDS_WAVE_BANK(X) X(base_color, 3) X(wave_vectors, K * 2) X(wave_phases, K) " \
           "X(wave_amplitudes, K * 3)" in text
    assert "#define SZ_KIND_FIELDS_TEXTURE(X) X(texture, T * T * 4)" in text
    assert "#define SZ_APPEARANCE_KINDS(X) X(WaveBank, wave_bank, SZ_KIND_FIELDS_WAVE_BANK) X(Texture, texture, " \
           "SZ_KIND_FIELDS_TEXTURE)" in text
    for f in SURFEL_FIELDS:
        assert (f.kind is not None) == (f.role == "appearance"), f.name
    assert field_header.kind_struct("wave_bank") == "WaveBank"
    with pytest.raises(ValueError, match="snake_case"):
        field_header.kind_struct("WaveBank")


def test_an_appearance_field_names_its_kind():
    with pytest.raises(ValueError, match="names its kind"):
        surfel_field(3, role="appearance", doc="a colour", valid=(0, 1))
    with pytest.raises(ValueError, match="names its kind"):
        surfel_field(role="opacity", doc="an opacity", valid=(0, 1), kind="wave_bank")


@pytest.mark.parametrize("source", ["rasterize_cpu.cpp", "rasterize_cuda.cu", "rasterize.h", "ext.cpp"])
def test_the_tile_loops_and_the_bindings_name_no_kind(source):
    """The loops ask the composition (Appearance: has_gain, gain, colour, fold) and the falloff dispatch
    (with_falloff); no kind's field, struct or size check appears in them."""
    code = _code(CSRC / source)
    kind_fields = [f.name for f in SURFEL_FIELDS if f.kind]
    structs = [field_header.kind_struct(k) for k in BUILTIN_KINDS]
    for name in kind_fields + structs + ["TEX_CHANNELS", "G_WAVES", "G_BASE", "fold_gains", "wave_gain"]:
        assert not re.search(rf"\b{name}\b", code), f"{source} names {name}: ask the composition instead"
    assert not re.search(r"\bTS\s*(>|==|!=)\s*0\b", code), f"{source} tests the texture size: ask Appearance::has_gain"
    assert not re.search(r"\.s\s*>\s*S\(0\)", code), f"{source} branches on the falloff: use with_falloff"


def test_the_falloff_is_dispatched_in_one_place():
    code = _code(CSRC / "surfel_math.h")
    assert len(re.findall(r"\bs\s*>\s*S\(0\)\s*\)", code)) == 1, "with_falloff is the only branch on the falloff"
    assert "template <bool BETA" not in code


# ---- Python kinds -------------------------------------------------------------------------------------------------

def _plugin():
    """The test plugin's module, imported from its source folder (its kinds registered once per session)."""
    spec = importlib.util.spec_from_file_location("splatzoo_wavekind", PLUGIN / "splatzoo_wavekind" / "__init__.py")
    if "splatzoo_wavekind" not in sys.modules:
        module = importlib.util.module_from_spec(spec)
        sys.modules["splatzoo_wavekind"] = module
        spec.loader.exec_module(module)
    module = sys.modules["splatzoo_wavekind"]
    for kind in (module.WAVE_BANK, module.TEXTURE):
        if kind.name not in APPEARANCE_KINDS:
            register_appearance_kind(kind)
    return module


def _through_python_waves(s: Surfels) -> Surfels:
    """s with its waves handed to the wave-bank-py kind (the built-in bank left with K = 0)."""
    n = s.num
    params = torch.cat([s.wave_vectors, s.wave_phases[..., None], s.wave_amplitudes], -1)
    return Surfels(s.means, s.quats, s.scales, s.opacities, s.base_color, s.means.new_zeros(n, 0, 2),
                   s.means.new_zeros(n, 0), s.means.new_zeros(n, 0, 3), falloff=s.falloff,
                   appearance_kind="wave-bank-py", appearance_params=params)


def _through_python_texture(s: Surfels) -> Surfels:
    """s with its texture handed to the texture-py kind."""
    return Surfels(**{k: v for k, v in s.tensors().items() if k != "texture"}, appearance_kind="texture-py",
                   appearance_params=s.texture)


def _textured(s: Surfels, size: int = 2, seed: int = 4) -> Surfels:
    g = torch.Generator().manual_seed(seed)
    t = torch.rand(s.num, size, size, 4, generator=g, dtype=torch.float64)
    t[..., :3] = (2 * t[..., :3] - 1) * 0.4
    t[..., 3] = 0.3 + 0.7 * t[..., 3]
    s.texture = t.to(s.means.dtype)
    return s


def _render_and_grads(s: Surfels, cam, settings=SETTINGS):
    """Outputs and gradients of every floating-point field (and a Python kind's parameters), reference backend,
    under one shared random cotangent."""
    s = s.map(lambda t: t.detach().clone().requires_grad_(True))
    out = rasterize(s, cam, backend="reference", background=[0.1, 0.2, 0.3], settings=settings)
    g = torch.Generator().manual_seed(9)
    loss = sum((getattr(out, k) * torch.randn(getattr(out, k).shape, generator=g, dtype=torch.float64)).sum()
               for k in FIELDS)
    inputs = dict(s.tensors())
    if s.appearance_params is not None:
        inputs["appearance_params"] = s.appearance_params
    grads = torch.autograd.grad(loss, list(inputs.values()), allow_unused=True, materialize_grads=True)
    return {k: getattr(out, k).detach() for k in FIELDS}, dict(zip(inputs, grads))


def test_a_python_wave_bank_renders_and_differentiates_as_the_built_in_one():
    _plugin()
    s, cam = sphere_and_wall(200, 40, 32, 4, seed=6, dtype=torch.float64)
    s.falloff = torch.rand(s.num, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    s.falloff[::2] = 0
    ref, g_ref = _render_and_grads(s, cam)
    py, g_py = _render_and_grads(_through_python_waves(s), cam)
    for k in FIELDS:
        torch.testing.assert_close(py[k], ref[k], rtol=0, atol=1e-12, msg=k)
    assert ref["alpha"].max() > 0.5 and ref["rgb"].std() > 0.05
    for name in ("means", "quats", "scales", "opacities", "base_color", "falloff"):
        torch.testing.assert_close(g_py[name], g_ref[name], rtol=1e-10, atol=1e-12, msg=name)
    waves = torch.cat([g_ref["wave_vectors"], g_ref["wave_phases"][..., None], g_ref["wave_amplitudes"]], -1)
    torch.testing.assert_close(g_py["appearance_params"], waves, rtol=1e-10, atol=1e-12)
    assert waves.abs().max() > 0


def test_a_python_texture_renders_its_opacity_gain_as_the_built_in_one():
    _plugin()
    s, cam = sphere_and_wall(200, 40, 32, 2, seed=7, dtype=torch.float64)
    s = _textured(s)
    ref, g_ref = _render_and_grads(s, cam)
    py, g_py = _render_and_grads(_through_python_texture(s), cam)
    for k in FIELDS:
        torch.testing.assert_close(py[k], ref[k], rtol=0, atol=1e-12, msg=k)
    for name in ("means", "quats", "scales", "opacities", "base_color", "wave_vectors", "wave_amplitudes"):
        torch.testing.assert_close(g_py[name], g_ref[name], rtol=1e-10, atol=1e-12, msg=name)
    torch.testing.assert_close(g_py["appearance_params"], g_ref["texture"], rtol=1e-10, atol=1e-12)
    assert g_ref["texture"][..., 3].abs().max() > 0  # the gain's gradient is exercised


def test_a_python_kind_is_differentiable_by_gradcheck():
    _plugin()
    s, cam = sphere_and_wall(6, 12, 10, 4, seed=3, dtype=torch.float64, px_sigma=(2.0, 3.0))
    s.opacities.fill_(0.6)
    py = _through_python_waves(s)
    means, names = py.means.detach(), ["quats", "scales", "opacities", "base_color"]
    inputs = [getattr(py, n).detach().clone().requires_grad_(True) for n in names]
    inputs.append(py.appearance_params.detach().clone().requires_grad_(True))

    def f(quats, scales, opacities, base_color, params):
        t = Surfels(means, quats, scales, opacities, base_color, py.wave_vectors, py.wave_phases, py.wave_amplitudes,
                    appearance_kind="wave-bank-py", appearance_params=params)
        out = rasterize(t, cam, backend="reference")
        return tuple(getattr(out, k) * w for k, w in zip(FIELDS, (1.0, 0.7, 0.3, 0.2, 0.5, 2.0)))

    assert torch.autograd.gradcheck(f, inputs, eps=1e-6, atol=1e-5, rtol=1e-4)


def test_a_python_kind_adds_to_the_built_in_kinds_and_is_anti_aliased_at_the_footprint_centre():
    """Its rgb adds to the table kinds' colour (here the built-in waves and the same waves again in Python: twice
    the amplitudes), and anti-aliased it is evaluated (not prefiltered) at the footprint's centre."""
    _plugin()
    s, cam = sphere_and_wall(120, 32, 32, 4, seed=8, dtype=torch.float64)
    doubled = s.map(lambda t: t.clone())
    doubled.wave_amplitudes = 2 * s.wave_amplitudes
    both = _through_python_waves(s)
    both.wave_vectors, both.wave_phases, both.wave_amplitudes = s.wave_vectors, s.wave_phases, s.wave_amplitudes
    a = rasterize(both, cam, backend="reference")
    b = rasterize(doubled, cam, backend="reference")
    torch.testing.assert_close(a.rgb, b.rgb, rtol=0, atol=1e-12)
    # anti-aliased, the built-in waves fade under the footprint and the Python ones keep their amplitude
    aa_py = rasterize(_through_python_waves(s), cam, backend="reference", settings=ANTIALIASED)
    aa_ref = rasterize(s, cam, backend="reference", settings=ANTIALIASED)
    torch.testing.assert_close(aa_py.alpha, aa_ref.alpha, rtol=0, atol=1e-12)
    assert (aa_py.rgb - aa_ref.rgb).abs().max() > 1e-6


@pytest.mark.parametrize("backend", ["cpu", "cuda-emulated", "cuda"])
def test_the_native_backends_refuse_a_python_kind_by_name(backend):
    _plugin()
    if backend == "cuda" and not torch.cuda.is_available():
        pytest.skip("needs a CUDA device")
    s, cam = sphere_and_wall(20, 16, 16, 4, seed=1)
    s = _through_python_waves(s)
    with pytest.raises(SplatzooError, match=r"backend cannot render the appearance kind 'wave-bank-py'") as e:
        rasterize(s.to("cuda") if backend == "cuda" else s, cam, backend=backend)
    assert "--backend reference" in str(e.value) and "surfel_math.h" in str(e.value)
    assert "written in Python (registered from code)" in str(e.value)


def test_python_kind_fields_are_checked_by_name():
    _plugin()
    s, cam = sphere_and_wall(10, 16, 16, 4, seed=1)
    py = _through_python_waves(s)
    bad = py.map(lambda t: t)
    bad.appearance_params = py.appearance_params[:, :3]
    with pytest.raises(ShapeError, match=r"appearance_params of the appearance kind 'wave-bank-py' must have shape "
                                         r"\[N,4,6\]"):
        bad.validate()
    bad.appearance_params = py.appearance_params.double()
    with pytest.raises(ShapeError, match="appearance_params is torch.float64"):
        bad.validate()
    bad.appearance_params = py.appearance_params.clone()
    bad.appearance_params[0, 0, 0] = math.nan
    with pytest.raises(ShapeError, match="NaN"):
        bad.validate()
    bad = py.map(lambda t: t)
    bad.appearance_kind = "wave-bank-pi"
    with pytest.raises(UnknownNameError, match="wave-bank-py"):
        bad.validate()
    bad = s.map(lambda t: t)
    bad.appearance_params = py.appearance_params
    with pytest.raises(ShapeError, match="appearance_kind is None"):
        bad.validate()
    # the kind travels with the surfels: indexing, moving
    sub = py.index(torch.arange(3))
    assert sub.appearance_kind == "wave-bank-py" and sub.appearance_params.shape == (3, 4, 6)
    assert py.to(dtype=torch.float64).appearance_params.dtype == torch.float64


def test_a_python_kinds_function_must_return_what_it_declares():
    def broken(u, v, view_dirs, params):
        return torch.zeros(*u.shape, 2), None  # rgb with two channels

    if "broken-rgb" not in APPEARANCE_KINDS:
        register_appearance_kind(AppearanceKindSpec("broken-rgb", broken, (1,)))
    s, cam = sphere_and_wall(10, 16, 16, 0, seed=1)
    s.appearance_kind, s.appearance_params = "broken-rgb", torch.zeros(s.num, 1)
    with pytest.raises(ShapeError, match=r"'broken-rgb': rgb must be \[P,n,3\]"):
        rasterize(s, cam, backend="reference")


def test_a_python_kind_sees_the_rays_direction():
    """view_dirs is the unit world direction from the camera through each pixel."""
    seen = {}

    def look(u, v, view_dirs, params):
        seen["dirs"] = view_dirs.detach()
        return torch.zeros(*u.shape, 3, dtype=u.dtype), None

    if "look" not in APPEARANCE_KINDS:
        register_appearance_kind(AppearanceKindSpec("look", look, (1,)))
    s, cam = sphere_and_wall(30, 16, 16, 0, seed=1, dtype=torch.float64)
    s.appearance_kind, s.appearance_params = "look", torch.zeros(s.num, 1, dtype=torch.float64)
    rasterize(s, cam, backend="reference")
    d = seen["dirs"]
    torch.testing.assert_close(d.norm(dim=-1), torch.ones(d.shape[:-1], dtype=torch.float64))
    # the central pixels look along the camera's axis (its third row in world coordinates)
    axis = cam.R[2].to(torch.float64)
    assert float((d.reshape(-1, 3) @ axis).max()) > 0.99


def test_a_kind_spec_is_checked_when_registered():
    with pytest.raises(PluginError, match="built-in appearance kind"):
        register_appearance_kind(AppearanceKindSpec("texture", lambda *a: None, (1,)))
    with pytest.raises(PluginError, match="parameter shape"):
        register_appearance_kind(AppearanceKindSpec("no-params", lambda *a: None, (0,)))
    with pytest.raises(PluginError, match="callable"):
        register_appearance_kind(AppearanceKindSpec("not-callable", None, (1,)))


# ---- a plugin, out of tree: entry points and `splatzoo compare` ------------------------------------------------------

@pytest.fixture(scope="module")
def plugin_env(tmp_path_factory):
    return install_plugin(tmp_path_factory, PLUGIN)


def test_a_plugin_kind_is_found_by_its_entry_point(plugin_env):
    code = """
from splatzoo.registry import APPEARANCE_KINDS
assert {"wave-bank-py", "texture-py"} <= set(APPEARANCE_KINDS.names())
e = {e.name: e for e in APPEARANCE_KINDS.entries()}["wave-bank-py"]
assert e.origin == "plugin (splatzoo-wavekind)" and e.spec.params == (4, 6), (e.origin, e.spec)
print("ok")
"""
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=plugin_env, timeout=120)
    assert out.returncode == 0 and out.stdout.strip() == "ok", out.stderr


def test_compare_a_plugin_kind_against_the_built_in_one(plugin_env, tmp_path):
    """`splatzoo compare gabor-py gabor --backend reference --no-antialias`: gabor through the Python wave bank trains
    as gabor does (the same maths, so the same metrics; anti-aliased, the built-in waves would be prefiltered and the
    Python ones not); without --backend reference the native backend refuses it by name."""
    from splatzoo.data.synthetic import make_synthetic_scene

    data = make_synthetic_scene("sweater", tmp_path / "data", views=4, width=24, height=24)
    out = tmp_path / "cmp"
    cmd = [sys.executable, "-m", "splatzoo.cli", "compare", "gabor-py", "gabor", "--data", str(data), "--out",
           str(out), "--iterations", "4", "--num-primitives", "60", "--no-antialias", "--backend", "reference"]
    r = subprocess.run(cmd, capture_output=True, text=True, env=plugin_env, timeout=600)
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
    runs = json.loads((out / "compare.json").read_text())["runs"]
    assert set(runs) == {"gabor-py", "gabor"}
    for metric in ("psnr", "ssim"):
        assert abs(runs["gabor-py"][metric] - runs["gabor"][metric]) < 1e-4, (metric, runs["gabor-py"][metric],
                                                                              runs["gabor"][metric])
    r = subprocess.run(cmd[:-2] + ["--backend", "cpu", "--out", str(tmp_path / "cpu")], capture_output=True,
                       text=True, env=plugin_env, timeout=600)
    said = " ".join((r.stdout + r.stderr).split())  # the error as the CLI wraps it
    assert r.returncode != 0 and "appearance kind 'wave-bank-py': it is written in Python (plugin" in said, said
