"""Training on several processes (torch.distributed, gloo on the CPU): batches of views, identical decisions on
every rank, checkpoints and resume, a dying rank ending the run clearly."""
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch

from splatzoo import load_model
from splatzoo.errors import SplatzooError
from splatzoo.runs import train
from splatzoo.training import TrainConfig

# densification inside the run (steps 10 and 20), so that "the same decisions on every rank" is tested
RUN = dict(iterations=24, backend="cpu", num_primitives=150, densify=True, densify_from=0, densify_until=30000,
           opacity_reset_interval=10 ** 6, log_every=4, eval_every=12, seed=2, densify_grad_threshold=5e-5)


@pytest.fixture(scope="module")
def tiny_data(tmp_path_factory):
    from splatzoo.data.synthetic import make_synthetic_scene

    return make_synthetic_scene("sweater", tmp_path_factory.mktemp("data") / "sweater", views=10, width=40, height=40)


def assert_close(a, b, rtol=1e-4, atol=1e-6):
    sa, sb = a.state_dict(), b.state_dict()
    assert sa.keys() == sb.keys()
    for k in sa:
        assert sa[k].shape == sb[k].shape, k
        assert torch.allclose(sa[k], sb[k], rtol=rtol, atol=atol), (k, (sa[k] - sb[k]).abs().max())


def test_batches_and_processes_agree(tiny_data, tmp_path):
    one = train(tiny_data, "gabor", {}, TrainConfig(**RUN, batch_size=2), tmp_path / "b2", progress=False,
                evaluate_at_end=False).model
    two = train(tiny_data, "gabor", {}, TrainConfig(**RUN, nproc=2), tmp_path / "n2", progress=False,
                evaluate_at_end=False).model
    assert one.num_primitives != RUN["num_primitives"], "densification should have changed the count"
    assert_close(one, two)
    single = train(tiny_data, "gabor", {}, TrainConfig(**RUN), tmp_path / "b1", progress=False,
                   evaluate_at_end=False).model
    assert not torch.equal(single.means, one.means)  # a batch of two is a different run, not the same one
    logs = (tmp_path / "n2" / "train_log.jsonl").read_text().splitlines()
    assert len(logs) == len((tmp_path / "b2" / "train_log.jsonl").read_text().splitlines())


def _children(pid: int) -> list[int]:
    out = []
    for d in Path("/proc").iterdir():
        if d.name.isdigit():
            try:
                stat = (d / "stat").read_text()
            except OSError:
                continue
            if int(stat.rsplit(")", 1)[1].split()[1]) == pid:
                out.append(int(d.name))
    return out


def _start(data, out):
    args = [sys.executable, "-m", "splatzoo.cli", "train", str(data), "--model", "gabor", "--out", str(out),
            "--nproc", "2", "--iterations", "150", "--num-primitives", "150", "--backend", "cpu",
            "--checkpoint-every", "10"]
    proc = subprocess.Popen(args, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                            env={**os.environ, "PYTHONUNBUFFERED": "1"})
    deadline = time.monotonic() + 180
    while not (out / "checkpoint.pt").exists():
        assert proc.poll() is None and time.monotonic() < deadline, proc.communicate()[0]
        time.sleep(0.05)
    return proc


def test_sigterm_checkpoints_and_resume_matches(tiny_data, tmp_path):
    reference = train(tiny_data, "gabor", {}, TrainConfig(iterations=150, num_primitives=150, backend="cpu",
                                                          nproc=2, checkpoint_every=10),
                      tmp_path / "reference", progress=False, evaluate_at_end=False).model
    run = tmp_path / "run"
    proc = _start(tiny_data, run)
    time.sleep(0.5)
    proc.send_signal(signal.SIGTERM)
    output, _ = proc.communicate(timeout=180)
    assert proc.returncode == 143, output
    assert "--resume" in output and "Traceback" not in output, output
    assert not (run / "model.pt").exists()
    r = subprocess.run([sys.executable, "-m", "splatzoo.cli", "train", "--resume", "--out", str(run)],
                       capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    assert_close(reference, load_model(run / "model.pt"), rtol=0, atol=0)
    r = subprocess.run([sys.executable, "-m", "splatzoo.cli", "train", "--resume", "--out", str(run), "--nproc", "1"],
                       capture_output=True, text=True)
    assert r.returncode != 0


def test_a_dying_rank_ends_the_run_clearly(tiny_data, tmp_path):
    run = tmp_path / "run"
    proc = _start(tiny_data, run)
    ranks = []
    deadline = time.monotonic() + 60
    while len(ranks) < 2 and time.monotonic() < deadline:  # the spawn start method adds a resource tracker
        ranks = [p for p in _children(proc.pid) if "spawn_main" in Path(f"/proc/{p}/cmdline").read_text()]
        time.sleep(0.05)
    os.kill(max(ranks), signal.SIGKILL)
    output, _ = proc.communicate(timeout=180)
    assert proc.returncode == 2, output
    assert "rank" in output and "SIGKILL" in output and "--resume" in output, output
    assert (run / "checkpoint.pt").exists()
    with pytest.raises(SplatzooError, match="nproc"):
        train(tiny_data, "gabor", {}, {"nproc": 3}, run, resume=True, progress=False)
