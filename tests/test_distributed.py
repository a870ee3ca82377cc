"""Training on several processes (torch.distributed, gloo on the CPU): batches of views, identical decisions on
every rank, checkpoints and resume, a dying rank ending the run clearly."""
import json
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch

from splatzoo import load_model
from splatzoo.errors import SplatzooError
from splatzoo.runs import Run, train
from splatzoo.training import TrainConfig

# densification inside the run (steps 10 and 20), so that "the same decisions on every rank" is tested
RUN = dict(iterations=24, backend="cpu", num_primitives=150, densify=True, densify_from=0, densify_until=30000,
           densify_interval=10,
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


@pytest.fixture(scope="module")
def batch_of_two(tiny_data, tmp_path_factory):
    """One process, two views per step: what two ranks of one view each must reproduce."""
    out = tmp_path_factory.mktemp("runs") / "b2"
    train(tiny_data, "gabor", {}, TrainConfig(**RUN, batch_size=2), out, progress=False, evaluate_at_end=False)
    return out


def test_batches_and_processes_agree(tiny_data, batch_of_two, tmp_path):
    one = load_model(batch_of_two / "model.pt")
    two = train(tiny_data, "gabor", {}, TrainConfig(**RUN, nproc=2), tmp_path / "n2", progress=False,
                evaluate_at_end=False).model
    assert one.num_primitives != RUN["num_primitives"], "densification should have changed the count"
    assert_close(one, two)
    single = train(tiny_data, "gabor", {}, TrainConfig(**RUN), tmp_path / "b1", progress=False,
                   evaluate_at_end=False).model
    assert not torch.equal(single.means, one.means)  # a batch of two is a different run, not the same one
    logs = (tmp_path / "n2" / "train_log.jsonl").read_text().splitlines()
    assert len(logs) == len((batch_of_two / "train_log.jsonl").read_text().splitlines())


# what each process a launcher starts runs: train() finds its rank in the environment
_LAUNCHED = """
import json, sys
from splatzoo.runs import train
from splatzoo.training import TrainConfig
data, out, config, stop_after = sys.argv[1], sys.argv[2], json.loads(sys.argv[3]), int(sys.argv[4])
resume = config is None
train(None if resume else data, None if resume else "gabor", None, None if resume else TrainConfig(**config), out,
      resume=resume, progress=False, evaluate_at_end=False, stop_after=stop_after or None)
"""


def _torchrun(*args):
    return subprocess.run([sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc-per-node", "2",
                           *map(str, args)], capture_output=True, text=True, timeout=300,
                          env={**os.environ, "OMP_NUM_THREADS": "1"})


def test_torchrun_matches_a_batch_and_resumes(tiny_data, batch_of_two, tmp_path):
    script = tmp_path / "launched.py"
    script.write_text(_LAUNCHED)
    run = tmp_path / "launched"
    r = _torchrun(script, tiny_data, run, json.dumps(RUN), 12)  # stops after iteration 12 with a checkpoint
    assert r.returncode == 0, r.stderr
    assert Run(run).status == "interrupted" and Run(run).train_config().nproc == 2
    r = _torchrun(script, tiny_data, run, "null", 0)  # every rank resumes from rank 0's checkpoint
    assert r.returncode == 0, r.stderr
    assert_close(load_model(batch_of_two / "model.pt"), load_model(run / "model.pt"))


def test_a_refused_launch_ends_every_rank(tmp_path):
    """Any launcher (torchrun, srun, mpirun) sets RANK and WORLD_SIZE: a request rank 0 refuses reaches every rank,
    none waits for the others, and each says why."""
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        port = sock.getsockname()[1]
    procs = [subprocess.Popen([sys.executable, "-m", "splatzoo", "train", "--resume", "--out", str(tmp_path / "none")],
                              stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                              env={**os.environ, "RANK": str(rank), "LOCAL_RANK": str(rank), "WORLD_SIZE": "2",
                                   "MASTER_ADDR": "127.0.0.1", "MASTER_PORT": str(port)})
             for rank in range(2)]
    for rank, proc in enumerate(procs):
        output = proc.communicate(timeout=120)[0]
        assert proc.returncode == 2, output
        assert f"error (rank {rank}): cannot resume" in output, output
        assert "Traceback" not in output, output
    assert not (tmp_path / "none").exists()  # a resume creates nothing


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


def _start(data, out, iterations=150, **env):
    args = [sys.executable, "-m", "splatzoo.cli", "train", str(data), "--model", "gabor", "--out", str(out),
            "--nproc", "2", "--iterations", str(iterations), "--num-primitives", "150", "--backend", "cpu",
            "--checkpoint-every", "10"]
    proc = subprocess.Popen(args, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                            env={**os.environ, "PYTHONUNBUFFERED": "1", **env})
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


def test_a_stopped_rank_ends_the_run_within_the_heartbeat_timeout(tiny_data, tmp_path):
    """A rank stopped with SIGSTOP (alive, silent) used to keep the others waiting for gloo's 10-minute timeout;
    its missing heartbeat ends the run (here after 6 s) with the usual message, the last checkpoint kept."""
    run = tmp_path / "run"
    proc = _start(tiny_data, run, iterations=100000, SPLATZOO_RANK_TIMEOUT="6")
    ranks = []
    deadline = time.monotonic() + 60
    while len(ranks) < 2 and time.monotonic() < deadline:
        ranks = [p for p in _children(proc.pid) if "spawn_main" in Path(f"/proc/{p}/cmdline").read_text()]
        time.sleep(0.05)
    stopped = max(ranks)
    t0 = time.monotonic()
    os.kill(stopped, signal.SIGSTOP)
    try:
        output, _ = proc.communicate(timeout=120)
    finally:
        for pid in ranks:  # nothing left behind, stopped or not
            try:
                os.kill(pid, signal.SIGKILL)
            except ProcessLookupError:
                pass
    assert time.monotonic() - t0 < 60
    assert proc.returncode == 2 and "stopped responding" in output and "--resume" in output, output
    assert (run / "checkpoint.pt").exists()


def _listening_addresses(pids: set[int]) -> set[str]:
    """Local addresses (hex, as /proc/net/tcp writes them) of the listening TCP sockets that `pids` hold."""
    inodes = set()
    for pid in pids:
        try:
            for fd in os.listdir(f"/proc/{pid}/fd"):
                link = os.readlink(f"/proc/{pid}/fd/{fd}")
                if link.startswith("socket:["):
                    inodes.add(link[8:-1])
        except OSError:
            continue
    found = set()
    for table in ("/proc/net/tcp", "/proc/net/tcp6"):
        for line in Path(table).read_text().splitlines()[1:]:
            cols = line.split()
            if cols[3] == "0A" and cols[9] in inodes:  # LISTEN
                found.add(cols[1].rsplit(":", 1)[0])
    return found


@pytest.mark.skipif(not Path("/proc/net/tcp").exists(), reason="reads Linux's socket tables")
def test_a_one_machine_run_listens_on_loopback_only(tiny_data, tmp_path):
    """torch.distributed has no authentication: the ranks of `--nproc` meet through a file and listen on the
    loopback interface alone, never on an address other machines reach."""
    import threading

    seen: set[str] = set()
    done = threading.Event()

    def children() -> set[int]:
        me, out = os.getpid(), set()
        for entry in os.listdir("/proc"):
            if entry.isdigit():
                try:
                    if int(Path(f"/proc/{entry}/stat").read_text().rsplit(")", 1)[1].split()[1]) == me:
                        out.add(int(entry))
                except (OSError, IndexError, ValueError):
                    continue
        return out

    def watch():
        while not done.wait(0.05):
            seen.update(_listening_addresses(children()))

    watcher = threading.Thread(target=watch, daemon=True)
    watcher.start()
    try:
        train(tiny_data, "2dgs", {}, TrainConfig(**{**RUN, "iterations": 8}, nproc=2), tmp_path / "n2",
              progress=False, evaluate_at_end=False)
    finally:
        done.set()
        watcher.join()
    loopback = {"0100007F", "00000000000000000000000001000000"}  # 127.0.0.1, ::1
    assert seen, "the ranks should listen for each other (gloo)"
    assert seen <= loopback, f"ranks listened on {sorted(seen - loopback)}"
