"""PLY export: the 3DGS/2DGS layout, exact round trips for every built-in model, plugins, errors, CLI."""
import json
import dataclasses
from dataclasses import dataclass

import numpy as np
import pytest
import torch
from torch import nn
from typer.testing import CliRunner

import splatzoo
from splatzoo import Camera, ModelSpec, Surfels, create_model, rasterize, save_model
from splatzoo.cli import app
from splatzoo.errors import SplatzooError
from splatzoo.export import export_run, read_ply_vertices, save_ply
from splatzoo.models.base import SurfelModel

runner = CliRunner()
CAM = Camera.look_at([0.4, -0.3, -3.0], [0.0, 0.0, 0.0], width=40, height=32, fov_deg=50.0, dtype=torch.float32)


def random_model(name, n=300, seed=0, **options):
    """A model with every parameter perturbed away from its initial value, so nothing round-trips by luck."""
    g = torch.Generator().manual_seed(seed)
    pts = torch.randn(n, 3, generator=g) * 0.5
    model = create_model(name, pts, torch.rand(n, 3, generator=g), seed=seed, **options)
    with torch.no_grad():
        for p in model.parameters():
            p.add_(0.1 * torch.randn(p.shape, generator=g))
        model.logit_opacity.add_(2.0)  # mostly opaque: more of every output is exercised
    return model


def max_render_diff(a, b, camera=CAM):
    with torch.no_grad():
        ra = rasterize(a.surfels(camera), camera, backend="auto")
        rb = rasterize(b.surfels(camera), camera, backend="auto")
    return max(float((x - y).abs().max()) for x, y in zip(ra.tensors().values(), rb.tensors().values()))


@pytest.mark.parametrize("name,options", [("2dgs", {}), ("2dgs", {"sh_degree": 3}), ("gabor", {}),
                                          ("gabor", {"n_waves": 2}), ("baseline-a", {}), ("baseline-c", {})])
def test_round_trip_renders_identically(tmp_path, name, options):
    model = random_model(name, **options)
    path = save_ply(model, tmp_path / "m.ply")
    back = splatzoo.load_ply(path)
    assert back.name == name and type(back) is type(model) and back.config == model.config
    assert back.num_primitives == model.num_primitives
    for k, v in model.state_dict().items():
        assert torch.equal(v, back.state_dict()[k]), k
    assert max_render_diff(model, back) < 1e-6
    assert [f.name for f in tmp_path.iterdir()] == ["m.ply"]  # no temporary left behind


def test_2dgs_layout_is_what_2dgs_tools_read(tmp_path):
    model = random_model("2dgs", n=50, sh_degree=3)
    arr, comments = read_ply_vertices(save_ply(model, tmp_path / "m.ply"))
    expected = (["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"] + [f"f_rest_{i}" for i in range(45)]
                + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"])
    assert list(arr.dtype.names) == expected
    assert all(arr.dtype[k] == np.dtype("<f4") for k in expected)
    assert "splatzoo model 2dgs" in comments and 'splatzoo config {"sh_degree":3}' in comments
    # the surfel's thickness: log(0), which splat-transform, Spark and GaussianSplats3D read as exactly flat
    assert np.all(arr["scale_2"] == -np.inf) and "SplatRenderMode: 2dgs" in comments
    p = {k: v.detach().numpy() for k, v in model.named_parameters()}
    assert np.array_equal(np.stack([arr["x"], arr["y"], arr["z"]], 1), p["means"])
    assert np.array_equal(arr["opacity"], p["logit_opacity"])                     # logit, as 3DGS
    assert np.array_equal(arr["scale_1"], p["log_scales"][:, 1])                  # log sigma
    assert np.array_equal(arr["rot_0"], p["quats"][:, 0])                         # w first
    assert np.array_equal(arr["f_dc_2"], p["sh_dc"][:, 0, 2])
    # 3DGS writes the SH bands channel-major: f_rest_0..14 are red bands 1..15, then green, then blue
    assert np.array_equal(arr["f_rest_1"], p["sh_rest"][:, 1, 0])
    assert np.array_equal(arr["f_rest_15"], p["sh_rest"][:, 0, 1])
    normals = np.stack([arr["nx"], arr["ny"], arr["nz"]], 1)
    assert np.allclose(np.linalg.norm(normals, axis=1), 1, atol=1e-5)


@pytest.mark.parametrize("color_param,colors", [("residual", ("gabor_color_base_", "gabor_color_diff_")),
                                                ("paper", ("gabor_color_a_", "gabor_color_b_"))])
def test_gabor_layout_names_its_waves(tmp_path, color_param, colors):
    model = random_model("gabor", n=20, n_waves=3, color_param=color_param)
    arr, comments = read_ply_vertices(save_ply(model, tmp_path / "g.ply"))
    names = list(arr.dtype.names)
    assert names[:9] == ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
    for prefix, count in ((colors[0], 3), (colors[1], 3), ("gabor_weight_", 3), ("gabor_freq_", 3),
                          ("gabor_phase_", 3)):
        assert [n for n in names if n.startswith(prefix)] == [f"{prefix}{i}" for i in range(count)]
    assert names[9:17] == ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    assert "splatzoo model gabor" in comments
    config = [c for c in comments if c.startswith("splatzoo config ")]
    assert len(config) == 1 and json.loads(config[0][len("splatzoo config "):]) == dataclasses.asdict(model.config)
    assert np.array_equal(arr["gabor_freq_2"], model.wave_freqs[:, 2].detach().numpy())
    # f_dc previews the mean colour (for 2DGS viewers); it is not read back
    c0 = model.surfels(CAM).base_color.detach().clamp(0, 1).numpy()
    assert np.allclose(arr["f_dc_0"] * 0.28209479177387814 + 0.5, c0[:, 0], atol=1e-5)


def test_gabor_ply_from_before_color_param_loads_as_the_paper_model(tmp_path):
    """A config comment without color_param was written before the option existed: the paper's parametrisation."""
    from splatzoo.export import load_ply

    model = random_model("gabor", n=30, n_waves=2, color_param="paper")
    data = save_ply(model, tmp_path / "m.ply").read_bytes()
    old = data.replace(b'"color_param":"paper",', b"")
    assert old != data
    (tmp_path / "old.ply").write_bytes(old)
    back = load_ply(tmp_path / "old.ply")
    assert back.config.color_param == "paper" and max_render_diff(model, back) == 0


def test_plain_2dgs_ply_without_splatzoo_comments_loads(tmp_path):
    model = random_model("2dgs", n=40, sh_degree=1)
    path = save_ply(model, tmp_path / "m.ply")
    data = path.read_bytes()
    header, body = data.split(b"end_header\n", 1)
    header = b"\n".join(line for line in header.split(b"\n") if not line.startswith(b"comment"))
    (tmp_path / "plain.ply").write_bytes(header + b"end_header\n" + body)
    back = splatzoo.load_ply(tmp_path / "plain.ply")
    assert back.name == "2dgs" and back.config.sh_degree == 1
    assert max_render_diff(model, back) < 1e-6


class _TintedModel(SurfelModel):
    """A plugin-like model with extra per-primitive parameters the standard layout does not know."""

    def __init__(self, config, num_primitives=0):
        super().__init__(config, num_primitives)
        self.tint = nn.Parameter(torch.zeros(num_primitives, 3))
        self.gain = nn.Parameter(torch.ones(num_primitives))

    def init_from_points(self, points, colors, generator):
        self.init_geometry(points, generator)
        self.tint.copy_(colors)

    def surfels(self, camera):
        g = self.geometry()
        return Surfels.constant_color(g["means"], g["quats"], g["scales"], g["opacities"],
                                      (self.tint * self.gain[:, None]).clamp_min(0))


@dataclass
class _TintedConfig:
    strength: float = 1.0


class _SharedModel(_TintedModel):
    def __init__(self, config, num_primitives=0):
        super().__init__(config, num_primitives)
        self.mlp = nn.Linear(3, 3)  # model-wide weights: no place in a per-vertex PLY


@pytest.fixture
def plugin_models():
    from splatzoo.registry import MODELS, register_model

    names = ["ply-test-tinted", "ply-test-shared"]
    register_model(ModelSpec(names[0], _TintedModel, _TintedConfig, "test"))
    register_model(ModelSpec(names[1], _SharedModel, _TintedConfig, "test"))
    yield names
    for n in names:
        MODELS._entries.pop(n, None)


def test_plugin_parameters_export_by_name(tmp_path, plugin_models):
    model = random_model(plugin_models[0], n=30, strength=2.5)
    arr, comments = read_ply_vertices(save_ply(model, tmp_path / "p.ply"))
    assert {"tint_0", "tint_1", "tint_2", "gain", "x", "opacity", "rot_0"} <= set(arr.dtype.names)
    back = splatzoo.load_ply(tmp_path / "p.ply")
    assert back.config.strength == 2.5 and max_render_diff(model, back) < 1e-6


def test_model_wide_parameters_are_refused(tmp_path, plugin_models):
    model = random_model(plugin_models[1], n=10)
    with pytest.raises(SplatzooError, match=r"mlp\.weight.*not per-primitive.*save_model"):
        save_ply(model, tmp_path / "s.ply")
    assert not (tmp_path / "s.ply").exists()


def _run_dir(tmp_path, model=None):
    run = tmp_path / "run"
    run.mkdir()
    (run / "config.json").write_text(json.dumps({"data": "nowhere", "model": "gabor"}))
    if model is not None:
        save_model(model, run / "model.pt")
    return run


def test_cli_export_from_run_dir(tmp_path):
    model = random_model("gabor", n=25)
    run = _run_dir(tmp_path, model)
    res = runner.invoke(app, ["export", str(run), "--out", str(tmp_path / "out" / "model.ply")])
    assert res.exit_code == 0, res.output
    back = splatzoo.load_ply(tmp_path / "out" / "model.ply")
    assert max_render_diff(model, back) < 1e-6
    assert export_run(run / "model.pt", tmp_path / "direct.ply").is_file()  # a model .pt works too


def test_export_errors(tmp_path):
    run = _run_dir(tmp_path)
    (run / "checkpoint.pt").write_bytes(b"")
    with pytest.raises(SplatzooError, match=r"no trained model \(model.pt\).*--resume"):
        export_run(run, tmp_path / "m.ply")
    with pytest.raises(SplatzooError, match="does not exist"):
        export_run(tmp_path / "missing", tmp_path / "m.ply")
    model = random_model("2dgs", n=5)
    blocker = tmp_path / "a_file"
    blocker.write_text("x")
    with pytest.raises(SplatzooError, match="cannot write"):
        save_ply(model, blocker / "m.ply")           # parent is a file
    with pytest.raises(SplatzooError, match="is a folder"):
        save_ply(model, tmp_path)
    with pytest.raises(SplatzooError, match="not a PLY"):
        splatzoo.load_ply(blocker)
    with pytest.raises(SplatzooError, match="no PLY file"):
        splatzoo.load_ply(tmp_path / "none.ply")
    good = save_ply(model, tmp_path / "t.ply")
    (tmp_path / "cut.ply").write_bytes(good.read_bytes()[:-10])
    with pytest.raises(SplatzooError, match="truncated"):
        splatzoo.load_ply(tmp_path / "cut.ply")
    res = runner.invoke(app, ["export", str(run), "--out", str(tmp_path / "m.ply")])
    assert res.exit_code != 0 and isinstance(res.exception, SplatzooError)
