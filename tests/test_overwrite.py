"""--overwrite loses nothing: every check that can refuse a new run comes before the old run is touched, and the old
run is set aside (not deleted) until the new run writes its first checkpoint, restored if anything fails before."""
import hashlib
import os
from pathlib import Path

import pytest
import torch
from typer.testing import CliRunner

from splatzoo.cli import app
from splatzoo.errors import SplatzooError
from splatzoo.runs import LOCK_NAME, REPLACED_NAME, Run, train
from splatzoo.training import TrainConfig

runner = CliRunner()


@pytest.fixture(scope="module")
def tiny_data(tmp_path_factory):
    from splatzoo.data.synthetic import make_synthetic_scene

    return make_synthetic_scene("sweater", tmp_path_factory.mktemp("data") / "sweater", views=8, width=32, height=32)


def cfg(**kw):
    return TrainConfig(**{**dict(iterations=6, backend="cpu", num_primitives=100, log_every=2, seed=3), **kw})


@pytest.fixture(scope="module")
def finished(tiny_data, tmp_path_factory):
    """A finished run (model, checkpoint, metrics) to copy into each test."""
    run = tmp_path_factory.mktemp("finished") / "run"
    train(tiny_data, "2dgs", {}, cfg(), run, progress=False)
    return run


def folder_digest(folder: Path) -> dict[str, str]:
    """Every file under `folder` (the lock too) by relative path -> sha256 of its bytes."""
    return {str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(folder.rglob("*")) if p.is_file()}


@pytest.fixture
def run(finished, tmp_path):
    import shutil

    copy = tmp_path / "run"
    shutil.copytree(finished, copy)
    return copy


def test_a_finished_run_at_rest_is_byte_identical_after_a_command(run, tiny_data):
    """The lock file holds its holder's name only while held: a refused command changes no byte of the folder."""
    before = folder_digest(run)
    assert (run / LOCK_NAME).read_bytes() == b""
    r = runner.invoke(app, ["train", str(tiny_data), "--out", str(run), "-i", "3"])
    assert r.exit_code != 0 and "--overwrite" in str(r.exception)
    assert folder_digest(run) == before


@pytest.mark.parametrize("args, says", [
    (["--backend", "cuda"], "cuda"),
    (["--nproc", "2", "--backend", "cuda"], "cuda"),
    (["--max-primitives", "1000000000"], "GiB"),
    (["-n", "1000000000", "--no-densify"], "GiB"),
    (["--nproc", "99999999999999999999999"], "CPU cores"),
])
def test_overwrite_refused_late_keeps_the_finished_run(run, tiny_data, args, says):
    if "cuda" in args and torch.cuda.is_available():
        pytest.skip("this machine has a GPU: --backend cuda is not refused")
    before = folder_digest(run)
    r = runner.invoke(app, ["train", str(tiny_data), "--model", "2dgs", "--out", str(run), "-i", "3",
                            "--overwrite", *args])
    assert r.exit_code != 0, r.output
    message = str(r.exception) + r.output
    assert says in message and "Traceback" not in r.output
    assert "ZeroDivision" not in message
    assert folder_digest(run) == before


def test_a_new_run_that_fails_before_its_first_checkpoint_gives_the_folder_back(run, tiny_data, monkeypatch):
    from splatzoo.training import trainer

    before = folder_digest(run)

    def broken(*a, **k):
        raise SplatzooError("the model could not be made")

    monkeypatch.setattr(trainer.Trainer, "start", classmethod(broken))
    with pytest.raises(SplatzooError, match="restored") as e:
        train(tiny_data, "gabor", {}, cfg(), run, progress=False, overwrite=True)
    assert "could not be made" in str(e.value)
    assert folder_digest(run) == before and not (run / REPLACED_NAME).exists()

    def interrupted(*a, **k):
        raise KeyboardInterrupt

    monkeypatch.setattr(trainer.Trainer, "start", classmethod(interrupted))
    with pytest.raises(KeyboardInterrupt):
        train(tiny_data, "gabor", {}, cfg(), run, progress=False, overwrite=True)
    assert folder_digest(run) == before


def test_a_killed_replacement_is_undone_by_the_next_command(run, tiny_data):
    """A process killed after it set the old run aside and before the new run's first checkpoint (SIGKILL, power
    loss): the next command to take the lock restores the old run."""
    before = folder_digest(run)
    old = Run(run)
    old.set_aside()
    (run / "config.json").write_text("{}")  # what the new run had written
    assert (run / REPLACED_NAME).is_dir() and old.status == "started"
    # a command that only reads (no lock) says where the old run is and how it comes back
    r = runner.invoke(app, ["eval", str(run), "--out", str(run.parent / "m.json")])
    assert isinstance(r.exception, SplatzooError), r.output
    assert f"the run it was to replace is kept in {run / REPLACED_NAME}" in str(r.exception)
    assert f"`splatzoo eval {run}`" in str(r.exception)
    with old.lock("splatzoo eval"):
        pass
    assert folder_digest(run) == before and old.status == "finished"


def test_the_replaced_run_goes_at_the_new_runs_first_checkpoint(run, tiny_data):
    old_model = (run / "model.pt").read_bytes()
    train(tiny_data, "gabor", {}, cfg(iterations=4, checkpoint_every=2), run, progress=False, overwrite=True,
          stop_after=2)
    assert Run(run).status == "interrupted" and not (run / REPLACED_NAME).exists()
    assert not (run / "model.pt").exists() and old_model  # the old model is gone for good: the new run resumes
    train(tiny_data, resume=True, out=run, progress=False)
    assert Run(run).status == "finished" and not (run / REPLACED_NAME).exists()


def test_a_refused_new_run_leaves_no_folder(tiny_data, tmp_path):
    out = tmp_path / "never"
    r = runner.invoke(app, ["train", str(tiny_data), "--out", str(out), "--max-primitives", "1000000000"])
    assert r.exit_code != 0 and "GiB" in str(r.exception)
    assert not out.exists()


def test_compare_overwrite_refused_late_keeps_the_runs(tiny_data, tmp_path):
    out = tmp_path / "cmp"
    base = ["compare", "2dgs", "--data", str(tiny_data), "--out", str(out), "-i", "3", "--backend", "cpu"]
    r = runner.invoke(app, [*base, "-n", "80"])
    assert r.exit_code == 0, r.output
    before = folder_digest(out)
    r = runner.invoke(app, [*base, "-n", "1000000000", "--overwrite"])
    assert r.exit_code != 0 and "Traceback" not in r.output
    assert "GiB" in str(r.exception) + r.output
    assert folder_digest(out) == before


def test_resume_on_a_backend_that_cannot_run_here_is_refused_by_name(tiny_data, tmp_path):
    if torch.cuda.is_available():
        pytest.skip("this machine has a GPU")
    run = tmp_path / "run"
    train(tiny_data, "2dgs", {}, cfg(iterations=4, checkpoint_every=2), run, progress=False, stop_after=2)
    before = folder_digest(run)
    r = runner.invoke(app, ["train", "--resume", "--out", str(run), "--backend", "cuda"])
    assert r.exit_code != 0 and "cuda" in str(r.exception).lower(), r.output
    assert folder_digest(run) == before


def test_a_full_disk_while_the_run_folder_is_made_is_named(tiny_data, tmp_path, monkeypatch):
    """ENOSPC on the lock's note and on config.json: a named error, and no half-made folder left."""
    import errno

    def full(*a, **k):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(os, "pwrite", full)
    monkeypatch.setattr(Path, "write_text", full)
    out = tmp_path / "run"
    with pytest.raises(SplatzooError, match="Free disk space"):
        train(tiny_data, "2dgs", {}, cfg(), out, progress=False)
    assert not out.exists()
