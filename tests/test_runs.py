"""Run folders you can trust: safe loading on every command path, no stale or mixed results, one writer at a time,
interrupts (SIGINT, SIGTERM, SIGKILL) that lose nothing, damaged files named clearly."""
import errno
import json
import re
import os
import random
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch
from typer.testing import CliRunner

from splatzoo.cli import app
from splatzoo.errors import SplatzooError
from splatzoo.runs import Run, RunLockedError, train
from splatzoo.training import TrainConfig

runner = CliRunner()
MARKER = "splatzoo_payload_ran"


class _Payload:
    """A pickle that creates a file when unpickled without weights_only."""

    def __init__(self, marker):
        self.marker = str(marker)

    def __reduce__(self):
        return (Path.touch, (Path(self.marker),))


@pytest.fixture(scope="module")
def tiny_data(tmp_path_factory):
    from splatzoo.data.synthetic import make_synthetic_scene

    return make_synthetic_scene("sweater", tmp_path_factory.mktemp("data") / "sweater", views=10, width=40, height=40)


def cfg(**kw):
    base = dict(iterations=12, backend="cpu", num_primitives=150, log_every=2, eval_every=6, seed=5)
    base.update(kw)
    return TrainConfig(**base)


def quick_train(data, out, model="2dgs", **kw):
    kw.setdefault("evaluate_at_end", False)
    return train(data, model, {}, kw.pop("config", cfg()), out, progress=False, **kw)


def assert_same_parameters(a, b):
    sa, sb = a.state_dict(), b.state_dict()
    assert sa.keys() == sb.keys()
    for k in sa:
        assert torch.equal(sa[k], sb[k]), k


# --- crafted files never run code ------------------------------------------------------------------------------

def test_crafted_files_run_no_code_on_any_command(tiny_data, tmp_path):
    marker = tmp_path / MARKER
    payload = {"model": _Payload(marker), "optimizer": {}, "densify": {}, "generator": torch.zeros(1),
               "iteration": 3, "train_seconds": 0.0, "view_order": []}
    # train --resume on a crafted checkpoint
    run = tmp_path / "resume"
    quick_train(tiny_data, run, stop_after=2)
    torch.save(payload, run / "checkpoint.pt")
    r = runner.invoke(app, ["train", "--resume", "--out", str(run)])
    assert r.exit_code != 0 and isinstance(r.exception, SplatzooError) and "checkpoint" in str(r.exception)
    # compare resumes on its own: the crafted checkpoint of a matching run must be refused too
    out = tmp_path / "cmp"
    r = runner.invoke(app, ["compare", "2dgs", "--data", str(tiny_data), "--out", str(out), "--iterations", "4",
                            "--num-primitives", "50", "--backend", "cpu"])
    assert r.exit_code == 0, r.output
    os.remove(out / "runs" / "2dgs" / "model.pt")
    torch.save(payload, out / "runs" / "2dgs" / "checkpoint.pt")
    r = runner.invoke(app, ["compare", "2dgs", "--data", str(tiny_data), "--out", str(out), "--iterations", "4",
                            "--num-primitives", "50", "--backend", "cpu"])
    assert r.exit_code != 0 and isinstance(r.exception, SplatzooError)
    # a crafted model.pt under eval, render, extract-mesh and export
    done = tmp_path / "done"
    quick_train(tiny_data, done)
    torch.save({"model": "2dgs", "config": {}, "state": _Payload(marker)}, done / "model.pt")
    for args in (["eval", str(done)], ["render", str(done)], ["extract-mesh", str(done)],
                 ["export", str(done), "--out", str(tmp_path / "x.ply")]):
        r = runner.invoke(app, args)
        assert r.exit_code != 0 and isinstance(r.exception, SplatzooError), (args, r.output)
        assert "model" in str(r.exception)
    assert not marker.exists()


# --- what made a run: reuse and resume only when it matches --------------------------------------------------------

def test_compare_never_reports_old_numbers(tiny_data, tmp_path):
    out = tmp_path / "cmp"
    base = ["compare", "2dgs", "--data", str(tiny_data), "--out", str(out), "--num-primitives", "50", "--backend", "cpu"]
    assert runner.invoke(app, base + ["--iterations", "4"]).exit_code == 0
    first = json.loads((out / "compare.json").read_text())["runs"]["2dgs"]
    # the same settings again: the finished run is reused, its numbers unchanged
    assert runner.invoke(app, base + ["--iterations", "4"]).exit_code == 0
    assert json.loads((out / "compare.json").read_text())["runs"]["2dgs"] == first
    # other settings: a clear error, nothing trained, compare.json untouched
    r = runner.invoke(app, base + ["--iterations", "6"])
    assert r.exit_code != 0 and "iterations" in str(r.exception) and "--overwrite" in str(r.exception)
    assert json.loads((out / "compare.json").read_text())["runs"]["2dgs"] == first
    # ... and with --overwrite the run is trained again with the new settings
    r = runner.invoke(app, base + ["--iterations", "6", "--overwrite"])
    assert r.exit_code == 0, r.output
    report = json.loads((out / "compare.json").read_text())
    assert report["settings"]["iterations"] == 6 and report["runs"]["2dgs"]["iterations"] == 6
    # other data with the same name of run folder: the fingerprint tells them apart
    from splatzoo.data.synthetic import make_synthetic_scene

    other = make_synthetic_scene("vest", tmp_path / "vest", views=10, width=40, height=40)
    r = runner.invoke(app, ["compare", "2dgs", "--data", str(other), "--out", str(out), "--num-primitives", "50",
                            "--backend", "cpu", "--iterations", "6"])
    assert r.exit_code != 0 and "dataset" in str(r.exception)


def test_compare_scores_lpips_with_the_network_asked_and_scores_a_finished_run_again_without_retraining(
        tiny_data, tmp_path):
    from splatzoo.evaluate import lpips_net_of

    out, run = tmp_path / "cmp", tmp_path / "cmp" / "runs" / "2dgs"
    base = ["compare", "2dgs", "--data", str(tiny_data), "--out", str(out), "--num-primitives", "50", "--backend",
            "cpu", "--iterations", "4", "--store", "8bit"]
    r = runner.invoke(app, base + ["--lpips-net", "alex"])
    assert r.exit_code == 0, r.output
    alex = json.loads((run / "metrics.json").read_text())
    assert lpips_net_of(alex) == "alex"
    assert json.loads((out / "compare.json").read_text())["settings"]["lpips_net"] == "alex"
    assert "LPIPS v0.1 alex" in (out / "report.md").read_text()
    trained = {p.name: p.read_bytes() for p in run.iterdir() if p.suffix in (".szp", ".pt", ".jsonl")}
    r = runner.invoke(app, base)  # VGG, the default: the same run scored again
    assert r.exit_code == 0, r.output
    vgg = json.loads((run / "metrics.json").read_text())
    assert lpips_net_of(vgg) == "vgg" and vgg["lpips"] != alex["lpips"]
    assert {k: vgg[k] for k in ("psnr", "ssim", "float32_psnr", "stored_bytes")} == {
        k: alex[k] for k in ("psnr", "ssim", "float32_psnr", "stored_bytes")}
    assert {p.name: p.read_bytes() for p in run.iterdir() if p.suffix in (".szp", ".pt", ".jsonl")} == trained
    other = [str(tmp_path / "other") if word == str(out) else word for word in base]
    r = runner.invoke(app, other + ["--lpips-net", "squeeze"])  # refused before any training
    assert r.exit_code != 0 and "vgg, alex" in str(r.exception) and not (tmp_path / "other").exists()


def test_compare_names_runs_made_by_other_code(tiny_data, tmp_path):
    """A finished run whose recorded code fingerprint is not today's (the models, trainer, rasterizers or metrics
    changed since) is reused but named in the report and on stderr; --overwrite retrains it with today's code. A
    run recorded before runs kept a fingerprint counts as today's."""
    from splatzoo.runs import code_fingerprint

    out = tmp_path / "cmp"
    base = ["compare", "2dgs", "--data", str(tiny_data), "--out", str(out), "--num-primitives", "50", "--backend",
            "cpu", "--iterations", "4"]
    assert runner.invoke(app, base).exit_code == 0
    config = out / "runs" / "2dgs" / "config.json"
    record = json.loads(config.read_text())
    assert record["code"] == code_fingerprint("2dgs")
    first = json.loads((out / "compare.json").read_text())["runs"]["2dgs"]
    config.write_text(json.dumps({**record, "code": "0" * 16}))
    r = runner.invoke(app, base)
    assert r.exit_code == 0, r.output
    report = json.loads((out / "compare.json").read_text())
    assert report["runs"]["2dgs"] == first and report["settings"]["trained_by_other_code"] == ["2dgs"]
    assert "trained by other splatzoo code" in (out / "report.md").read_text()
    assert "trained by other splatzoo code" in r.stderr
    r = runner.invoke(app, base + ["--overwrite"])
    assert r.exit_code == 0, r.output
    assert json.loads(config.read_text())["code"] == code_fingerprint("2dgs")
    assert json.loads((out / "compare.json").read_text())["settings"]["trained_by_other_code"] == []
    assert "other splatzoo code" not in (out / "report.md").read_text()
    record = json.loads(config.read_text())
    del record["code"]
    config.write_text(json.dumps(record))
    r = runner.invoke(app, base)
    assert r.exit_code == 0 and "other splatzoo code" not in r.stderr


def test_compare_at_equal_bytes(tiny_data, tmp_path):
    """--equal-bytes: the first model gets --num-primitives and its trained size is the budget, the others get as
    many primitives as fit in it; the runs record their own counts, so an equal-count comparison in the same folder
    is another setting, not a reuse."""
    out = tmp_path / "cmp"
    base = ["compare", "2dgs", "gabor", "--data", str(tiny_data), "--out", str(out), "--num-primitives", "100",
            "--backend", "cpu", "--iterations", "4"]
    r = runner.invoke(app, base + ["--equal-bytes"])
    assert r.exit_code == 0, r.output
    report = json.loads((out / "compare.json").read_text())
    runs, counts = report["runs"], report["settings"]["primitives"]
    assert runs["2dgs"]["num_primitives"] == counts["2dgs"] == 100
    # gabor K=4: 28 floats a surfel against 2DGS's 13
    assert runs["gabor"]["num_primitives"] == counts["gabor"] == 100 * 13 // 28
    assert 0.95 < runs["gabor"]["size_bytes"] / runs["2dgs"]["size_bytes"] <= 1.0
    assert "equal bytes" in (out / "report.md").read_text() and "equal bytes" in r.output
    r = runner.invoke(app, base)
    assert r.exit_code != 0 and "num_primitives" in str(r.exception)
    r = runner.invoke(app, base + ["--equal-bytes", "--no-antialias"])  # another setting too: no silent reuse
    assert r.exit_code != 0 and "antialias" in str(r.exception)
    r = runner.invoke(app, base + ["--equal-bytes", "--antialias", "--overwrite"])
    assert r.exit_code == 0, r.output
    report = json.loads((out / "compare.json").read_text())
    assert report["settings"]["antialias"] and "anti-aliased" in (out / "report.md").read_text()
    assert json.loads((out / "runs" / "gabor" / "config.json").read_text())["train"]["antialias"] is True
    r = runner.invoke(app, base + ["--equal-bytes", "--densify"])
    assert r.exit_code != 0 and "fixed primitive counts" in str(r.exception)
    # gabor first: its trained size (what an adaptive model keeps) is the budget, and 2DGS fills it
    r = runner.invoke(app, ["compare", "gabor", "2dgs", "--data", str(tiny_data), "--out", str(tmp_path / "cmp2"),
                            "--num-primitives", "100", "--backend", "cpu", "--iterations", "4", "--equal-bytes"])
    assert r.exit_code == 0, r.output
    runs = json.loads((tmp_path / "cmp2" / "compare.json").read_text())["runs"]
    assert runs["gabor"]["num_primitives"] == 100
    assert runs["2dgs"]["num_primitives"] == runs["gabor"]["size_bytes"] // 52 == 100 * 28 // 13
    # an adaptive gabor first: the budget is what it kept after pruning its waves
    r = runner.invoke(app, ["compare", "gabor:prune_relative=2", "2dgs", "--data", str(tiny_data), "--out",
                            str(tmp_path / "cmp3"), "--num-primitives", "100", "--backend", "cpu", "--iterations", "4",
                            "--equal-bytes"])
    assert r.exit_code == 0, r.output
    runs = json.loads((tmp_path / "cmp3" / "compare.json").read_text())["runs"]
    assert runs["gabor:prune_relative=2"]["size_bytes"] < 100 * 28 * 4
    assert runs["2dgs"]["num_primitives"] == runs["gabor:prune_relative=2"]["size_bytes"] // 52
    # without --num-primitives the first model starts from every initial point, as an equal-count compare trains it:
    # that run is reused as the budget (the paper's table first, then its "Ours*" in the same folder)
    out4 = tmp_path / "cmp4"
    plain = ["--data", str(tiny_data), "--out", str(out4), "--backend", "cpu", "--iterations", "4"]
    assert runner.invoke(app, ["compare", "2dgs", *plain]).exit_code == 0
    first = json.loads((out4 / "compare.json").read_text())["runs"]["2dgs"]
    r = runner.invoke(app, ["compare", "2dgs", "gabor", *plain, "--equal-bytes"])
    assert r.exit_code == 0, r.output
    runs = json.loads((out4 / "compare.json").read_text())["runs"]
    assert runs["2dgs"] == first and runs["gabor"]["num_primitives"] == first["size_bytes"] // (28 * 4)
    assert "trained size of all initial points of `2dgs`" in (out4 / "report.md").read_text()


def test_resume_takes_its_settings_from_the_run(tiny_data, tmp_path):
    run = tmp_path / "run"
    r = runner.invoke(app, ["train", str(tiny_data), "--model", "2dgs", "--iterations", "8", "--num-primitives", "80",
                            "--backend", "cpu", "--out", str(run)])
    assert r.exit_code == 0, r.output
    os.remove(run / "model.pt")  # as if it had been interrupted after its last checkpoint...
    quick_train(tiny_data, tmp_path / "other")
    config_before = (run / "config.json").read_bytes()
    for extra, what in ((["--iterations", "9"], "iterations"), (["--model", "gabor"], "model"),
                        (["--resolution", "2"], "resolution"), (["--num-primitives", "81"], "num_primitives")):
        r = runner.invoke(app, ["train", "--resume", "--out", str(run)] + extra)
        assert r.exit_code != 0 and what in str(r.exception), (extra, r.output)
    from splatzoo.data.synthetic import make_synthetic_scene

    other = make_synthetic_scene("vest", tmp_path / "vest", views=10, width=40, height=40)
    r = runner.invoke(app, ["train", str(other), "--resume", "--out", str(run)])
    assert r.exit_code != 0 and "dataset" in str(r.exception)
    assert (run / "config.json").read_bytes() == config_before
    # agreeing options and an operational change (the backend) are fine; the closing line names the run's model
    r = runner.invoke(app, ["train", str(tiny_data), "--resume", "--out", str(run), "--iterations", "8",
                            "--backend", "reference"])
    assert r.exit_code == 0, r.output
    assert r.output.strip().splitlines()[-1].startswith("2dgs:")


def test_data_path_is_absolute_so_runs_work_from_anywhere(tiny_data, tmp_path, monkeypatch):
    monkeypatch.chdir(tiny_data.parent)
    quick_train(Path(tiny_data.name), tmp_path / "run")
    record = json.loads((tmp_path / "run" / "config.json").read_text())
    assert Path(record["data"]).is_absolute() and record["data_fingerprint"]
    monkeypatch.chdir(tmp_path)
    r = runner.invoke(app, ["render", str(tmp_path / "run")])
    assert r.exit_code == 0, r.output


# --- one writer at a time; runs are never silently replaced -------------------------------------------------------

def test_a_second_writer_is_refused_and_names_the_first(tiny_data, tmp_path):
    run = tmp_path / "run"
    with Run(run).lock("splatzoo train (the first)", create=True):
        with pytest.raises(RunLockedError, match=f"the first.*pid {os.getpid()}"):
            quick_train(tiny_data, run)
    assert not (run / "config.json").exists()
    quick_train(tiny_data, run)  # the lock went with its holder


def test_a_finished_run_is_not_overwritten(tiny_data, tmp_path):
    run = tmp_path / "run"
    quick_train(tiny_data, run)
    os.remove(run / "checkpoint.pt")  # a finished run need not keep its checkpoint
    model = (run / "model.pt").read_bytes()
    with pytest.raises(SplatzooError, match="finished run"):
        quick_train(tiny_data, run)
    r = runner.invoke(app, ["train", str(tiny_data), "--out", str(run), "--iterations", "3"])
    assert r.exit_code != 0 and "--overwrite" in str(r.exception)
    assert (run / "model.pt").read_bytes() == model
    with pytest.raises(SplatzooError, match="not a splatzoo run"):
        quick_train(tiny_data, tiny_data)  # a dataset folder is not a run folder
    quick_train(tiny_data, run, overwrite=True, config=cfg(iterations=3))
    assert json.loads((run / "config.json").read_text())["train"]["iterations"] == 3


# --- interrupts lose nothing -------------------------------------------------------------------------------------

KILL_RUN = dict(iterations=1000, num_primitives=150, backend="cpu", checkpoint_every=25)


@pytest.fixture(scope="module")
def uninterrupted(tiny_data, tmp_path_factory):
    return train(tiny_data, "gabor", {}, TrainConfig(**KILL_RUN), tmp_path_factory.mktemp("ref") / "run",
                 progress=False, evaluate_at_end=False).model


def _train_cmd(data, out):
    return [sys.executable, "-m", "splatzoo.cli", "train", str(data), "--model", "gabor", "--out", str(out)] + \
        [a for k, v in KILL_RUN.items() for a in (f"--{k.replace('_', '-')}", str(v))]


@pytest.mark.parametrize("signum", [signal.SIGINT, signal.SIGTERM, signal.SIGKILL])
def test_killed_training_resumes_bit_identically(tiny_data, tmp_path, signum, uninterrupted):
    run = tmp_path / "run"
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    proc = subprocess.Popen(_train_cmd(tiny_data, run), stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                            env=env)
    deadline = time.monotonic() + 120
    while not (run / "train_log.jsonl").exists() or not (run / "train_log.jsonl").read_text():
        assert proc.poll() is None and time.monotonic() < deadline, proc.communicate()[0]
        time.sleep(0.05)
    time.sleep(random.Random(int(signum)).uniform(0.0, 1.5))  # a random moment of the run
    proc.send_signal(signum)
    output, _ = proc.communicate(timeout=120)
    if proc.returncode == 0:
        pytest.fail("training finished before the signal arrived; make the run longer")
    assert proc.returncode == (-9 if signum == signal.SIGKILL else 128 + signum), output
    if signum != signal.SIGKILL:
        assert "--resume" in output and "Traceback" not in output and "stack trace" not in output, output
        assert (run / "checkpoint.pt").exists()
    assert not (run / "model.pt").exists()
    r = subprocess.run([sys.executable, "-m", "splatzoo.cli", "train", "--resume", "--out", str(run)],
                       capture_output=True, text=True, env=env)
    assert r.returncode == 0, r.stderr
    from splatzoo import load_model

    assert_same_parameters(uninterrupted, load_model(run / "model.pt"))
    assert not [p for p in run.iterdir() if p.name.startswith(".checkpoint")]


def test_checkpoints_by_time_and_stale_temp_files(tiny_data, tmp_path, monkeypatch):
    import splatzoo.run_launch as runs

    saves = []
    real = runs.torch_save
    monkeypatch.setattr(runs, "torch_save", lambda obj, path: (saves.append(obj["iteration"]), real(obj, path)))
    quick_train(tiny_data, tmp_path / "timed", config=cfg(checkpoint_every=1000, checkpoint_minutes=1e-9))
    assert saves == list(range(1, 13))
    saves.clear()
    quick_train(tiny_data, tmp_path / "untimed", config=cfg(checkpoint_every=1000, checkpoint_minutes=0))
    assert saves == [12]
    run = tmp_path / "part"
    quick_train(tiny_data, run, stop_after=5)
    stale = run / ".checkpoint.pt.k1ll3d_x.pt"
    stale.write_bytes(b"half a checkpoint")
    quick_train(tiny_data, run, resume=True)
    assert not stale.exists() and (run / "model.pt").exists()


# --- damaged files and bad values ----------------------------------------------------------------------------------

def _crafted_states(state: dict) -> dict:
    """Checkpoints whose training state is inconsistent, by what their error must name."""
    opt = state["optimizer"]
    first = next(iter(opt["state"]))
    wrong_shape = {**opt, "state": {**opt["state"], first: {**opt["state"][first],
                                                            "exp_avg": torch.zeros(3, 1)}}}
    nan_moment = {**opt, "state": {**opt["state"], first: {**opt["state"][first],
                                                           "exp_avg_sq": opt["state"][first]["exp_avg_sq"] * float("nan")}}}
    n = state["densify"]["count"].shape[0]
    return {
        "iteration 13 is outside": {**state, "iteration": 13},  # past the end: it would train nothing, finish
        "iteration -1 is outside": {**state, "iteration": -1},
        "iteration is 6.5": {**state, "iteration": 6.5},
        "view_order names view 10": {**state, "view_order": [10]},
        "view_order names view -1": {**state, "view_order": [-1]},
        "view_order must list at most": {**state, "view_order": list(range(9)) * 200},
        "names a training view twice": {**state, "view_order": [1, 1]},
        "recent_error is 'x'": {**state, "recent_error": "x"},
        "train_seconds is nan": {**state, "train_seconds": float("nan")},
        "no Adam state": {**state, "optimizer": {**opt, "state": {}}},
        "exp_avg of means has shape": {**state, "optimizer": wrong_shape},
        "exp_avg_sq of means holds non-finite": {**state, "optimizer": nan_moment},
        "statistic count has shape": {**state, "densify": {**state["densify"], "count": torch.zeros(n + 1)}},
        "statistic grad_sum must hold": {**state, "densify": {**state["densify"],
                                                              "grad_sum": torch.full((n,), -1.0)}},
    }


def test_an_inconsistent_training_state_is_refused_before_training(tiny_data, tmp_path):
    """Each crafted checkpoint is a named error that keeps the checkpoint and writes no model."""
    run = tmp_path / "run"
    quick_train(tiny_data, run, stop_after=6)
    good = (run / "checkpoint.pt").read_bytes()
    state = torch.load(run / "checkpoint.pt", weights_only=True)
    for problem, crafted in _crafted_states(state).items():
        torch.save(crafted, run / "checkpoint.pt")
        kept = (run / "checkpoint.pt").read_bytes()
        with pytest.raises(SplatzooError, match="consistent training state") as e:
            quick_train(tiny_data, run, resume=True)
        assert problem in str(e.value), (problem, str(e.value))
        assert (run / "checkpoint.pt").read_bytes() == kept and not (run / "model.pt").exists()
    (run / "checkpoint.pt").write_bytes(good)
    quick_train(tiny_data, run, resume=True)  # the good one still resumes
    assert (run / "model.pt").exists()


def test_damaged_files_give_clear_errors(tiny_data, tmp_path):
    run = tmp_path / "run"
    quick_train(tiny_data, run, stop_after=6)
    good = (run / "checkpoint.pt").read_bytes()
    for damaged in (b"", good[: len(good) // 2], b"not a zip at all"):
        (run / "checkpoint.pt").write_bytes(damaged)
        with pytest.raises(SplatzooError, match="checkpoint"):
            quick_train(tiny_data, run, resume=True)
    (run / "checkpoint.pt").write_bytes(good)
    state = torch.load(run / "checkpoint.pt", weights_only=True)
    torch.save({**state, "optimizer": {"state": {}, "param_groups": [{"params": [99]}]}}, run / "checkpoint.pt")
    with pytest.raises(SplatzooError, match="consistent training state"):
        quick_train(tiny_data, run, resume=True)
    (run / "checkpoint.pt").write_bytes(good)
    # a log line cut short by a kill is dropped on resume
    with open(run / "train_log.jsonl", "a") as f:
        f.write('{"iteration": 7, "lo')
    config = (run / "config.json").read_text()
    (run / "config.json").write_text(config[:40])
    with pytest.raises(SplatzooError, match="config.json"):
        quick_train(tiny_data, run, resume=True)
    r = runner.invoke(app, ["eval", str(run)])
    assert r.exit_code != 0 and isinstance(r.exception, SplatzooError)
    (run / "config.json").write_text(config)
    quick_train(tiny_data, run, resume=True)
    log = Run(run).log()
    assert [rec["iteration"] for rec in log if "loss" in rec] == list(range(2, 13, 2))
    assert all(json.loads(line) for line in (run / "train_log.jsonl").read_text().splitlines())


def test_bad_values_and_full_disk(tiny_data, tmp_path, monkeypatch):
    for bad in ("nan", "inf", "-1"):
        r = runner.invoke(app, ["train", str(tiny_data), "--lambda-normal", bad, "--out", str(tmp_path / bad)])
        assert r.exit_code != 0 and "lambda_normal" in str(r.exception), r.output
        assert not (tmp_path / bad / "config.json").exists()
    # metrics are strict JSON: a non-finite number is null, never `Infinity`
    from splatzoo.io import write_json

    write_json(tmp_path / "m.json", {"psnr": float("inf"), "x": [float("nan")]})
    assert json.loads((tmp_path / "m.json").read_text(), parse_constant=lambda c: pytest.fail(c)) == \
        {"psnr": None, "x": [None]}
    # a full disk while checkpointing: a clear error, and the previous checkpoint stays intact
    run = tmp_path / "disk"
    quick_train(tiny_data, run, stop_after=4)
    before = (run / "checkpoint.pt").read_bytes()

    def full(obj, path):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(torch, "save", full)
    with pytest.raises(SplatzooError, match="No space left"):
        quick_train(tiny_data, run, resume=True)
    assert (run / "checkpoint.pt").read_bytes() == before
    assert [p.name for p in run.iterdir() if p.name.startswith(".checkpoint")] == []

    # what torch really raises when its zip writer meets a full disk: a RuntimeError, half a file written
    def torch_full(obj, path):
        Path(path).write_bytes(b"PK\x03\x04 half")
        raise RuntimeError("[enforce fail at inline_container.cc:664] . unexpected pos 4096 vs 4043")

    monkeypatch.setattr(torch, "save", torch_full)
    with pytest.raises(SplatzooError, match=r"cannot write .*checkpoint.pt: .*Free disk space"):
        quick_train(tiny_data, run, resume=True)
    assert (run / "checkpoint.pt").read_bytes() == before
    assert [p.name for p in run.iterdir() if p.name.startswith(".checkpoint")] == []


def test_runs_from_before_the_antialiased_default_resume_without_it(tiny_data, tmp_path):
    """Anti-aliasing is on by default now; a run record written before the option existed lacks the key and meant
    off, so its resume must not switch the filter on halfway."""
    run = tmp_path / "run"
    quick_train(tiny_data, run, config=TrainConfig(iterations=2, backend="cpu"))
    assert Run(run).train_config().antialias is True  # the default
    rec = json.loads((run / "config.json").read_text())
    del rec["train"]["antialias"]
    (run / "config.json").write_text(json.dumps(rec))
    assert Run(run).train_config().antialias is False
    assert TrainConfig().antialias is True


def test_a_run_on_read_only_media_is_evaluated_rendered_and_meshed_elsewhere(tiny_data, tmp_path, monkeypatch):
    """Reading commands with --out outside the run take no lock and write nothing into it; without --out a
    read-only run folder is named, with the option to use."""
    import os

    run = tmp_path / "run"
    quick_train(tiny_data, run)
    before = sorted(p.name for p in run.iterdir())
    real_access = os.access
    monkeypatch.setattr(os, "access", lambda p, mode, **kw: False if Path(p) == run and mode & os.W_OK
                        else real_access(p, mode, **kw))
    real_open = os.open

    def no_writes_in_run(path, flags, *a, **kw):  # what a read-only mount does to the lock file
        if Path(path).parent == run and flags & (os.O_CREAT | os.O_WRONLY | os.O_RDWR):
            raise OSError(30, "Read-only file system")
        return real_open(path, flags, *a, **kw)

    monkeypatch.setattr(os, "open", no_writes_in_run)
    for args, written in ((["eval", str(run), "--backend", "cpu", "--out", str(tmp_path / "m.json")], "m.json"),
                          (["render", str(run), "--backend", "cpu", "--out", str(tmp_path / "r")], "r")):
        r = runner.invoke(app, args)
        assert r.exit_code == 0, (args, r.output, r.exception)
        assert (tmp_path / written).exists()
    # a 12-iteration model has little surface to mesh: the command reads the run and fuses its depth all the same,
    # writing the mesh (or saying that too little was fused) outside the run
    r = runner.invoke(app, ["extract-mesh", str(run), "--backend", "cpu", "--out", str(tmp_path / "mesh.ply")])
    if r.exception is None:
        assert r.exit_code == 0 and (tmp_path / "mesh.ply").exists(), r.output
    else:
        assert isinstance(r.exception, SplatzooError) and "depth pixels were fused" in str(r.exception), r.output
    assert json.loads((tmp_path / "m.json").read_text())["psnr"] > 0
    assert list((tmp_path / "r" / "test").glob("*.png"))
    for args, option in ((["eval", str(run), "--backend", "cpu"], "--out FILE.json"),
                         (["render", str(run), "--backend", "cpu"], "--out FOLDER"),
                         (["extract-mesh", str(run), "--backend", "cpu"], "--out FILE.ply")):
        r = runner.invoke(app, args)
        assert r.exit_code != 0 and "is read-only" in str(r.exception) and option in str(r.exception), r.output
    assert sorted(p.name for p in run.iterdir()) == before


def test_hand_edited_config_and_meta_tensors_are_named(tiny_data, tmp_path):
    """config.json with a number for data or a string for scene_options, and a model.pt holding a meta tensor
    (no data): named errors instead of TypeError, ValueError or RuntimeError tracebacks."""
    run = tmp_path / "run"
    quick_train(tiny_data, run)
    good = (run / "config.json").read_text()
    for key, value, want in (("data", 5, "'data' must be a string or null, not int"),
                             ("scene_options", "x", "'scene_options' must be an object or null, not str"),
                             ("train", [], "'train' must be an object, not list")):
        (run / "config.json").write_text(json.dumps({**json.loads(good), key: value}))
        with pytest.raises(SplatzooError, match=re.escape(want)):
            Run(run).load("cpu")
    (run / "config.json").write_text(good)
    from splatzoo import load_model

    state = torch.load(run / "model.pt", weights_only=True)
    state["state"]["means"] = torch.empty(state["state"]["means"].shape, device="meta")
    torch.save(state, tmp_path / "meta.pt")
    with pytest.raises(SplatzooError, match="state entry 'means' holds no data"):
        load_model(tmp_path / "meta.pt")


def test_a_run_recorded_before_a_training_field_existed_is_reused():
    """A record without a field added since (densify_views) and with the strategy "auto" stands for ("adc" for 2dgs)
    asks for nothing new; the same record for a model whose own strategy differs does."""
    import dataclasses

    from splatzoo.runs import differences
    from splatzoo.training import TrainConfig

    wanted_train = dataclasses.asdict(TrainConfig(iterations=10))
    old_train = {k: v for k, v in wanted_train.items() if k != "densify_views"}
    old_train["strategy"] = "adc"
    assert differences({"model": "2dgs", "train": old_train}, {"model": "2dgs", "train": wanted_train}) == []
    changed = differences({"model": "neural-gabor", "train": old_train},
                          {"model": "neural-gabor", "train": wanted_train})
    assert changed == ["strategy: run has 'adc', asked 'frequency'"]
    assert differences({"model": "2dgs", "train": {**old_train, "densify_views": 3}},
                       {"model": "2dgs", "train": wanted_train}) == ["densify_views: run has 3, asked 20"]


def test_compare_with_one_densification_strategy(tiny_data, tmp_path):
    """--strategy with --densify: every model densifies so (the runs record it, so it is a setting, never a reuse);
    without --densify it is an error naming the missing option, before any training."""
    out = tmp_path / "cmp"
    base = ["compare", "2dgs", "neural-gabor", "--data", str(tiny_data), "--out", str(out), "--num-primitives", "60",
            "--backend", "cpu", "--iterations", "4"]
    r = runner.invoke(app, base + ["--strategy", "mcmc"])
    assert r.exit_code != 0 and "--densify" in str(r.exception) and not out.exists()
    r = runner.invoke(app, base + ["--densify", "--strategy", "mcmc"])
    assert r.exit_code == 0, r.output
    for label in ("2dgs", "neural-gabor"):
        assert json.loads((out / "runs" / label / "config.json").read_text())["train"]["strategy"] == "mcmc"
    assert "strategy mcmc" in (out / "report.md").read_text()
    r = runner.invoke(app, base + ["--densify"])  # auto: each its own, another setting for neural-gabor
    assert r.exit_code != 0 and "strategy" in str(r.exception)
    r = runner.invoke(app, base + ["--densify", "--strategy", "shuffle"])
    assert r.exit_code != 0 and "--strategy must be one of" in str(r.exception)
