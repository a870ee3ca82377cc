"""Export formats: the registry and `--format` parsing, the third scale of the ply layout, PLY files of other tools
(2DGS, 3DGS) read by load_ply, files whose model cannot be told refused, and splat-transform's SPZ and SOG."""
import json
import sys
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import plyfile
import pytest
import torch
from test_export import max_render_diff, random_model
from typer.testing import CliRunner

import splatzoo
from splatzoo.cli import app
from splatzoo.errors import SplatzooError, UnknownNameError
from splatzoo.export import (EXPORTERS, ExporterSpec, export, flatten_gaussians, load_ply, load_source, parse_format,
                             register_exporter, save_ply)
from splatzoo.geometry import quat_to_rotmat
from splatzoo.io import read_ply_vertices
from splatzoo.registry import MODELS

runner = CliRunner()
SH_C0 = 0.28209479177387814


def builtin_models() -> list[str]:
    return [e.name for e in MODELS.entries() if e.origin == "built-in" and not e.broken]


@pytest.mark.parametrize("name", builtin_models())
def test_every_builtin_model_round_trips_exactly(tmp_path, name):
    model = random_model(name, n=40)
    back = load_ply(save_ply(model, tmp_path / "m.ply"))
    assert back.name == name and back.config == model.config and back.notes == []
    for k, v in model.state_dict().items():
        assert torch.equal(v, back.state_dict()[k]), k
    assert max_render_diff(model, back) == 0


def test_the_third_scale_is_a_flat_surfel(tmp_path):
    """scale_2 = log(0): splat-transform's 'zero-thickness surfel', Spark's zero scale, GaussianSplats3D's exp()=0."""
    model = random_model("gabor", n=30)
    arr, comments = read_ply_vertices(save_ply(model, tmp_path / "m.ply"))
    names = list(arr.dtype.names)
    assert names.index("scale_1") + 1 == names.index("scale_2") == names.index("rot_0") - 1
    assert np.all(arr["scale_2"] == -np.inf) and np.all(np.exp(arr["scale_2"]) == 0)
    assert "SplatRenderMode: 2dgs" in comments and "splatzoo model gabor" in comments
    assert np.isfinite(np.stack([arr[k] for k in names if k != "scale_2"])).all()
    # the normal a viewer derives from the rotation's third column is the surfel's, and nx..nz say the same
    normals = quat_to_rotmat(model.quats.detach())[:, :, 2].numpy()
    assert np.allclose(np.stack([arr["nx"], arr["ny"], arr["nz"]], 1), normals, atol=1e-6)
    # a version-1 file (no scale_2) still loads
    old = plyfile.PlyData([plyfile.PlyElement.describe(_drop(arr, "scale_2"), "vertex")], byte_order="<",
                          comments=[c for c in comments if not c.startswith("SplatRenderMode")])
    old.write(str(tmp_path / "v1.ply"))
    assert max_render_diff(model, load_ply(tmp_path / "v1.ply")) == 0


def _drop(arr, *names):
    keep = [k for k in arr.dtype.names if k not in names]
    out = np.empty(len(arr), dtype=[(k, arr.dtype[k]) for k in keep])
    for k in keep:
        out[k] = arr[k]
    return out


def _write(path: Path, columns: dict, comments=()) -> Path:
    """A PLY as another tool writes it, through plyfile (float32 properties, no splatzoo header)."""
    n = len(next(iter(columns.values())))
    arr = np.empty(n, dtype=[(k, "<f4") for k in columns])
    for k, v in columns.items():
        arr[k] = v
    plyfile.PlyData([plyfile.PlyElement.describe(arr, "vertex")], byte_order="<", comments=list(comments)).write(
        str(path))
    return path


def _gaussians(n, seed=0, sh_rest=0, three=True):
    rng = np.random.default_rng(seed)
    cols = {"x": rng.normal(size=n), "y": rng.normal(size=n), "z": rng.normal(size=n),
            "nx": np.zeros(n), "ny": np.zeros(n), "nz": np.zeros(n)}
    cols.update({f"f_dc_{i}": rng.normal(size=n) for i in range(3)})
    cols.update({f"f_rest_{i}": 0.1 * rng.normal(size=n) for i in range(sh_rest)})
    cols["opacity"] = rng.normal(size=n)
    cols.update({f"scale_{i}": rng.uniform(-5, -2, n) for i in range(3 if three else 2)})
    cols.update({f"rot_{i}": rng.normal(size=n) for i in range(4)})
    return cols


def test_a_2dgs_file_of_another_tool_loads_as_2dgs_exactly(tmp_path):
    cols = _gaussians(50, sh_rest=9, three=False)
    model = load_ply(_write(tmp_path / "point_cloud.ply", cols))
    assert model.name == "2dgs" and model.config.sh_degree == 1 and model.notes == []
    assert np.array_equal(model.means.detach().numpy(), np.stack([cols["x"], cols["y"], cols["z"]], 1).astype("f4"))
    assert np.array_equal(model.log_scales.detach().numpy()[:, 1], cols["scale_1"].astype("f4"))
    assert np.array_equal(model.sh_rest.detach().numpy()[:, 0, 1], cols["f_rest_3"].astype("f4"))  # channel-major
    assert not model.antialias


def test_a_3dgs_file_becomes_surfels_across_its_two_largest_axes(tmp_path):
    cols = _gaussians(200, seed=3)
    with pytest.warns(UserWarning, match=r"3DGS file .*two largest axes.* of 200 were far from flat"):
        model = load_ply(_write(tmp_path / "3dgs.ply", cols))
    assert model.name == "2dgs" and model.num_primitives == 200
    s = np.stack([cols[f"scale_{i}"] for i in range(3)], 1)
    q = np.stack([cols[f"rot_{i}"] for i in range(4)], 1)
    R = quat_to_rotmat(torch.tensor(q)).numpy()
    thin = s.argmin(1)
    # the surfel keeps the covariance of the two largest axes; the thinnest axis is its normal
    cov = np.einsum("nij,nj,nkj->nik", R, np.exp(2 * s), R)
    normal = R[np.arange(200), :, thin]
    expected = cov - np.exp(2 * s.min(1))[:, None, None] * normal[:, :, None] * normal[:, None, :]
    R2 = quat_to_rotmat(model.quats.detach().double()).numpy()
    s2 = model.log_scales.detach().double().numpy()
    got = np.einsum("nij,nj,nkj->nik", R2[:, :, :2], np.exp(2 * s2), R2[:, :, :2])
    assert np.allclose(got, expected, rtol=1e-4, atol=1e-9)
    assert np.allclose(np.abs((R2[:, :, 2] * normal).sum(1)), 1, atol=1e-5)
    assert np.all(np.linalg.det(R2) > 0.999)  # a rotation, never a mirror
    kept = np.sort(s, 1)[:, 1:]
    assert np.allclose(np.sort(s2, 1), kept, atol=1e-6)
    # Gaussians already thinnest along their third axis keep their quaternion bit for bit
    same = thin == 2
    assert same.any() and np.array_equal(model.quats.detach().numpy()[same], q[same].astype("f4"))


def test_a_3dgs_layout_with_flat_third_scales_is_exact(tmp_path):
    model = random_model("2dgs", n=30, sh_degree=2)
    arr, _ = read_ply_vertices(save_ply(model, tmp_path / "m.ply"))
    cols = {k: arr[k] for k in arr.dtype.names}  # scale_2 = -inf, and no splatzoo header
    back = load_ply(_write(tmp_path / "plain.ply", cols))
    assert back.notes == [] and back.config.sh_degree == 2
    assert max_render_diff(model, back) < 1e-6


def test_flatten_gaussians_picks_the_thinnest_axis():
    q = np.array([[1.0, 0, 0, 0]] * 3, np.float32)
    s = np.log(np.array([[0.1, 1, 2], [1, 0.1, 2], [1, 2, 0.1]], np.float32))
    scales, quats, thick = flatten_gaussians(s, q)
    normals = quat_to_rotmat(torch.tensor(quats))[:, :, 2].numpy()
    assert np.allclose(np.abs(normals), np.eye(3), atol=1e-6) and thick == 0
    assert np.allclose(np.exp(scales), [[1, 2], [2, 1], [1, 2]], atol=1e-6)


def test_files_whose_model_cannot_be_told_are_refused(tmp_path):
    model = random_model("gabor", n=10)
    arr, _ = read_ply_vertices(save_ply(model, tmp_path / "g.ply"))
    cols = {k: arr[k] for k in arr.dtype.names}
    with pytest.raises(SplatzooError, match=r"gabor_color_base_0.* of the splatzoo model .*'gabor'.* but no "
                                            r"'comment splatzoo model' header"):
        load_ply(_write(tmp_path / "headless.ply", cols))
    cols = _gaussians(5)
    del cols["opacity"], cols["rot_3"]
    with pytest.raises(SplatzooError, match=r"lacks the properties opacity, rot_3 .*not a 2DGS/3DGS splat file"):
        load_ply(_write(tmp_path / "missing.ply", cols))
    points = {"x": np.zeros(3), "y": np.zeros(3), "z": np.zeros(3), "red": np.ones(3), "green": np.ones(3),
              "blue": np.ones(3)}
    with pytest.raises(SplatzooError, match=r"a point cloud .*not a splat model"):
        load_ply(_write(tmp_path / "points.ply", points))
    with pytest.raises(SplatzooError, match=r"5 f_rest properties match no SH degree"):
        load_ply(_write(tmp_path / "sh.ply", _gaussians(5, sh_rest=5)))
    beta = random_model("beta", n=5) if "beta" in builtin_models() else None
    if beta is not None:
        arr, _ = read_ply_vertices(save_ply(beta, tmp_path / "b.ply"))
        with pytest.raises(SplatzooError, match=r"falloff_logit of the splatzoo model 'beta'(, '[^']+')* but no "
                                                r"'comment splatzoo model' header"):
            load_ply(_write(tmp_path / "b-headless.ply", {k: arr[k] for k in arr.dtype.names}))
    # another tool's extras are ignored, and the warning says which
    with pytest.warns(UserWarning, match=r"ignored the properties filter_3D"):
        load_ply(_write(tmp_path / "extra.ply", {**_gaussians(5, three=False), "filter_3D": np.zeros(5)}))


def test_load_ply_keeps_its_checks_for_headerless_files(tmp_path):
    cols = _gaussians(5, three=False)
    cols["scale_0"][2] = np.nan
    with pytest.raises(SplatzooError, match=r"parameter 'log_scales' has 1 non-finite"):
        load_ply(_write(tmp_path / "nan.ply", cols))
    cols = _gaussians(5)
    cols["rot_1"][0] = np.inf
    with pytest.raises(SplatzooError, match=r"1 Gaussian\(s\) have NaN or infinite"):
        load_ply(_write(tmp_path / "inf.ply", cols))


def test_ascii_export_round_trips(tmp_path):
    model = random_model("gabor", n=15)
    path = export(_saved(model, tmp_path), tmp_path / "a.ply", "ply:ascii=true")
    assert b"format ascii 1.0" in path.read_bytes()[:200]
    back = load_ply(path)
    assert max_render_diff(model, back) == 0


def _saved(model, tmp_path) -> Path:
    splatzoo.save_model(model, tmp_path / "model.pt")
    return tmp_path / "model.pt"


def test_counts_are_checked_before_plyfile_allocates(tmp_path):
    """plyfile sizes each element by its header count up front: a crafted count in any element (a mesh's faces
    too) is refused by the size checks in front of it, fast and without the memory it asks for."""
    import time
    import tracemalloc

    header = ("ply\nformat {fmt} 1.0\nelement vertex 1\nproperty float x\nproperty float y\nproperty float z\n"
              "element face {faces}\nproperty list uchar int vertex_indices\nend_header\n")
    cases = {"bin.ply": header.format(fmt="binary_little_endian", faces=10**12).encode() + bytes(12 + 4),
             "ascii.ply": header.format(fmt="ascii", faces=10**12).encode() + b"0 0 0\n3 0 0 0\n"}
    for name, data in cases.items():
        (tmp_path / name).write_bytes(data)
        tracemalloc.start()
        start = time.perf_counter()
        try:
            with pytest.raises(SplatzooError, match=r"promises|truncated"):
                read_ply_vertices(tmp_path / name)
            peak = tracemalloc.get_traced_memory()[1]
        finally:
            tracemalloc.stop()
        assert time.perf_counter() - start < 1.0 and peak < 5_000_000, name
    # the same file with its true face count reads (its vertices)
    (tmp_path / "ok.ply").write_bytes(header.format(fmt="ascii", faces=1).encode() + b"0.5 0 0\n3 0 0 0\n")
    arr, _ = read_ply_vertices(tmp_path / "ok.ply")
    assert arr["x"].tolist() == [0.5]


def test_big_endian_files_load(tmp_path):
    model = random_model("2dgs", n=12, sh_degree=1)
    arr, comments = read_ply_vertices(save_ply(model, tmp_path / "m.ply"))
    plyfile.PlyData([plyfile.PlyElement.describe(arr.astype(arr.dtype.newbyteorder(">")), "vertex")],
                    byte_order=">", comments=comments).write(str(tmp_path / "be.ply"))
    assert b"binary_big_endian" in (tmp_path / "be.ply").read_bytes()[:100]
    assert max_render_diff(model, load_ply(tmp_path / "be.ply")) == 0


# --- the registry and --format ---------------------------------------------------------------------------------

def test_format_parsing_and_errors():
    spec, options = parse_format("spz:version=3")
    assert spec.name == "spz" and options.version == 3
    spec, options = parse_format("sog:sh-iterations=4,gpu=cpu")
    assert options.sh_iterations == 4
    assert parse_format("ply:ascii=yes")[1].ascii is True
    with pytest.raises(UnknownNameError, match=r"unknown export format 'splz'; known: .*ply.*sog.*spz.*Did you mean"):
        parse_format("splz")
    with pytest.raises(SplatzooError, match=r"'spz' has no option\(s\) versoin; its options are: version"):
        parse_format("spz:versoin=3")
    with pytest.raises(SplatzooError, match=r"option version expects int, got 'four'"):
        parse_format("spz:version=four")
    with pytest.raises(SplatzooError, match=r"version must be 3 or 4"):
        parse_format("spz:version=5")
    with pytest.raises(SplatzooError, match=r"must look like key=value"):
        parse_format("spz:version")


@dataclass
class _EchoOptions:
    scale: float = field(default=1.0, metadata={"help": "a factor"})
    flag: bool = False


def _echo(source, out, *, progress=None, scale=1.0, flag=False):
    Path(out).write_text(json.dumps({"source": str(source), "scale": scale, "flag": flag}))
    return Path(out)


@pytest.fixture
def echo_format():
    register_exporter(ExporterSpec("test-echo", _echo, _EchoOptions, "test", (".echo",)))
    yield "test-echo"
    EXPORTERS._entries.pop("test-echo", None)


def test_a_registered_format_is_dispatched_with_its_options(tmp_path, echo_format):
    model = random_model("2dgs", n=5)
    src = _saved(model, tmp_path)
    path = export(src, tmp_path / "o.echo", "test-echo:scale=2.5,flag=on")
    assert json.loads(path.read_text()) == {"source": str(src), "scale": 2.5, "flag": True}
    with pytest.raises(SplatzooError, match=r"--out must end in \.echo.*e\.g\. .*o\.echo"):
        export(src, tmp_path / "o.ply", "test-echo")
    (tmp_path / "x.echo").write_text("")
    with pytest.raises(SplatzooError, match="refusing to export onto the model being read"):
        export(tmp_path / "x.echo", tmp_path / "x.echo", "test-echo")
    res = runner.invoke(app, ["export", str(src), "--format", "test-echo:flag=true", "--out", str(tmp_path / "c.echo")])
    assert res.exit_code == 0, res.output
    assert json.loads((tmp_path / "c.echo").read_text())["flag"] is True


def test_cli_lists_formats_and_refuses_unknown_ones(tmp_path):
    res = runner.invoke(app, ["export", "--list"])
    assert res.exit_code == 0
    for name in ("ply", "spz", "sog", "compressed-ply", "baked", "mesh-glb"):
        assert f"\n{name} " in "\n" + res.output
    assert "version=INT" in res.output and "ascii=BOOL" in res.output
    assert runner.invoke(app, ["export", "--format", "help"]).output == res.output
    src = _saved(random_model("2dgs", n=5), tmp_path)
    res = runner.invoke(app, ["export", str(src), "--format", "obj", "--out", str(tmp_path / "m.obj")])
    assert isinstance(res.exception, UnknownNameError)
    assert "known: baked, compressed-ply, glb-splat, mesh-glb, mesh-obj, ply, sog, spz" in str(res.exception)
    res = runner.invoke(app, ["export", str(src), "--format", "spz", "--out", str(tmp_path / "m.ply")])
    assert isinstance(res.exception, SplatzooError) and "must end in .spz" in str(res.exception)
    res = runner.invoke(app, ["export", str(src), "--out", str(tmp_path / "m.ply")])
    assert res.exit_code == 0 and load_ply(tmp_path / "m.ply").num_primitives == 5


def test_lazy_formats_say_when_their_module_is_missing(tmp_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "splatzoo.bake", None)  # as if this installation had no splatzoo.bake
    src = _saved(random_model("2dgs", n=5), tmp_path)
    with pytest.raises(SplatzooError, match=r"export format 'baked' needs splatzoo.bake, which this splatzoo "
                                            r"installation does not have"):
        export(src, tmp_path / "b.ply", "baked")
    res = runner.invoke(app, ["export", "--list"])
    assert res.exit_code == 0 and "unavailable: export format 'baked' needs splatzoo.bake" in res.output
    assert not (tmp_path / "b.ply").exists()


def test_export_formats_do_not_import_their_modules_until_used(monkeypatch):
    lazy = ("splatzoo.bake", "splatzoo.mesh_texture", "splatzoo.splat_tools")
    for name in lazy:
        monkeypatch.delitem(sys.modules, name, raising=False)
    assert isinstance(EXPORTERS.get("baked").fn, str) and isinstance(EXPORTERS.get("mesh-glb").fn, str)
    parse_format("ply")
    parse_format("spz:version=3")
    assert [m for m in lazy if m in sys.modules] == []


# --- splat-transform (SPZ, SOG) ----------------------------------------------------------------------------------

def _splat_transform():
    from splatzoo.splat_tools import find_splat_transform

    try:
        return find_splat_transform()
    except SplatzooError as e:
        pytest.skip(f"splat-transform is not installed here ({str(e)[:80]})")


def test_a_missing_splat_transform_says_how_to_install_it(tmp_path, monkeypatch):
    import splatzoo.splat_tools as tools

    monkeypatch.setenv(tools.ENV, str(tmp_path / "nowhere"))
    with pytest.raises(SplatzooError, match=r"SPLATZOO_SPLAT_TRANSFORM=.*not an executable.*scripts/install.sh"):
        tools.find_splat_transform()
    monkeypatch.delenv(tools.ENV)
    monkeypatch.setattr(tools, "_CHECKOUT_CLI", tmp_path / "none")
    monkeypatch.setenv("PATH", str(tmp_path))
    with pytest.raises(SplatzooError, match=r"not installed: install it with `bash scripts/install.sh`.*npm install -g "
                                            r"@playcanvas/splat-transform"):
        export(_saved(random_model("2dgs", n=5), tmp_path), tmp_path / "m.spz", "spz")
    assert not (tmp_path / "m.spz").exists()


def _scene_model(n=300):
    g = torch.Generator().manual_seed(0)
    model = splatzoo.create_model("2dgs", torch.randn(n, 3, generator=g) * 0.5, torch.rand(n, 3, generator=g))
    with torch.no_grad():
        model.logit_opacity.copy_(torch.randn(n, generator=g))
    return model


# Tolerances of the formats' quantisation (what splat-transform 3.7.0 keeps), measured on this 300-surfel scene with
# positions within +-2: SOG positions 16 bits over a log-scaled range (6e-5 seen), SPZ 12 fraction bits (1.2e-4);
# opacity and colour 8 bits, 1/255 (colour through SOG's 256-entry codebook: 2e-3 seen); SPZ log scales in steps of
# 1/16 (0.031 seen). Each bound below is about twice what was seen, within one quantisation step.
TOLERANCE = {"sog": {"position": 5e-4, "opacity": 1 / 255 + 1e-3, "color": 0.01, "log_scale": 0.01},
             "spz": {"position": 5e-4, "opacity": 1 / 255 + 1e-3, "color": 0.01, "log_scale": 0.04}}


@pytest.mark.parametrize("fmt", ["sog", "spz"])
def test_splat_transform_round_trip(tmp_path, fmt):
    _splat_transform()
    from splatzoo.splat_tools import convert_file

    model = _scene_model()
    src = _saved(model, tmp_path)
    packed = export(src, tmp_path / f"m.{fmt}", fmt)
    assert packed.stat().st_size < save_ply(model, tmp_path / "ref.ply").stat().st_size
    with pytest.warns() if fmt == "spz" else _no_warning():  # SPZ holds no 2DGS tag: a third scale comes back
        back = load_ply(convert_file(packed, tmp_path / f"back-{fmt}.ply"))
    assert back.name == "2dgs" and back.num_primitives == model.num_primitives
    with pytest.warns() if fmt == "spz" else _no_warning():  # commands read SPZ and SOG files through splat-transform
        assert load_source(packed)[0].num_primitives == model.num_primitives
    a, b = model.means.detach().numpy(), back.means.detach().numpy()
    order = ((a[:, None] - b[None]) ** 2).sum(-1).argmin(1)  # the formats may reorder the splats
    assert len(set(order.tolist())) == len(a)
    tol = TOLERANCE[fmt]
    assert np.abs(a - b[order]).max() < tol["position"]
    opacity = lambda m: torch.sigmoid(m.logit_opacity).detach().numpy()  # noqa: E731
    assert np.abs(opacity(model) - opacity(back)[order]).max() < tol["opacity"]
    color = lambda m: (m.sh_dc[:, 0] * SH_C0 + 0.5).detach().numpy()  # noqa: E731
    assert np.abs(color(model) - color(back)[order]).max() < tol["color"]
    assert np.abs(model.log_scales.detach().numpy() - back.log_scales.detach().numpy()[order]).max() < tol["log_scale"]
    normal = lambda m: quat_to_rotmat(m.quats.detach())[:, :, 2].numpy()  # noqa: E731
    assert np.abs((normal(model) * normal(back)[order]).sum(1)).min() > 0.99


class _no_warning:
    def __enter__(self):
        import warnings

        self.catch = warnings.catch_warnings()
        self.catch.__enter__()
        warnings.simplefilter("error")

    def __exit__(self, *exc):
        self.catch.__exit__(*exc)


def test_splat_transform_reads_our_ply(tmp_path):
    """Every splat of our ply survives splat-transform's NaN filter (which keeps -inf in scale_*) and its reader sees
    a 2DGS scene with our extra properties."""
    from splatzoo.splat_tools import run_splat_transform

    _splat_transform()
    model = random_model("gabor", n=25)
    ply = save_ply(model, tmp_path / "g.ply")
    info = json.loads(run_splat_transform(["-q", str(ply), "--filter-nan", "--info", "json", "null"], what="test"))
    assert info["numGaussians"] == 25 and info["model"] == "2dgs"
    assert "gabor_weight_0" in [c["name"] for c in info["extraColumns"]]
    path = export(ply, tmp_path / "g.compressed.ply", "compressed-ply")
    assert path.read_bytes()[:3] == b"ply" and not list(tmp_path.glob(".g.*"))
    with pytest.raises(SplatzooError, match=r"is a compressed PLY .*convert it to a plain one first"):
        load_ply(path)
    back, _ = load_source(path)  # the commands convert it themselves (its waves are gone: a 2dgs model)
    assert back.name == "2dgs" and back.num_primitives == 25


# --- commands that read model files --------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def tiny_data(tmp_path_factory):
    from splatzoo.data.synthetic import make_synthetic_scene

    return make_synthetic_scene("plain", tmp_path_factory.mktemp("data") / "data", views=4, width=24, height=24)


def test_eval_render_view_and_train_read_a_ply(tmp_path, tiny_data):
    from splatzoo.model_files import open_model
    from splatzoo.viewer import Viewer, expand_runs, viewer_source

    g = torch.Generator().manual_seed(1)
    model = splatzoo.create_model("2dgs", torch.randn(20, 3, generator=g) * 0.3, torch.rand(20, 3, generator=g))
    ply = save_ply(model, tmp_path / "m.ply")
    res = runner.invoke(app, ["eval", str(ply), "--data", str(tiny_data), "--backend", "reference",
                              "--out", str(tmp_path / "metrics.json")])
    assert res.exit_code == 0, res.output
    metrics = json.loads((tmp_path / "metrics.json").read_text())
    assert metrics["num_primitives"] == 20 and metrics["psnr"] > 0
    res = runner.invoke(app, ["render", str(ply), "--data", str(tiny_data), "--backend", "reference"])
    assert res.exit_code == 0, res.output
    assert [p.suffix for p in (tmp_path / "m_renders").rglob("*") if p.is_file()] == [".png"]
    res = runner.invoke(app, ["eval", str(ply)])
    assert isinstance(res.exception, SplatzooError) and "--data DATA" in str(res.exception)
    # the viewer shows a model file without training cameras, framed from a camera that looks at it
    source = viewer_source(open_model(expand_runs([ply])[0], latest=True))
    assert source.views == [] and source.fixed_model.num_primitives == 20 and "no training cameras" in source.note
    home = Viewer([source], host="127.0.0.1", port=0, backend="reference", snapshot_dir=tmp_path).home_camera()
    with torch.no_grad():
        assert float(model.render(home.to(dtype=torch.float32), backend="reference").alpha.max()) > 0.1
    # training starts from the file's surfels (and its model), not from the dataset's points
    res = runner.invoke(app, ["train", str(tiny_data), "--init-from", str(ply), "--iterations", "2", "--no-densify",
                              "--backend", "reference", "--out", str(tmp_path / "run")])
    assert res.exit_code == 0, res.output
    record = json.loads((tmp_path / "run" / "config.json").read_text())
    assert record["model"] == "2dgs" and record["init_from"] == str(ply.resolve())
    assert splatzoo.load_model(tmp_path / "run" / "model.pt").num_primitives == 20
    res = runner.invoke(app, ["train", str(tiny_data), "--init-from", str(ply), "--model", "gabor", "--out",
                              str(tmp_path / "run2")])
    assert isinstance(res.exception, SplatzooError) and "holds a '2dgs' model but this run trains 'gabor'" in \
        str(res.exception)
    assert not (tmp_path / "run2" / "config.json").exists()


def test_ply_for_3dgs_viewers_keeps_each_splats_mass(tmp_path):
    """ply:viewer=3dgs shrinks each surfel's screen variance by the viewer's 0.3 px^2 (less the model's own footprint)
    and lowers its opacity so that o sqrt(s0 s1) on screen stays; mip raises it instead. A model file has no cameras:
    a clear error."""
    import torch

    from splatzoo import Camera, create_model
    from splatzoo.export import VIEWER_DILATION, compensate_viewer_dilation, export, load_ply, save_ply

    torch.manual_seed(0)
    cam = Camera.look_at([0, 0, -3], [0, 0, 0], width=64, height=64)
    model = create_model("2dgs", torch.randn(50, 3) * 0.3, torch.rand(50, 3))
    model.antialias = False
    before = {k: v.detach().clone() for k, v in model.per_primitive().items()}
    compensate_viewer_dilation(model, [cam], "3dgs")
    after = model.per_primitive()
    assert torch.all(after["log_scales"] < before["log_scales"])
    assert torch.all(after["logit_opacity"] <= before["logit_opacity"] + 1e-6)
    # the mass on screen: o sqrt(s0 s1) before equals o' sqrt((s0' + d)(s1' + d)) after, d the viewer's dilation
    z = (model.per_primitive()["means"].detach().double()[:, 2] + 3)
    px2 = (z / float(cam.K[0, 0])) ** 2
    from splatzoo.geometry import quat_to_rotmat

    axes = quat_to_rotmat(torch.nn.functional.normalize(before["quats"].double(), dim=1))[:, :, :2]
    d = torch.nn.functional.normalize(before["means"].double() - torch.tensor([0, 0, -3.0]).double(), dim=1)
    fore = (1 - torch.einsum("nk,nki->ni", d, axes) ** 2).clamp(0.05, 1)
    s0 = torch.exp(2 * before["log_scales"].double()) / px2[:, None] * fore
    s1 = torch.exp(2 * after["log_scales"].detach().double()) / px2[:, None] * fore
    mass0 = torch.sigmoid(before["logit_opacity"].double()) * s0.prod(1).sqrt()
    mass1 = torch.sigmoid(after["logit_opacity"].detach().double()) * (s1 + VIEWER_DILATION).prod(1).sqrt()
    unclamped = torch.sigmoid(after["logit_opacity"].detach().double()) > 2e-6
    assert torch.allclose(mass0[unclamped], mass1[unclamped], rtol=1e-4)
    with pytest.raises(SplatzooError, match="unknown viewer rule"):
        compensate_viewer_dilation(model, [cam], "sibr")
    save_ply(model, tmp_path / "m.ply")
    with pytest.raises(SplatzooError, match="training cameras: export from the run"):
        export(tmp_path / "m.ply", tmp_path / "v.ply", "ply:viewer=3dgs")
    with pytest.raises(SplatzooError, match="viewer='sibr' is not known"):
        export(tmp_path / "m.ply", tmp_path / "v.ply", "ply:viewer=sibr")
    assert load_ply(tmp_path / "m.ply").num_primitives == 50
