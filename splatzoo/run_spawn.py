"""--nproc: a run's ranks spawned on this machine (torch.distributed over a file rendezvous and the loopback
interface), each beating a heartbeat; a rank that stops beating, fails or dies ends the run with a clear error.
"""
from __future__ import annotations

import dataclasses
import os
import shutil
import signal
import sys
import threading
import time
from pathlib import Path

import torch

from .errors import SplatzooError
from .run_folder import Run, TrainingInterrupted, TrainResult
from .training import TrainConfig

def spawn_ranks(run: Run, scene, model: str, model_config, cfg: TrainConfig, resume: bool, *, loop, progress: bool,
                evaluate_at_end: bool, stop_after: int | None, lpips_net: str) -> TrainResult:
    """Train on cfg.nproc processes (torch.distributed: gloo on CPU, NCCL on CUDA) while this process holds the
    run's lock: each rank runs `loop` (the training loop of splatzoo.run_launch, a module-level function: it
    travels to the ranks by name). Ctrl-C reaches every rank from the terminal; SIGTERM to this process is passed on.
    A rank that fails or dies ends the run with a clear error; the last checkpoint stays."""
    import tempfile

    import torch.multiprocessing as mp

    # The ranks meet through a file (no listening store socket) and talk over the loopback interface only:
    # torch.distributed has no authentication, so nothing of a one-machine run may listen on the network.
    rendezvous = Path(tempfile.mkdtemp(prefix="splatzoo-ranks-")) / "store"
    # each rank's heartbeat (a thread beating even while the rank computes or waits in a collective): a rank that
    # stops beating was stopped (SIGSTOP) or hangs, and the others would wait for it until gloo's 10-minute timeout
    beats = mp.get_context("spawn").Array("d", cfg.nproc, lock=False)
    ctx = mp.start_processes(_rank_main, nprocs=cfg.nproc, join=False, start_method="spawn",
                             args=(cfg.nproc, str(rendezvous), beats, loop, str(run.path), scene, model,
                                   dataclasses.asdict(model_config), dataclasses.asdict(cfg), resume, progress,
                                   evaluate_at_end, stop_after, lpips_net))
    pids = [p.pid for p in ctx.processes]
    silent_after = float(os.environ.get("SPLATZOO_RANK_TIMEOUT", RANK_TIMEOUT_S))
    started = time.time()

    def forward(signum, frame):
        for pid in pids:
            try:
                os.kill(pid, signum)
            except ProcessLookupError:
                pass

    previous = {s: signal.signal(s, forward if s == signal.SIGTERM else signal.SIG_IGN)
                for s in (signal.SIGINT, signal.SIGTERM)} if threading.current_thread() is threading.main_thread() else {}
    try:
        while not ctx.join(timeout=1.0):
            now = time.time()
            for rank, beat in enumerate(beats[:]):
                if now - (beat or started) > silent_after:  # no beat yet: counted from the spawn
                    for pid in pids:
                        try:
                            os.kill(pid, signal.SIGKILL)
                        except ProcessLookupError:
                            pass
                    raise SplatzooError(f"rank {rank} of {cfg.nproc} stopped responding (no heartbeat for "
                                        f"{silent_after:.0f} s: stopped, or hung); the run was ended "
                                        f"({_what_is_kept(run)})")
    except mp.ProcessExitedException as e:
        code = e.exit_code
        if code in (130, 143):
            name = "SIGINT" if code == 130 else "SIGTERM"
            raise TrainingInterrupted(f"training stopped by {name}; checkpoint written. Resume with: splatzoo "
                                      f"train --resume --out {run.path}", code) from None
        how = f"was killed by {signal.Signals(-code).name}" if code < 0 else f"exited with code {code}"
        raise SplatzooError(f"rank {e.error_index} of {cfg.nproc} {how}; the run stopped "
                            f"({_what_is_kept(run)})") from None
    except mp.ProcessRaisedException as e:
        last = str(e).strip().splitlines()[-1]
        raise SplatzooError(f"rank {e.error_index} of {cfg.nproc} failed: {last} ({_what_is_kept(run)})") from None
    finally:
        for s, h in previous.items():
            signal.signal(s, h)
        shutil.rmtree(rendezvous.parent, ignore_errors=True)
    from .zoo import load_model

    return TrainResult(run.path, load_model(run.model_path) if run.model_path.exists() else None,
                       run.metrics() or {})


def _what_is_kept(run: Run) -> str:
    if run.checkpoint_path.exists():
        return f"its last checkpoint is kept; resume with: splatzoo train --resume --out {run.path}"
    return "it stopped before its first checkpoint"


def loopback_interface() -> str | None:
    """The name of the loopback network interface ("lo" on Linux, "lo0" on macOS), None if there is none."""
    import socket as socket_module

    try:
        return next((name for _, name in socket_module.if_nameindex() if name.startswith("lo")), None)
    except OSError:
        return None


RANK_TIMEOUT_S = 60.0  # a rank whose heartbeat is older than this ends an --nproc run ($SPLATZOO_RANK_TIMEOUT)
HEARTBEAT_S = 2.0


def _beat(beats, rank: int) -> None:
    """Write this rank's heartbeat every HEARTBEAT_S seconds, from a daemon thread: it keeps beating while the rank
    computes or waits for the others, and stops only when the whole process is stopped or gone."""
    def run():
        while True:
            beats[rank] = time.time()
            time.sleep(HEARTBEAT_S)

    threading.Thread(target=run, name="splatzoo-heartbeat", daemon=True).start()


def _rank_main(rank: int, world: int, rendezvous: str, beats, loop, run_path: str, scene, model: str,
               model_config: dict, cfg: dict, resume: bool, progress: bool, evaluate_at_end: bool,
               stop_after: int | None, lpips_net: str) -> None:
    """One rank of `spawn_ranks`: join the process group, train with `loop`, and exit with the shell's code for how
    it ended."""
    from datetime import timedelta

    import torch.distributed as dist

    from .zoo import make_config

    _beat(beats, rank)

    cfg = TrainConfig(**cfg)
    cuda = cfg.backend == "cuda" or (cfg.backend == "auto" and torch.cuda.is_available())
    if cuda:
        torch.cuda.set_device(rank % torch.cuda.device_count())
    else:  # the ranks share the cores
        torch.set_num_threads(max(1, (os.cpu_count() or 1) // world))
    lo = loopback_interface()
    if lo is not None:  # gloo and NCCL bind their connections to this interface (unless the user chose one)
        os.environ.setdefault("GLOO_SOCKET_IFNAME", lo)
        os.environ.setdefault("NCCL_SOCKET_IFNAME", lo)
    dist.init_process_group("nccl" if cuda else "gloo", init_method=f"file://{rendezvous}", rank=rank,
                            world_size=world, timeout=timedelta(minutes=10))
    code = 0
    try:
        run = Run(run_path)
        loop(run, scene, model, make_config(model, **model_config), cfg, run.checkpoint() if resume else None,
             progress=progress, evaluate_at_end=evaluate_at_end, stop_after=stop_after, lpips_net=lpips_net,
             distributed=True)
    except TrainingInterrupted as e:
        if rank == 0:
            print(e, file=sys.stderr, flush=True)
        code = e.exit_code
    except SplatzooError as e:
        print(f"error (rank {rank}): {e}", file=sys.stderr, flush=True)
        code = 2
    finally:
        leave_process_group(dist)
    if code:
        sys.exit(code)


def leave_process_group(dist) -> None:
    """Every rank waits for the others before tearing the group down: a rank that destroyed it (rank 0 with it the
    rendezvous store) while another still used it aborted that rank now and then (gloo: std::terminate)."""
    from datetime import timedelta

    try:
        if dist.get_backend() == "gloo":
            dist.monitored_barrier(timeout=timedelta(seconds=60))
        else:
            dist.barrier()
    except Exception:  # a rank that is gone already: nothing to wait for
        pass
    dist.destroy_process_group()


