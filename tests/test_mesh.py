"""Mesh extraction: accuracy against the true mesh of a synthetic scene after a short training, options, errors."""
import subprocess
import sys

import numpy as np
import pytest
import torch
from typer.testing import CliRunner

from splatzoo import Camera, create_model
from splatzoo.cli import app
from splatzoo.errors import SplatzooError
from splatzoo.mesh import extract_mesh, mesh_accuracy, mesh_parameters, write_mesh

runner = CliRunner()

# Thresholds of the issue, as fractions of the scene radius (scene.extent / 1.1: the radius of the camera
# centres around their mean, the 2DGS/3DGS convention)
MAX_MEAN_DISTANCE = 0.01
MIN_WITHIN_2PCT = 0.90
TRAIN = dict(iterations=200, densify=False, seed=0)  # all 4000 scene points, fixed count


@pytest.fixture(scope="module")
def trained_run(tmp_path_factory):
    """A short 2DGS training on a small synthetic scene that comes with its true mesh."""
    from splatzoo.data import load_scene
    from splatzoo.data.synthetic import make_synthetic_scene
    from splatzoo.runs import train
    from splatzoo.training import TrainConfig

    root = tmp_path_factory.mktemp("mesh")
    data = make_synthetic_scene("sweater", root / "sweater", views=16, width=96, height=96)
    scene = load_scene(data)
    train(scene, "2dgs", {}, TrainConfig(backend="auto", **TRAIN), root / "run", progress=False, evaluate_at_end=False)
    return root / "run", scene


@pytest.mark.slow
def test_extracted_mesh_matches_the_true_surface(trained_run, tmp_path):
    import open3d as o3d

    run, scene = trained_run
    out = tmp_path / "mesh.ply"
    res = runner.invoke(app, ["extract-mesh", str(run), "--out", str(out)])
    assert res.exit_code == 0, res.output
    mesh = o3d.io.read_triangle_mesh(str(out))
    assert len(mesh.triangles) > 1000 and mesh.has_vertex_colors()
    colors = np.asarray(mesh.vertex_colors)
    assert 0.05 < colors.mean() < 0.95  # real colours, not black or white
    gt = o3d.io.read_triangle_mesh(str(scene.mesh_path))
    radius = scene.extent / 1.1
    m = mesh_accuracy(mesh, gt, [v.camera for v in scene.train], radius, within=0.02)
    print("mesh accuracy:", m)
    assert m["accuracy_mean"] < MAX_MEAN_DISTANCE, m
    assert m["completeness_within"] >= MIN_WITHIN_2PCT, m


@pytest.mark.slow
def test_keep_largest_and_expected_depth(trained_run):
    from splatzoo.runs import load_run

    model, scene, _ = load_run(trained_run[0])
    cams = [v.camera for v in scene.train]
    full, params, _ = extract_mesh(model, cams, depth="expected")
    largest, _, stats = extract_mesh(model, cams, depth="expected", keep_largest=True)
    assert 0 < len(largest.triangles) <= len(full.triangles)
    labels, counts, _ = largest.cluster_connected_triangles()
    assert len(np.asarray(counts)) == 1 and stats.triangles == len(largest.triangles)


def _cameras(n=6, size=24):
    return [Camera.look_at([3 * np.cos(a), 3 * np.sin(a), 0.5], [0, 0, 0], up=(0, 0, -1), width=size, height=size,
                           fov_deg=50, dtype=torch.float32) for a in np.linspace(0, 2 * np.pi, n, endpoint=False)]


def _blob(opacity_logit: float):
    g = torch.Generator().manual_seed(0)
    d = torch.randn(400, 3, generator=g)
    pts = 0.5 * d / d.norm(dim=1, keepdim=True)
    model = create_model("2dgs", pts, torch.full((400, 3), 0.6))
    with torch.no_grad():
        model.logit_opacity.fill_(opacity_logit)
        model.log_scales.add_(0.7)
    return model


def test_defaults_follow_the_cameras():
    cams = _cameras()
    p = mesh_parameters(cams)
    assert np.allclose(p.center, 0, atol=1e-6) and abs(p.radius - np.sqrt(9.25)) < 1e-4
    assert abs(p.depth_trunc - 2 * p.radius) < 1e-9 and abs(p.sdf_trunc - 5 * p.voxel_size) < 1e-12
    # small images: half a pixel's footprint wins over depth_trunc / 1024
    assert abs(p.voxel_size - 0.5 * p.radius / float(cams[0].K[0, 0])) < 1e-6
    big = [c.scaled(100) for c in cams]  # 2400 px: the 2DGS rule
    assert abs(mesh_parameters(big).voxel_size - p.depth_trunc / 1024) < 1e-9
    q = mesh_parameters(cams, voxel_size=0.01, depth_trunc=4.0)
    assert (q.voxel_size, q.sdf_trunc, q.depth_trunc) == (0.01, 0.05, 4.0)


def test_empty_meshes_say_why(tmp_path):
    cams = _cameras()
    with pytest.raises(SplatzooError, match="nothing opaque"):
        extract_mesh(_blob(-8.0), cams)
    with pytest.raises(SplatzooError, match="beyond the depth truncation.*--depth-trunc"):
        extract_mesh(_blob(6.0), cams, depth_trunc=1.0)
    with pytest.raises(SplatzooError, match="--depth"):
        extract_mesh(_blob(6.0), cams, depth="mean")
    mesh, _, _ = extract_mesh(_blob(6.0), cams)   # the same blob, sensibly set up, gives a mesh
    assert len(mesh.triangles) > 0
    blocker = tmp_path / "file"
    blocker.write_text("x")
    with pytest.raises(SplatzooError, match="cannot write"):
        write_mesh(mesh, blocker / "mesh.ply")
    with pytest.raises(SplatzooError, match="is a folder"):
        write_mesh(mesh, tmp_path)


def test_a_mesh_file_name_that_cannot_be_written_is_refused_before_any_work(tmp_path):
    run = tmp_path / "run"
    run.mkdir()   # no model in it: a refusal that names --out comes before the run is read
    blocker = tmp_path / "file"
    blocker.write_text("x")
    for out, message in ((tmp_path, "it is a folder"), (tmp_path / "m", "(no suffix)"),
                         (tmp_path / "m.xyz", "not a mesh file name splatzoo writes (.xyz)"),
                         (blocker / "sub" / "m.ply", "file is a file, not a folder")):
        r = runner.invoke(app, ["extract-mesh", str(run), "--out", str(out)])
        assert isinstance(r.exception, SplatzooError) and message in str(r.exception), (out, r.output, r.exception)
        assert "model" not in str(r.exception)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["file", "run"] and not list(run.iterdir())


def test_run_without_model(tmp_path):
    run = tmp_path / "run"
    run.mkdir()
    (run / "config.json").write_text('{"data": "nowhere"}')
    res = runner.invoke(app, ["extract-mesh", str(run)])
    assert res.exit_code != 0 and isinstance(res.exception, SplatzooError)
    assert "model.pt" in str(res.exception)
    res = runner.invoke(app, ["extract-mesh", str(tmp_path / "missing")])
    assert isinstance(res.exception, SplatzooError) and "does not exist" in str(res.exception)


def test_import_splatzoo_does_not_load_open3d():
    code = "import sys, splatzoo, splatzoo.mesh, splatzoo.export; print('open3d' in sys.modules)"
    assert subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.strip() == "False"
