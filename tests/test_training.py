"""Training end to end: loss goes down, interrupted runs resume to the same result, CLI and compare outputs."""
import json
import math

import pytest
import torch
from typer.testing import CliRunner

from splatzoo.cli import app
from splatzoo.data import load_scene
from splatzoo.errors import SplatzooError
from splatzoo.runs import train
from splatzoo.training import TrainConfig
from splatzoo.training.losses import depth_to_normal
from splatzoo import Camera

runner = CliRunner()


@pytest.fixture(scope="module")
def tiny_data(tmp_path_factory):
    from splatzoo.data.synthetic import make_synthetic_scene

    return make_synthetic_scene("sweater", tmp_path_factory.mktemp("data") / "sweater", views=10, width=48, height=48)


def small_config(**kw):
    base = dict(iterations=40, backend="auto", num_primitives=300, log_every=5, eval_every=20, seed=3)
    base.update(kw)
    return TrainConfig(**base)


def test_training_raises_test_psnr(tiny_data, tmp_path):
    scene = load_scene(tiny_data)
    result = train(scene, "gabor", {}, small_config(iterations=150, densify=False), tmp_path / "run", progress=False)
    log = [json.loads(line) for line in (tmp_path / "run" / "train_log.jsonl").read_text().splitlines()]
    first = [r["train_psnr"] for r in log if "train_psnr" in r][:3]
    last = [r["train_psnr"] for r in log if "train_psnr" in r][-3:]
    assert sum(last) / 3 > sum(first) / 3 + 2.0, (first, last)
    m = result.metrics
    for key in ("psnr", "ssim", "lpips", "fps", "train_seconds", "num_primitives", "size_bytes", "iterations",
                "model", "backend", "conventions"):
        assert key in m
    # the untrained model's test PSNR, for comparison
    from splatzoo import create_model
    from splatzoo.training.trainer import select_initial_points, test_psnr

    pts, cols = select_initial_points(scene.points, scene.colors, 300, 3)
    initial = test_psnr(create_model("gabor", pts, cols, seed=3), scene, result.metrics["backend"])
    # the untrained model already shows each point's colour (the residual start): 150 steps add about 2 dB here
    assert m["psnr"] > initial + 1.5, (initial, m["psnr"])
    paper_start = test_psnr(create_model("gabor", pts, cols, seed=3, color_param="paper"), scene,
                            result.metrics["backend"])
    assert initial > paper_start + 1.5, (initial, paper_start)  # the paper's start is dark
    assert (tmp_path / "run" / "renders" / "test").is_dir()
    cfg = json.loads((tmp_path / "run" / "config.json").read_text())
    assert cfg["model_config"]["n_waves"] == 4 and cfg["train"]["iterations"] == 150


@pytest.mark.parametrize("model, options", [("gabor", {}), ("2dgs", {}),
                                            # a measured pruning at step 30 (after densification's window), after
                                            # the stop: the resumed run must measure and decide as the full one
                                            ("gabor-adaptive", {"prune_from": 0.3})])
def test_resume_gives_the_same_parameters(tiny_data, tmp_path, model, options):
    scene = load_scene(tiny_data)
    cfg = small_config(iterations=30, backend="reference", num_primitives=120, densify=True,
                       densify_from=0, densify_interval=10000, opacity_reset_interval=20000)
    full = train(scene, model, options, cfg, tmp_path / "full", progress=False, evaluate_at_end=False)
    part = train(scene, model, options, cfg, tmp_path / "part", progress=False, evaluate_at_end=False,
                 stop_after=17)
    assert not (tmp_path / "part" / "model.pt").exists()
    resumed = train(scene, model, {}, None, tmp_path / "part", resume=True, progress=False, evaluate_at_end=False)
    a, b = full.model.state_dict(), resumed.model.state_dict()
    assert a.keys() == b.keys() and full.model.summary() == resumed.model.summary()
    if model == "gabor-adaptive":
        assert 0 < full.model.summary()["wave_fraction"] < 1  # the prunings removed some waves and kept some
    for k in a:
        assert torch.equal(a[k], b[k]), k
    log_a = (tmp_path / "full" / "train_log.jsonl").read_text().splitlines()
    log_b = (tmp_path / "part" / "train_log.jsonl").read_text().splitlines()
    assert [json.loads(x)["iteration"] for x in log_a] == [json.loads(x)["iteration"] for x in log_b]
    del part


def test_existing_run_is_not_overwritten(tiny_data, tmp_path):
    train(tiny_data, "2dgs", {}, small_config(iterations=2), tmp_path / "r", progress=False, evaluate_at_end=False)
    with pytest.raises(SplatzooError, match="--resume"):
        train(tiny_data, "2dgs", {}, small_config(iterations=2), tmp_path / "r", progress=False)
    with pytest.raises(SplatzooError, match="no checkpoint"):
        train(tiny_data, "2dgs", {}, None, tmp_path / "empty", resume=True, progress=False)


def test_depth_to_normal_of_a_plane():
    cam = Camera.look_at([0.0, 0.0, -3.0], [0.0, 0.0, 0.0], width=16, height=16, dtype=torch.float32)
    depth = torch.full((16, 16), 3.0)
    n = depth_to_normal(depth, cam)
    assert torch.allclose(n[5:10, 5:10], torch.tensor([0.0, 0.0, -1.0]).expand(5, 5, 3), atol=1e-5)


def test_cli_train_eval_render_compare(tiny_data, tmp_path):
    run = tmp_path / "cli_run"
    r = runner.invoke(app, ["train", str(tiny_data), "--model", "gabor", "--n-waves", "2", "--iterations", "20",
                            "--num-primitives", "200", "--no-densify", "--out", str(run)])
    assert r.exit_code == 0, r.output
    cfg = json.loads((run / "config.json").read_text())
    assert cfg["model_config"]["n_waves"] == 2
    r = runner.invoke(app, ["eval", str(run), "--lpips-net", "alex"])
    assert r.exit_code == 0, r.output
    assert "PSNR" in r.output and "metrics.json" in r.output and '"psnr"' not in r.output
    metrics = json.loads((run / "metrics.json").read_text())
    assert "alex" in metrics["conventions"]["lpips"] and metrics["num_primitives"] == 200
    r = runner.invoke(app, ["render", str(run), "--split", "train", "--video", "--frames", "8"])
    assert r.exit_code == 0, r.output
    video = run / "renders" / "orbit.webm"
    assert video.stat().st_size > 100
    import cv2

    cap = cv2.VideoCapture(str(video))
    frames = 0
    while cap.read()[0]:
        frames += 1
    assert frames == 8 and cap.get(cv2.CAP_PROP_FOURCC) != 0
    r = runner.invoke(app, ["train", str(tiny_data), "--model", "gabor", "--n-wave", "2", "--out", str(tmp_path / "x")])
    assert r.exit_code != 0 and "n-waves" in str(r.exception or r.output)

    out = tmp_path / "cmp"
    r = runner.invoke(app, ["compare", "gabor", "2dgs", "--data", str(tiny_data), "--out", str(out),
                            "--iterations", "20", "--num-primitives", "200"])
    assert r.exit_code == 0, r.output
    assert f"wrote {out}" in r.output
    report = json.loads((out / "compare.json").read_text())
    assert set(report["runs"]) == {"gabor", "2dgs"} and report["settings"]["num_primitives"] == 200
    for m in report["runs"].values():
        assert m["num_primitives"] == 200
    text = (out / "report.md").read_text()
    assert "| gabor |" in text and "**" in text
    for png in ("compare.png", "convergence.png"):
        assert (out / png).stat().st_size > 10_000


def test_checkpoint_loads_as_a_model_and_outputs_are_readable(tiny_data, tmp_path):
    import os
    import stat

    from splatzoo import load_model

    train(tiny_data, "gabor", {}, small_config(iterations=3), tmp_path / "r", progress=False, evaluate_at_end=False,
          stop_after=2)
    model = load_model(tmp_path / "r" / "checkpoint.pt")
    assert model.name == "gabor" and model.num_primitives == 300
    mode = stat.S_IMODE(os.stat(tmp_path / "r" / "config.json").st_mode)
    assert mode & stat.S_IRGRP and mode & stat.S_IROTH


def test_densification_is_sane_at_any_run_length(tiny_data):
    """A short run keeps the 30k schedule's statistics window and reset spacing; growth is capped per step and in
    all (one surfel per 128 training pixels by default)."""
    from splatzoo.training.densify import DensifyStats, densify_and_prune
    from splatzoo.model_checks import densify_budget
    from splatzoo.training.trainer import Trainer
    from splatzoo.zoo import make_config

    scene = load_scene(tiny_data)
    short = Trainer.start(scene, "2dgs", make_config("2dgs"), small_config(iterations=3000, densify=True), "cpu",
                          torch.device("cpu"))
    assert short.d_every == 100 and short.reset_every == 1000
    pixels = sum(v.camera.width * v.camera.height for v in scene.train)
    assert short.budget == densify_budget(scene, 300) == max(pixels // 128, 600)
    long = Trainer.start(scene, "2dgs", make_config("2dgs"), small_config(iterations=60000, densify=True), "cpu",
                         torch.device("cpu"))
    assert long.d_every == 200 and long.reset_every == 6000  # longer runs stretch the schedule as before
    net, opt = short.net, short.optimizer
    stats = DensifyStats(net.num_primitives)
    stats.grad_sum += 1.0
    stats.count += 1.0  # every surfel is a candidate
    densify_and_prune(net, opt, stats, grad_threshold=1e-9, scene_extent=scene.extent, min_opacity=0.0,
                      generator=torch.Generator().manual_seed(0), max_growth=0.5)
    assert net.num_primitives == 450  # 300 + at most half of it
    stats = DensifyStats(net.num_primitives)
    stats.grad_sum += 1.0
    stats.count += 1.0
    densify_and_prune(net, opt, stats, grad_threshold=1e-9, scene_extent=scene.extent, min_opacity=0.0,
                      generator=torch.Generator().manual_seed(0), max_primitives=500, max_growth=0.5)
    assert net.num_primitives == 500


def test_random_downscale_trains_some_views_smaller(tiny_data, monkeypatch):
    """--random-downscale: the chosen fraction of (step, view) pairs renders at 1/2 or 1/4 size against the image's
    area average, drawn the same way every time (so a resumed run repeats them) and not from the view order's
    generator."""
    from splatzoo.evaluate import area_resize
    from splatzoo.training import trainer as trainer_module
    from splatzoo.training.trainer import DOWNSCALES, Trainer
    from splatzoo.zoo import make_config

    scene = load_scene(tiny_data)  # 48 px views
    monkeypatch.setattr(trainer_module, "MIN_DOWNSCALED_SIDE", 12)
    cfg = small_config(iterations=20, densify=False, antialias=True, random_downscale=0.5, backend="cpu")
    t = Trainer.start(scene, "gabor", make_config("gabor"), cfg, "cpu", torch.device("cpu"))
    draws = [t._downscale(v, step) for step in range(1, 41) for v in scene.train]
    assert draws == [t._downscale(v, step) for step in range(1, 41) for v in scene.train]
    small = [s for s in draws if s < 1]
    assert 0.35 < len(small) / len(draws) < 0.65, len(small)
    assert set(small) == set(DOWNSCALES)
    state = t.gen.get_state()
    step, view = next((s, v) for s in range(1, 41) for v in scene.train if t._downscale(v, s) == 0.25)
    out = t._loss(view, step)
    render, target, cam = out.render, out.target, out.camera
    assert torch.equal(t.gen.get_state(), state) and out.scale == 0.25
    assert (cam.width, cam.height) == (12, 12) and render.rgb.shape[:2] == (12, 12)
    assert torch.allclose(target, area_resize(view.image_float(), 12, 12))
    assert torch.allclose(target.mean((0, 1)), view.image_float().mean((0, 1)), atol=1e-5)
    for _ in range(5):
        assert math.isfinite(t.step()["loss"])
    none = Trainer.start(scene, "gabor", make_config("gabor"), small_config(random_downscale=0.0), "cpu",
                         torch.device("cpu"))
    assert all(none._downscale(v, s) == 1.0 for s in range(1, 21) for v in scene.train)
    monkeypatch.setattr(trainer_module, "MIN_DOWNSCALED_SIDE", 20)  # 1/4 of 48 px is too small now
    assert {t._downscale(v, s) for s in range(1, 41) for v in scene.train} == {1.0, 0.5}
    monkeypatch.setattr(trainer_module, "MIN_DOWNSCALED_SIDE", 64)  # and every smaller scale
    assert {t._downscale(v, s) for s in range(1, 41) for v in scene.train} == {1.0}
    with pytest.raises(SplatzooError, match="random-downscale"):
        small_config(random_downscale=1.5).validate()


def test_wave_l1_per_count_keeps_the_pull_per_pixel():
    """The default scaling: WAVE_L1_COUNT / the surfel count. At WAVE_L1_COUNT surfels it is the plain penalty;
    twice as many surfels, each covering about half the pixels, get half the pull per wave; off, any count gets
    wave_l1 per wave."""
    from splatzoo import create_model
    from splatzoo.models.gabor import WAVE_L1, WAVE_L1_COUNT

    grads = {}
    for n in (WAVE_L1_COUNT, 2 * WAVE_L1_COUNT, 4):
        for per_count in (True, False):
            m = create_model("gabor", torch.rand(n, 3), torch.rand(n, 3), wave_l1_per_count=per_count)
            m.regulariser().backward()
            grads[n, per_count] = m.wave_weights.grad.abs()
    assert torch.allclose(grads[WAVE_L1_COUNT, True], torch.full_like(grads[WAVE_L1_COUNT, True], WAVE_L1))
    assert torch.allclose(grads[2 * WAVE_L1_COUNT, True], torch.full_like(grads[2 * WAVE_L1_COUNT, True], WAVE_L1 / 2))
    assert torch.allclose(grads[4, True], torch.full_like(grads[4, True], WAVE_L1 * WAVE_L1_COUNT / 4))
    for n in (WAVE_L1_COUNT, 2 * WAVE_L1_COUNT, 4):
        assert torch.allclose(grads[n, False], torch.full_like(grads[n, False], WAVE_L1))


def test_wave_l1_pulls_unneeded_waves_to_zero(tiny_data):
    """gabor:wave_l1: the model's penalty is wave_l1 x sum |w| (by default WAVE_L1; None when off, for the paper's
    colours and for models without waves), the trainer adds it, and a run with it ends with smaller wave weights
    than one without."""
    import math as _math

    from splatzoo import create_model
    from splatzoo.models.gabor import WAVE_L1
    from splatzoo.zoo import make_config

    pts, cols = torch.rand(50, 3), torch.rand(50, 3)
    uniform = create_model("gabor", pts, cols, wave_l1_per_count=False)
    assert torch.allclose(uniform.regulariser(), WAVE_L1 * uniform.wave_weights.abs().sum())
    assert create_model("gabor", pts, cols, wave_l1=0).regulariser() is None
    assert create_model("gabor", pts, cols, color_param="paper").regulariser() is None
    with pytest.raises(SplatzooError, match="residual only"):
        make_config("gabor", color_param="paper", wave_l1=1e-3)
    # a model's own default penalty (beta-gabor's is twice gabor's) is simply unused in the paper's colours
    assert make_config("beta-gabor", color_param="paper", fit_waves=0).wave_l1 == 2 * WAVE_L1
    with pytest.raises(SplatzooError, match="residual only"):
        make_config("beta-gabor", color_param="paper", fit_waves=0, wave_l1=WAVE_L1)
    assert create_model("2dgs", pts, cols).regulariser() is None
    net = create_model("gabor", pts, cols, wave_l1=1e-3, wave_l1_per_count=False)
    penalty = net.regulariser()
    assert torch.allclose(penalty, 1e-3 * net.wave_weights.abs().sum())
    penalty.backward()
    assert torch.allclose(net.wave_weights.grad, 1e-3 * torch.sign(net.wave_weights.detach()))
    for bad in (-1.0, _math.nan, _math.inf):
        with pytest.raises(SplatzooError, match="wave_l1"):
            make_config("gabor", wave_l1=bad)
    scene = load_scene(tiny_data)
    weights = {}
    for l1 in (0.0, 1e-2):
        result = train(scene, "gabor", {"wave_l1": l1}, small_config(iterations=60, densify=False, backend="cpu"),
                       tiny_data.parent / f"l1-{l1}", progress=False, evaluate_at_end=False)
        weights[l1] = result.model.wave_weights.detach().abs().mean().item()
    assert weights[1e-2] < 0.5 * weights[0.0], weights


@pytest.mark.parametrize("model", ["2dgs", "gabor"])
def test_a_training_step_waits_for_the_device_four_times(model, tmp_path):
    """A step between densifications on the cuda-emulated backend (the GPU code path) reads the device at four
    points: the binning's visible set and pair count (to size its buffers), the step's numbers (loss, error: one
    read), and the finiteness check of the surfels. Each read stalls a GPU's queue; a new one fails this test."""
    from splatzoo.data.synthetic import make_synthetic_scene
    from splatzoo.testing import HostSyncs
    from splatzoo.training.trainer import Trainer
    from splatzoo.zoo import make_config

    scene = load_scene(make_synthetic_scene("sweater", tmp_path / "data", views=6, width=32, height=32))
    cfg = TrainConfig(iterations=300, backend="cuda-emulated", num_primitives=200)
    trainer = Trainer.start(scene, model, make_config(model), cfg, "cuda-emulated", torch.device("cpu"))
    trainer.step()  # first-step set-up (view order, probe views) is not per step
    counts = []
    for _ in range(3):
        with HostSyncs() as syncs:
            trainer.step()
        counts.append(syncs.total)
        sites = "; ".join(f"{f}:{line} {kind} x{n}" for (f, line, kind), n in sorted(syncs.sites.items()))
        assert syncs.total <= 4, f"{syncs.total} host syncs in one step: {sites}"
    assert counts == [4, 4, 4], counts


def test_counts_and_seeds_beyond_the_machine_are_refused_with_the_real_cause(tmp_path, monkeypatch):
    """A primitive count the memory cannot hold is refused with the estimate before anything is allocated (it
    used to allocate until the kernel killed it, or be blamed on a checkpoint the fresh run does not have); a seed
    beyond 64 bits is named; the largest seed trains, random draws per view included."""
    from splatzoo.data.synthetic import make_synthetic_scene
    from splatzoo.training import trainer as trainer_module

    data = make_synthetic_scene("plain", tmp_path / "data", views=4, width=24, height=24)
    monkeypatch.setattr(trainer_module, "available_memory", lambda: 2**30)  # a 1 GiB machine
    for option, value in (("num_primitives", 10_000_000), ("max_primitives", 10_000_000)):
        cfg = TrainConfig(iterations=2, backend="cpu", **{option: value})
        with pytest.raises(SplatzooError, match=rf"GiB .* 1.0 GiB are available; pass a smaller --{option.replace('_', '-')}") as e:
            train(data, "gabor", {}, cfg, tmp_path / option, progress=False, evaluate_at_end=False)
        assert "checkpoint" not in str(e.value) and "10,000,000 primitives" in str(e.value)
    with pytest.raises(SplatzooError, match=r"--seed must be between 0 and 9223372036854775807"):
        TrainConfig(seed=2**64).validate()
    cfg = TrainConfig(iterations=2, backend="cpu", num_primitives=50, seed=2**63 - 1, random_downscale=1.0)
    train(data, "2dgs", {}, cfg, tmp_path / "big_seed", progress=False, evaluate_at_end=False)
    assert (tmp_path / "big_seed" / "model.pt").is_file()
