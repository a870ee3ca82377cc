"""The command line: every command has --help; errors are one clear line, not a traceback."""
import subprocess
import sys

import pytest
import typer
from typer.testing import CliRunner

from splatzoo.cli import app

runner = CliRunner()
COMMANDS = sorted(c.name or c.callback.__name__ for c in app.registered_commands)


def test_commands_exist():
    assert "models" in COMMANDS


@pytest.mark.parametrize("command", COMMANDS)
def test_every_command_has_help(command):
    result = runner.invoke(app, [command, "--help"])
    assert result.exit_code == 0, result.output
    assert "Usage" in result.output and len(result.output) > 100


def test_models_lists_builtins():
    result = runner.invoke(app, ["models"])
    assert result.exit_code == 0
    for name in ("2dgs", "gabor", "gabor-adaptive", "baseline-a", "baseline-b", "baseline-c"):
        assert name in result.output
    assert "built-in" in result.output


def test_console_script_reports_errors_without_traceback(tmp_path):
    out = subprocess.run([sys.executable, "-m", "splatzoo.cli", "nonexistent-command"], capture_output=True, text=True)
    assert out.returncode != 0 and "Traceback" not in out.stderr


def test_version():
    import splatzoo

    result = runner.invoke(app, ["--version"])
    assert result.exit_code == 0 and result.output.strip() == f"splatzoo {splatzoo.__version__}"


def test_metrics_table_is_readable():
    from splatzoo.evaluate import metrics_table

    text = metrics_table({"psnr": 24.7, "ssim": 0.8667, "lpips": 0.1195, "fps": 120.3, "train_seconds": 55.2,
                          "num_primitives": 2000, "size_bytes": 224000, "iterations": 1500, "model": "gabor",
                          "backend": "cpu", "split": "test", "views": 3, "resolution": [128, 128]})
    lines = text.splitlines()
    assert lines[0].split() == ["model", "gabor", "(2000", "primitives,", "0.22", "MB)"]
    assert "PSNR      24.70 dB" in text and "SSIM      0.8667" in text and "120.3 FPS (cpu backend)" in text
    assert "{" not in text  # a table, not JSON
    empty = metrics_table({})  # missing fields do not break it, and a model file's table has no training line
    assert [line.split()[:2] for line in empty.splitlines()][2] == ["PSNR", "-"] and "training" not in empty


@pytest.mark.parametrize("command", ["train", "synth", "compare"])
def test_help_shows_flags_as_flags_and_arguments_by_name(command):
    out = runner.invoke(app, [command, "--help"]).output
    assert "<bool>" not in out, out
    usage = out.splitlines()[0]
    assert usage == usage.replace("{data}", "").replace("{models}", ""), usage  # upper-case metavars: DATA, MODEL


def test_readme_python_snippet_runs_as_written(tmp_path, monkeypatch):
    import re
    from pathlib import Path

    readme = (Path(__file__).parents[1] / "README.md").read_text()
    blocks = re.findall(r"```python\n(.*?)```", readme, re.S)
    assert blocks, "README.md has no python snippet"
    monkeypatch.chdir(tmp_path)  # the snippet writes model.pt
    scopes = []
    for code in blocks:  # every snippet runs: the quick tour and the plugin example
        scopes.append({})
        exec(compile(code, "README.md", "exec"), scopes[-1])
    scope = next(s for s in scopes if "out" in s)
    out = scope["out"]
    assert out.alpha.max() > 0.5 and out.rgb.max() > 0  # it rendered something: the sphere covers the view centre
    assert (tmp_path / "model.pt").is_file()
    assert "model.render(" in readme and scope["picture"].shape == (128, 128, 3)  # the one render call
    spec = next(s["SPEC"] for s in scopes if "SPEC" in s)  # the plugin example declares a working model
    plugin = spec.cls(spec.config_cls(), 0)
    assert plugin.config.texture_size == 8 and spec.name == "stripes-textured"


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory):
    """A finished 5-iteration run on a small synthetic scene: (data folder, run folder)."""
    from splatzoo.data.synthetic import make_synthetic_scene
    from splatzoo.runs import train
    from splatzoo.training.trainer import TrainConfig

    root = tmp_path_factory.mktemp("tiny")
    data = make_synthetic_scene("plain", root / "data", views=6, width=32, height=32)
    train(data, "2dgs", {}, TrainConfig(iterations=5, backend="cpu", num_primitives=100, densify=False), root / "run",
          progress=False, evaluate_at_end=False)
    return data, root / "run"


@pytest.mark.skipif(__import__("torch").cuda.is_available(), reason="the cuda backend runs here")
@pytest.mark.parametrize("command", ["train", "eval", "render", "extract-mesh", "view", "compare"])
def test_an_unavailable_backend_is_named_before_anything_runs(command, tiny_run, tmp_path):
    """--backend cuda where torch has no CUDA (or no GPU is visible): one line saying why, exit 2, no traceback."""
    data, run = tiny_run
    args = {"train": ["train", str(data), "--out", str(tmp_path / "run")],
            "compare": ["compare", "gabor", "--quick", "--data", str(data), "--out", str(tmp_path / "cmp")]}.get(
        command, [command, str(run)])
    out = subprocess.run([sys.executable, "-m", "splatzoo.cli", *args, "--backend", "cuda"], capture_output=True,
                         text=True, timeout=300)
    assert out.returncode == 2 and "Traceback" not in out.stderr, out.stderr[-2000:]
    last = out.stderr.strip().splitlines()[-1]
    assert last.startswith("error:") and "CUDA" in last and "cuda rasterizer" in last


def test_a_run_folder_opens_in_a_fresh_interpreter(tiny_run):
    """splatzoo.load_model reads a run folder without its caller importing splatzoo.runs first (the model-file layer
    loads the run-folder format by name)."""
    from splatzoo.runs import Run

    _, run = tiny_run
    code = f"import splatzoo; print(splatzoo.load_model({str(run)!r}).num_primitives)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr[-2000:]
    assert int(out.stdout.split()[-1]) == Run(run).load()[0].num_primitives > 0


def test_sfm_options_reach_the_mapper(tmp_path):
    """--focal is passed on (a bad one is refused before anything is written)."""
    images = tmp_path / "photos"
    images.mkdir()
    import numpy as np
    import cv2

    for i in range(3):
        cv2.imwrite(str(images / f"p{i}.png"), np.full((32, 32, 3), 40 * i, np.uint8))
    result = runner.invoke(app, ["sfm", str(images), "--out", str(tmp_path / "out"), "--focal", "-5", "--no-retry"])
    assert result.exit_code != 0 and "focal" in str(result.exception or result.output)
    assert not (tmp_path / "out").exists()


def test_one_model_syntax_for_every_command(tmp_path):
    """`--model gabor:n_waves=2` (compare's syntax) and `--model gabor --n-waves 2` make the same run."""
    import json

    from splatzoo.data.synthetic import make_synthetic_scene

    data = make_synthetic_scene("plain", tmp_path / "data", views=4, width=24, height=24)
    common = [str(data), "--iterations", "2", "--num-primitives", "50", "--no-densify", "--backend", "cpu"]
    for name, model in (("inline", ["--model", "gabor:n_waves=2,prune-waves=0.01"]),
                        ("flags", ["--model", "gabor", "--n-waves", "2", "--prune-waves", "0.01"])):
        result = runner.invoke(app, ["train", *common, "--out", str(tmp_path / name), *model])
        assert result.exit_code == 0, result.output
    inline, flags = (json.loads((tmp_path / n / "config.json").read_text()) for n in ("inline", "flags"))
    assert inline["model"] == flags["model"] == "gabor"
    assert inline["model_config"] == flags["model_config"] and inline["model_config"]["n_waves"] == 2
    result = runner.invoke(app, ["train", *common, "--out", str(tmp_path / "bad"), "--model", "gabor:n_waves"])
    assert result.exit_code != 0 and "key=value" in str(result.exception or result.output)


def test_model_lists_split_between_models_not_between_options():
    """The benchmarks' --models lists: an item with '=' and no ':' belongs to the model before it."""
    from splatzoo.compare import parse_model_list
    from splatzoo.errors import SplatzooError

    got = parse_model_list("gabor:n_waves=8,wave_l1=0,2dgs, gabor:prune_relative=2")
    assert [(c.label, c.model, c.options) for c in got] == [
        ("gabor:n_waves=8,wave_l1=0", "gabor", {"n_waves": "8", "wave_l1": "0"}), ("2dgs", "2dgs", {}),
        ("gabor:prune_relative=2", "gabor", {"prune_relative": "2"})]
    with pytest.raises(SplatzooError, match="name the model first"):
        parse_model_list("n_waves=8,gabor")


def test_a_signal_during_the_final_evaluation_exits_with_its_own_code(monkeypatch, capsys):
    """SIGTERM that lands after training, while the run evaluates, exits 143 (not Ctrl-C's 130)."""
    import signal

    import splatzoo.cli as cli
    from splatzoo.runs import TrainingInterrupted

    def app():
        try:
            cli._on_signal(signal.SIGTERM, None)
        except KeyboardInterrupt:
            raise TrainingInterrupted("training finished but its evaluation was interrupted", 130) from None

    monkeypatch.setattr(cli, "app", app)
    monkeypatch.setattr(signal, "signal", lambda *a: None)  # leave this process's handlers alone
    monkeypatch.setattr(cli, "_received_signal", [])
    with pytest.raises(SystemExit) as e:
        cli.main()
    assert e.value.code == 143
    assert "evaluation was interrupted" in capsys.readouterr().err


def test_bench_fps_measures_a_trained_run(tiny_run):
    """`splatzoo bench --fps RUN`: frame rates at the run's size and at 1080 lines, image-only and full."""
    _, run = tiny_run
    r = runner.invoke(app, ["bench", "--fps", str(run), "--backend", "cpu"])
    assert r.exit_code == 0, r.output
    lines = [line for line in r.output.splitlines() if "FPS image-only" in line]
    assert len(lines) == 2 and "32x32" in lines[0] and "1080x1080" in lines[1], r.output
    assert all(float(line.split(":")[1].split()[0]) > 0 for line in lines)


def test_bad_render_and_eval_arguments_are_named(tiny_run, tmp_path):
    """`render --frames 0` is a usage error, not an IndexError; a model file given for a run folder says so."""
    _, run = tiny_run
    r = runner.invoke(app, ["render", str(run), "--video", "--frames", "0"])
    assert r.exit_code == 2 and "--frames" in r.output, r.output
    model = tmp_path / "model.ply"
    model.write_bytes(b"ply\n")
    out = subprocess.run([sys.executable, "-m", "splatzoo.cli", "eval", str(model)], capture_output=True, text=True,
                         timeout=120)
    assert out.returncode == 2 and "is a model file, not a run folder" in out.stderr and "load_ply" in out.stderr


def test_compare_passes_skip_missing_to_the_scene(monkeypatch, tmp_path):
    """`compare --skip-missing` loads a transforms.json dataset whose export dropped some photos, as train does."""
    import splatzoo.compare

    seen = {}

    def fake_compare(models, data, out, **kw):
        seen.update(kw["scene_options"])
        out.mkdir(parents=True, exist_ok=True)
        (out / "report.md").write_text("report")

    monkeypatch.setattr(splatzoo.compare, "compare", fake_compare)
    r = runner.invoke(app, ["compare", "2dgs", "--data", str(tmp_path), "--out", str(tmp_path / "cmp"), "-r", "4",
                            "--skip-missing"])
    assert r.exit_code == 0, r.output
    assert seen == {"resolution": 4, "skip_missing": True}
