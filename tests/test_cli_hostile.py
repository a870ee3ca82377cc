"""Hostile input on the command line: every refusal is a named error that says what to do (no traceback), it comes
before any work, and it leaves every existing file byte-identical; nothing typed is silently dropped."""
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

import splatzoo.cli as cli
from splatzoo.cli import app
from splatzoo.errors import SplatzooError

runner = CliRunner()


def refused(args) -> str:
    """Run a command that must be refused: a non-zero exit, a SplatzooError (one line through `main`) or a usage
    error, no traceback. Returns the message."""
    r = runner.invoke(app, [str(a) for a in args])
    assert r.exit_code != 0, r.output
    exc = r.exception
    if exc is None or isinstance(exc, SystemExit):  # a usage error: click printed it
        message = r.output
    else:
        assert isinstance(exc, SplatzooError), f"{type(exc).__name__}: {exc}"
        message = str(exc)
    assert "Traceback" not in r.output + message
    return message


def snapshot(*folders) -> dict:
    """Every file under the folders with its bytes (FIFOs and other special files by their kind)."""
    out = {}
    for folder in folders:
        for p in sorted(Path(folder).rglob("*")):
            out[p] = p.read_bytes() if p.is_file() else ("dir" if p.is_dir() else "special")
    return out


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    """(data, finished 2dgs run, interrupted gabor run with n_waves=2) on a small synthetic scene."""
    from splatzoo.data.synthetic import make_synthetic_scene
    from splatzoo.runs import train
    from splatzoo.training.trainer import TrainConfig

    root = tmp_path_factory.mktemp("hostile")
    data = make_synthetic_scene("plain", root / "data", views=6, width=24, height=24)
    cfg = TrainConfig(iterations=2, backend="cpu", num_primitives=50, densify=False)
    train(data, "2dgs", {}, cfg, root / "run", progress=False, evaluate_at_end=False)
    train(data, "gabor", {"n_waves": 2}, cfg, root / "cut", progress=False, evaluate_at_end=False)
    for name in ("model.pt", "model.szp"):  # as if stopped before the end: checkpoint and record only
        (root / "cut" / name).unlink(missing_ok=True)
    return data, root / "run", root / "cut"


@pytest.fixture
def no_benchmark(monkeypatch):
    """bench's modules as they are, but running one fails the test: a refusal must come before the work."""
    real = cli._bench_module

    def guarded(name):
        module = real(name)

        def ran(*a, **k):
            raise AssertionError(f"{name} ran although the request should have been refused")

        module.run_benchmark = module.run = ran
        return module

    monkeypatch.setattr(cli, "_bench_module", guarded)


# --- splatzoo bench -----------------------------------------------------------------------------------------------

@pytest.mark.parametrize("args, said", [
    (["--waves", "x"], ["'x'", "not a wave count", "0,4,4a"]),
    (["--waves", "-1"], ["'-1'", "not a wave count"]),
    (["--waves", "1000000000"], ["at most 64"]),
    (["--waves", "65"], ["65 waves", "at most 64"]),
    (["--waves", "0t0"], ["texels a side", "1 to 64"]),
    (["--waves", "0t99999999999"], ["texels a side", "1 to 64"]),
    (["--waves", "0,0"], ["0 twice"]),
    (["--waves", "0,,4"], ["empty entry"]),
    (["--repeats", "0"], ["--repeats 0", "1 to 1000"]),
    (["--repeats", "-3"], ["1 to 1000"]),
    (["--repeats", "100000"], ["1 to 1000"]),
    (["--backends", "bogus"], ["unknown backend 'bogus'", "cuda, cpu, reference"]),
    (["--backends", "cpu,cpu"], ["cpu twice"]),
    (["--backends", ","], ["empty entry"]),
    (["--gpu", "--backends", "reference"], ["none of the chosen scenes runs on the reference backend"]),
    (["--quick", "--gpu"], ["pass one of them"]),
    (["--json", "/proc/x.json"], ["/proc", "cannot be written"]),
    (["--size", "64x64"], ["--size", "--training"]),
    (["--backend", "cpu"], ["--backend", "--backends"]),
    (["--iterations", "5", "--models", "2dgs"], ["--iterations and --models", "--training"]),
    (["--training", "--size", "100000x100000"], ["8 to 16384"]),
    (["--training", "--size", "16000x16000", "--views", "100000"], ["GiB of memory"]),
    (["--training", "--size", "0x0"], ["8 to 16384"]),
    (["--training", "--size", "big"], ["WIDTHxHEIGHT"]),
    (["--training", "--views", "1"], ["--views 1", "2 to"]),
    (["--training", "--iterations", "0"], ["--iterations 0"]),
    (["--training", "--models", "2dgs,bogus"], ["unknown model 'bogus'", "gabor"]),
    (["--training", "--models", "2dgs,2dgs"], ["2dgs twice"]),
    (["--training", "--models", "gabor:n_waves=8"], ["model names only"]),
    (["--training", "--backend", "bogus"], ["auto, cpu, cuda or reference"]),
    (["--training", "--gsplat-examples", "."], ["simple_trainer_2dgs.py not found"]),
    (["--training", "--data", "no/such/data"], ["does not exist", "dataset folder"]),
    (["--training", "--repeats", "2"], ["--repeats does not apply to --training"]),
    (["--training", "--json", "/proc/x.json"], ["/proc", "cannot be written"]),
    (["--training", "--fps", "somewhere"], ["pass one of them"]),
])
def test_bench_refuses_before_running(args, said, no_benchmark):
    message = refused(["bench", *args])
    for text in said:
        assert text in message, message


def test_bench_refuses_unusable_paths_by_what_they_are(no_benchmark, runs, tmp_path):
    data, run, _ = runs
    fifo = tmp_path / "fifo"
    os.mkfifo(fifo)
    (tmp_path / "folder").mkdir()
    (tmp_path / "plain").write_text("x")
    before = snapshot(tmp_path)
    assert "is a FIFO" in refused(["bench", "--json", fifo])
    assert "is a folder" in refused(["bench", "--json", tmp_path / "folder"])
    assert "is a file, not a folder" in refused(["bench", "--json", tmp_path / "plain" / "x.json"])
    assert "is a FIFO" in refused(["bench", "--training", "--data", fifo])
    assert "shape the synthetic scene" in refused(["bench", "--training", "--data", data, "--size", "64x64"])
    assert "does not exist" in refused(["bench", "--fps", tmp_path / "nothere"])
    assert "is a FIFO" in refused(["bench", "--fps", fifo])
    assert "not a splatzoo run" in refused(["bench", "--fps", data])
    assert "writes no file" in refused(["bench", "--fps", run, "--json", tmp_path / "r.json"])
    assert snapshot(tmp_path) == before


def test_bench_refusal_leaves_an_existing_report_alone(no_benchmark, tmp_path):
    report = tmp_path / "r.json"
    report.write_text('{"kept": true}')
    before = snapshot(tmp_path)
    refused(["bench", "--waves", "x", "--json", report])
    refused(["bench", "--backends", "bogus", "--json", report])
    assert snapshot(tmp_path) == before


def test_bench_writes_its_report_atomically(monkeypatch, tmp_path):
    """A real (tiny) rasterizer benchmark replaces the report whole; nothing temporary is left beside it."""
    real = cli._bench_module

    def tiny(name):
        module = real(name)
        module.CONFIGS = (("24x24/100", "sphere", 24, 24, 100, ("cpu", "reference")),)
        return module

    monkeypatch.setattr(cli, "_bench_module", tiny)
    report = tmp_path / "out" / "r.json"
    report.parent.mkdir()
    report.write_text("old")
    r = runner.invoke(app, ["bench", "--backends", "reference", "--waves", "0,2a", "--repeats", "1", "--json",
                            str(report)])
    assert r.exit_code == 0, r.output
    rows = json.loads(report.read_text())["results"]
    assert [(row["backend"], row["K"]) for row in rows] == [("reference", "0"), ("reference", "2a")]
    assert sorted(p.name for p in report.parent.iterdir()) == ["r.json"]


def test_bench_errors_reach_the_console_as_one_line():
    """Through the real entry point: exit 2, `error: ...`, no traceback."""
    out = subprocess.run([sys.executable, "-m", "splatzoo.cli", "bench", "--backends", "bogus"], capture_output=True,
                         text=True, timeout=300)
    assert out.returncode == 2 and "Traceback" not in out.stderr, out.stderr[-2000:]
    assert out.stderr.strip().splitlines()[-1].startswith("error: unknown backend 'bogus'")


# --- train: model options where DATA is, and on --resume ---------------------------------------------------------

def test_model_options_cannot_change_on_resume(runs):
    data, run, cut = runs
    message = refused(["train", "--resume", "--out", cut, "--n-waves", "8"])
    assert "--resume continues" in message and "n_waves: run has 2, asked 8" in message
    # the run's model has no such option: said of the option, not of its value
    assert "unknown option '--n-waves' for model '2dgs'" in refused(["train", "--resume", "--out", run, "--n-waves",
                                                                      "8"])


def test_options_before_data_reach_the_model(runs, tmp_path):
    """`train --model gabor --n-waves 2 DATA` is the same run as `train DATA --model gabor --n-waves 2`."""
    data, _, _ = runs
    r = runner.invoke(app, ["train", "--model", "gabor", "--n-waves", "2", str(data), "--out", str(tmp_path / "r"),
                            "--iterations", "1", "--num-primitives", "30", "--no-densify", "--backend", "cpu"])
    assert r.exit_code == 0, r.output
    assert json.loads((tmp_path / "r" / "config.json").read_text())["model_config"]["n_waves"] == 2
    message = refused(["train", "--model", "gabor", "--n-waves", "2", data, "stray", "--out", tmp_path / "s"])
    assert "unexpected argument" in message and "'stray'" in message
    assert not (tmp_path / "s").exists()


@pytest.mark.parametrize("model_args, said", [
    (["--model", "gabor", "--n-waves", "2", "--n-waves", "4"], "given twice"),
    (["--model", "gabor", "--n-waves=2", "--n-waves", "4"], "given twice"),
    (["--model", "gabor:n_waves=2", "--n-waves", "4"], "given twice"),
    (["--model", "gabor:n_waves=2,n-waves=4"], "given twice"),
    (["--model", "neural-gabor:hidden=1,hidden=2"], "hidden is given twice"),
    (["--model", "neural-gabor", "--view-dependent", "--no-view-dependent"], "given twice"),
    (["--model", "gabor:=3"], "no name"),
])
def test_train_refuses_an_option_given_twice(model_args, said, runs, tmp_path):
    data, _, _ = runs
    message = refused(["train", data, "--out", tmp_path / "run", *model_args])
    assert said in message, message
    assert not (tmp_path / "run").exists()


def test_option_strings_refuse_repeats_everywhere():
    """Model specs, export format specs and mesh texture options: a key given twice is refused by name."""
    from splatzoo.compare import parse_model_list
    from splatzoo.export import parse_format
    from splatzoo.mesh_texture import make_options
    from splatzoo.options import model_spec, parse_model_args

    assert model_spec("gabor:n_waves=2,prune-waves=0.1") == ("gabor", {"n_waves": "2", "prune_waves": "0.1"})
    for call in (lambda: model_spec("neural-gabor:hidden=1,hidden=2"),
                 lambda: parse_model_list("gabor:n_waves=2,n_waves=3,2dgs"),
                 lambda: parse_format("ply:viewer=exact,viewer=3dgs"),
                 lambda: parse_model_args("gabor", ["--n-waves", "2", "--n-waves=3"]),
                 lambda: make_options({"texture_size": "64"}, texture_size=128)):
        with pytest.raises(SplatzooError, match="twice"):
            call()
    with pytest.raises(SplatzooError, match="unexpected argument 'x'"):
        parse_model_args("gabor", ["x"])
    words = []
    assert parse_model_args("gabor", ["--n-waves", "2", "DATA"], positionals=words) == {"n_waves": "2"}
    assert words == ["DATA"]


def test_export_refuses_a_repeated_format_option(runs, tmp_path):
    _, run, _ = runs
    out = tmp_path / "model.ply"
    out.write_bytes(b"existing")
    message = refused(["export", run, "--out", out, "--format", "ply:viewer=exact,viewer=3dgs"])
    assert "viewer is given twice" in message
    assert out.read_bytes() == b"existing"


# --- eval and render: a RUN that is no run --------------------------------------------------------------------

@pytest.mark.parametrize("command", ["eval", "render"])
def test_eval_and_render_name_what_the_path_is(command, runs, tmp_path):
    data, run, _ = runs
    fifo = tmp_path / "fifo"
    os.mkfifo(fifo)
    (tmp_path / "folder").mkdir()
    before = snapshot(tmp_path, data)
    for with_data in ([], ["--data", data]):
        missing = refused([command, tmp_path / "modle.ply", *with_data])
        assert "does not exist" in missing and "--data is for a model file" not in missing
        assert "is a FIFO (named pipe)" in refused([command, fifo, *with_data])
        assert "is a character device" in refused([command, "/dev/zero", *with_data])
    folder = refused([command, tmp_path / "folder", "--data", data])
    assert "holds no splatzoo run" in folder and "model file" in folder
    assert "holds no splatzoo run" in refused([command, data, "--data", data])
    assert "scored on its own dataset" in refused([command, run, "--data", data])
    (tmp_path / "model.ply").write_bytes(b"")
    assert "Did you mean 'model.ply'" in refused([command, tmp_path / "modle.ply", "--data", data])
    (tmp_path / "model.ply").unlink()
    assert snapshot(tmp_path, data) == before


# --- sweep: options that a grid would drop ----------------------------------------------------------------------

@pytest.mark.parametrize("args, said", [
    (["--model", "textured", "--texture-size", "0", "--n-waves", "0"], "has no n_waves option"),
    (["--model", "2dgs", "--n-waves", "0,2"], "has no n_waves option"),
    (["--model", "gabor", "--prune-waves", "0.01", "--n-waves", "0"], "trains only the 2dgs model"),
    (["--model", "gabor:n_waves=4"], "the sweep sets n_waves from --n-waves"),
    (["--model", "gabor", "--n-waves", "0,31"], "at most 30"),
    (["--model", "gabor", "--prune-waves", "-1", "--n-waves", "0,2"], "prune_waves"),
    (["--model", "gabor:prune_waves=0.1", "--prune-waves", "0.2"], "given twice"),
])
def test_sweep_refuses_what_its_grid_would_drop(args, said, runs, tmp_path):
    data, _, _ = runs
    message = refused(["sweep", data, "--out", tmp_path / "sweep", "--num-primitives", "30", "--iterations", "1",
                       *args])
    assert said in message, message
    assert not (tmp_path / "sweep").exists()


def test_sweep_says_the_zero_column_runs_without_the_options():
    from splatzoo.sweep import check_sweep_model

    check_sweep_model("gabor", [0, 2], {"prune_waves": "0.01"})  # allowed: the note is printed by sweep()
    with pytest.raises(SplatzooError, match="wave models: .*gabor"):
        check_sweep_model("neural-gabor", [0, 2])


# --- export --format mesh-obj: the .mtl and .png beside --out ------------------------------------------------------

def _tiny_textured_mesh():
    from splatzoo.mesh_texture import TexturedMesh

    return TexturedMesh(np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], np.float32), np.array([[0, 1, 2]]),
                        uvs=np.array([[0, 0], [1, 0], [0, 1]], np.float32), texture=np.zeros((4, 4, 3), np.uint8))


def test_obj_export_never_overwrites_a_foreign_mtl_or_png(runs, tmp_path):
    from splatzoo.mesh_texture import write_obj

    _, run, _ = runs
    for foreign in ("mesh.png", "mesh.mtl"):
        folder = tmp_path / foreign.replace(".", "_")
        folder.mkdir()
        (folder / foreign).write_bytes(b"someone else's")
        before = snapshot(folder)
        message = refused(["export", run, "--out", folder / "mesh.obj", "--format", "mesh-obj"])
        assert foreign in message and "already exist" in message and "another --out" in message
        with pytest.raises(SplatzooError, match="already exist"):
            write_obj(_tiny_textured_mesh(), folder / "mesh.obj")
        assert snapshot(folder) == before
    # an OBJ written here before owns its .mtl and .png: writing it again replaces all three
    path = write_obj(_tiny_textured_mesh(), tmp_path / "again" / "mesh.obj")
    write_obj(_tiny_textured_mesh(), path)
    assert sorted(p.name for p in path.parent.iterdir()) == ["mesh.mtl", "mesh.obj", "mesh.png"]
    (path.parent / "mesh.mtl").write_text("# a material of mine\n")  # no longer the OBJ's own
    with pytest.raises(SplatzooError, match="mesh.mtl"):
        write_obj(_tiny_textured_mesh(), path)
