"""Every member of the zoo trained on real photos (instant-ngp's fox, prepared by scripts/gpu-prepare.sh), one after
the other in one process, each scored on the test views: PSNR, SSIM, LPIPS, iterations per second, peak GPU memory
and frames per second, image-only, at the test views' size and at 1080 lines.

    python benchmarks/bench_fox.py run DATA [--members 2dgs,beta,textured,neural-gabor,gabor] [--iterations 1000]
        [--backend auto] [--work DIR] [--json FILE] [--renders DIR] [--deadline UNIX_SECONDS | --time-left S]
        [--lpips-net auto] [--resolution N] [--fps-height 1080]
    python benchmarks/bench_fox.py score DATA RENDERS [--json FILE] [--lpips-net vgg]

`run`: each member trains with splatzoo's defaults (densification on, the 30k schedule scaled to --iterations) on
DATA's training views; "train s" is the training loop alone (the run's train_seconds; a test PSNR at the end of the
loop included), "wall s" the whole member (set-up, training, checkpoints, scoring, FPS). LPIPS: --lpips-net auto
takes VGG (the project's tables) when its weights are installed, else AlexNet (what gsplat's trainer reports; the GPU
check carries only AlexNet's 10 MB), else none; the JSON names the one used. With --renders, each test view's render
is written as PNG (RENDERS/MEMBER/NAME.png) so that `score` can add VGG LPIPS on another machine. The JSON is
rewritten after every member, so a run cut short keeps what it finished. Time limit: with --deadline (or
--time-left), a member whose estimated cost (the first: --first-estimate-s; later ones: the time per iteration
measured so far times the member's relative cost, RELATIVE_COST) does not fit before the deadline is skipped and
reported as "skipped: out of time".

`score`: the PNG renders of `run --renders` against DATA's test views (8-bit renders: PSNR within about 0.01 dB of
the float one), with --lpips-net (default vgg), on the CPU.
"""
from __future__ import annotations

import argparse
import json
import math
import statistics
import sys
import time
from pathlib import Path

import torch

MEMBERS = ("2dgs", "beta", "textured", "neural-gabor", "gabor")  # the baseline, then the kinds new to a GPU
# training time per iteration relative to 2dgs (README / BENCHMARKS.md at equal count; an estimate for the deadline)
RELATIVE_COST = {"2dgs": 1.0, "beta": 1.1, "gabor": 1.4, "textured": 2.0, "neural-gabor": 1.7}


def lpips_net_available(choice: str) -> str | None:
    """The LPIPS network to use: `choice` itself (an error when its weights are missing) or, for "auto", vgg, else
    alex, else None."""
    from splatzoo.errors import SplatzooError
    from splatzoo.metrics import lpips

    probe = torch.rand(32, 32, 3, generator=torch.Generator().manual_seed(0))
    for net in (("vgg", "alex") if choice == "auto" else (choice,)):
        try:
            lpips(probe, probe, net=net)
            return net
        except SplatzooError:
            if choice != "auto":
                raise
    return None


def _write_json(path: Path, data: dict) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(path.suffix + ".tmp")
    tmp.write_text(json.dumps(data, indent=1, default=str))
    tmp.replace(path)


def _finite_mean(values):
    good = [v for v in values if v is not None and math.isfinite(v)]
    return statistics.fmean(good) if good else None


@torch.no_grad()
def score_views(model, scene, backend: str, lpips_net: str | None, renders: Path | None) -> dict:
    """Mean PSNR, SSIM and LPIPS of `model` over the test views (train views when there are none), optionally
    writing each render as PNG into `renders`."""
    from splatzoo.evaluate import write_png
    from splatzoo.metrics import lpips, psnr, ssim

    views = scene.test or scene.train
    device = next(model.parameters()).device  # the metrics run there too (LPIPS on a GPU: milliseconds)
    ps, ss, ls = [], [], []
    for v in views:
        pred = model.render(v.camera, background=scene.background, backend=backend, image_only=True).image()
        gt = v.image_float()
        ps.append(psnr(pred, gt))
        ss.append(ssim(pred.to(device), gt.to(device)))
        if lpips_net is not None and min(gt.shape[:2]) >= 32:
            ls.append(lpips(pred.to(device), gt.to(device), net=lpips_net))
        if renders is not None:
            write_png(renders / (Path(v.name).stem + ".png"), pred)
    return {"psnr": _finite_mean(ps), "ssim": _finite_mean(ss), "lpips": _finite_mean(ls) if ls else None,
            "lpips_net": lpips_net if ls else None, "views": len(views)}


def train_member(scene, member: str, args, backend: str, lpips_net: str | None) -> dict:
    from splatzoo.evaluate import fps_report
    from splatzoo.io import read_torch
    from splatzoo.runs import train
    from splatzoo.training import TrainConfig

    cuda = backend == "cuda"
    if cuda:
        torch.cuda.synchronize()
        torch.cuda.reset_peak_memory_stats()
    t0 = time.perf_counter()
    cfg = TrainConfig(iterations=args.iterations, backend=backend, seed=args.seed, eval_every=args.iterations,
                      **({"max_primitives": args.max_primitives} if args.max_primitives else {}))
    result = train(scene, member, {}, cfg, args.work / member, progress=False, evaluate_at_end=False,
                   overwrite=True)
    train_wall = time.perf_counter() - t0
    checkpoint = read_torch(result.run_dir / "checkpoint.pt", "checkpoint", "train again")
    train_s = float(checkpoint.get("train_seconds") or train_wall)
    row = {"member": member, "iterations": args.iterations, "train_s": round(train_s, 2),
           "it_per_s": round(args.iterations / train_s, 2), "primitives": result.model.num_primitives,
           "size_mb": round(result.model.size_bytes() / 1e6, 3),
           "peak_train_gib": round(torch.cuda.max_memory_allocated() / 2**30, 3) if cuda else None}
    model = result.model.eval()
    renders = args.renders / member if args.renders is not None else None
    row.update(score_views(model, scene, backend, lpips_net, renders))
    cams = [v.camera for v in (scene.test or scene.train)]
    for fps in fps_report(model, cams, scene.background, backend, height=args.fps_height, min_frames=args.fps_frames):
        key = "own" if fps["label"] == "own size" else "lines"
        row[f"fps_image_{key}"] = round(fps["fps_image"], 2)
        row[f"fps_full_{key}"] = round(fps["fps_full"], 2)
        row[f"fps_size_{key}"] = fps["size"]
    row["peak_gib"] = round(torch.cuda.max_memory_allocated() / 2**30, 3) if cuda else None
    row["wall_s"] = round(time.perf_counter() - t0, 2)
    del checkpoint
    return row


def estimate_s(member: str, iterations: int, done: list[dict], first_estimate_s: float) -> float:
    """Expected seconds for `member`: from the members measured so far (time per iteration per unit of relative
    cost, and the fixed cost of scoring), else first_estimate_s scaled by the member's relative cost."""
    cost = RELATIVE_COST.get(member, 1.5)
    measured = [r for r in done if "train_s" in r]
    if not measured:
        return first_estimate_s * cost
    per_it = statistics.fmean(r["train_s"] / (r["iterations"] * RELATIVE_COST.get(r["member"], 1.5))
                              for r in measured)
    fixed = statistics.fmean(r["wall_s"] - r["train_s"] for r in measured)
    return per_it * iterations * cost + fixed


def machine() -> dict:
    info = {"torch": torch.__version__, "python": sys.version.split()[0], "cpu_threads": torch.get_num_threads()}
    if torch.cuda.is_available():
        info.update(gpu=torch.cuda.get_device_name(), cuda=torch.version.cuda)
    return info


def run(args) -> int:
    from splatzoo.data import load_scene
    from splatzoo.rasterizers import resolve_backend

    members = [m for m in args.members.split(",") if m]
    from splatzoo.zoo import list_models

    unknown = [m for m in members if m not in list_models()]
    if unknown:
        raise SystemExit(f"unknown member(s) {', '.join(unknown)}; the zoo has {', '.join(list_models())}")
    deadline = args.deadline if args.deadline is not None else (
        time.time() + args.time_left if args.time_left is not None else None)
    if args.backend == "cuda" and not torch.cuda.is_available():
        raise SystemExit(f"--backend cuda, but torch {torch.__version__} sees no CUDA device here; use --backend cpu "
                         "(or auto) for a run on the CPU")
    gpu = torch.cuda.is_available() and args.backend in ("auto", "cuda")
    backend = resolve_backend(args.backend, torch.device("cuda" if gpu else "cpu"))
    t0 = time.perf_counter()
    scene = load_scene(args.data, resolution=args.resolution)
    load_s = time.perf_counter() - t0
    lpips_net = lpips_net_available(args.lpips_net)
    cam = scene.train[0].camera
    report = {"machine": machine(), "backend": backend, "data": str(args.data), "size": f"{cam.width}x{cam.height}",
              "train_views": len(scene.train), "test_views": len(scene.test), "points": int(scene.points.shape[0]),
              "background": list(scene.background), "iterations": args.iterations, "lpips_net": lpips_net,
              "load_s": round(load_s, 2), "date": time.strftime("%Y-%m-%d %H:%M"),
              "schedule": f"splatzoo defaults, densification on, the 30k schedule scaled to {args.iterations} "
                          "iterations", "members": []}
    print(f"# {report['machine']}; backend {backend}; {args.data}: {len(scene.train)} train / {len(scene.test)} test "
          f"views at {cam.width}x{cam.height}, {scene.points.shape[0]} points; {args.iterations} iterations; LPIPS "
          f"{lpips_net or 'none (no weights)'}", flush=True)
    header = (f"{'member':<14}{'train s':>8}{'it/s':>8}{'PSNR':>8}{'SSIM':>8}{'LPIPS':>8}{'surfels':>9}{'peak GiB':>9}"
              f"{'FPS own':>9}{'FPS ' + str(args.fps_height):>10}")
    print(header, flush=True)
    for member in members:
        if deadline is not None:
            need = estimate_s(member, args.iterations, report["members"], args.first_estimate_s)
            left = deadline - time.time()
            if need > left:
                report["members"].append({"member": member, "skipped": f"out of time: needs ~{need:.0f} s, "
                                                                       f"{max(left, 0):.0f} s left"})
                print(f"{member:<14}skipped: out of time (needs ~{need:.0f} s, {max(left, 0):.0f} s left)", flush=True)
                _write_json(args.json, report)
                continue
        try:
            row = train_member(scene, member, args, backend, lpips_net)
        except Exception as e:  # one member failing must not cost the others their measurement
            row = {"member": member, "error": f"{type(e).__name__}: {str(e)[:600]}"}
            print(f"{member:<14}FAILED: {row['error']}", flush=True)
            if backend == "cuda":
                torch.cuda.empty_cache()
        else:
            def f(key, fmt):
                v = row.get(key)
                return "-" if v is None else format(v, fmt)
            print(f"{member:<14}{f('train_s', '.1f'):>8}{f('it_per_s', '.1f'):>8}{f('psnr', '.2f'):>8}"
                  f"{f('ssim', '.4f'):>8}{f('lpips', '.4f'):>8}{f('primitives', 'd'):>9}{f('peak_gib', '.2f'):>9}"
                  f"{f('fps_image_own', '.1f'):>9}{f('fps_image_lines', '.1f'):>10}", flush=True)
        report["members"].append(row)
        _write_json(args.json, report)
    print(f"# wrote {args.json}", flush=True)
    failed = [r["member"] for r in report["members"] if "error" in r]
    return 1 if failed else 0


def score(args) -> int:
    """VGG (or --lpips-net) LPIPS, PSNR and SSIM of the PNG renders of `run --renders`, on this machine."""
    import numpy as np
    from PIL import Image

    from splatzoo.data import load_scene
    from splatzoo.metrics import lpips, psnr, ssim

    scene = load_scene(args.data, resolution=args.resolution)
    views = scene.test or scene.train
    out = {"data": str(args.data), "renders": str(args.renders), "lpips_net": args.lpips_net,
           "note": "8-bit PNG renders against the test views", "members": {}}
    members = sorted(p for p in args.renders.iterdir() if p.is_dir())
    if not members:
        raise SystemExit(f"{args.renders} holds no member folders (RENDERS/MEMBER/NAME.png)")
    for folder in members:
        ps, ss, ls, missing = [], [], [], []
        for v in views:
            path = folder / (Path(v.name).stem + ".png")
            if not path.is_file():
                missing.append(path.name)
                continue
            pred = torch.from_numpy(np.asarray(Image.open(path).convert("RGB"), dtype=np.float32) / 255.0)
            gt = v.image_float()
            ps.append(psnr(pred, gt))
            ss.append(ssim(pred, gt))
            ls.append(lpips(pred, gt, net=args.lpips_net))
        row = {"psnr": _finite_mean(ps), "ssim": _finite_mean(ss), "lpips": _finite_mean(ls), "views": len(ps)}
        if missing:
            row["missing"] = missing
        out["members"][folder.name] = row
        print(f"{folder.name:<14} PSNR {row['psnr']:.2f}  SSIM {row['ssim']:.4f}  LPIPS({args.lpips_net}) "
              f"{row['lpips']:.4f}  ({len(ps)} views{', missing ' + str(len(missing)) if missing else ''})", flush=True)
    if args.json is not None:
        _write_json(args.json, out)
    return 0


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    r = sub.add_parser("run", help="train and score every member")
    r.add_argument("data", type=Path)
    r.add_argument("--members", default=",".join(MEMBERS))
    r.add_argument("--iterations", type=int, default=1000)
    r.add_argument("--backend", default="auto", help="auto, cuda or cpu")
    r.add_argument("--seed", type=int, default=0)
    r.add_argument("--resolution", type=int, default=None, help="load DATA downscaled by this factor (1, 2, 4, 8)")
    r.add_argument("--max-primitives", type=int, default=None, help="cap on densification (default: splatzoo's)")
    r.add_argument("--work", type=Path, default=Path("benchmarks/results/fox"), help="the run folders")
    r.add_argument("--json", type=Path, default=None, help="default: WORK/fox.json")
    r.add_argument("--renders", type=Path, default=None, help="write the test renders here (MEMBER/NAME.png)")
    r.add_argument("--lpips-net", default="auto", choices=("auto", "vgg", "alex"))
    r.add_argument("--fps-height", type=int, default=1080, help="FPS also at this many lines (aspect kept)")
    r.add_argument("--fps-frames", type=int, default=10, help="frames per FPS measurement (at least)")
    group = r.add_mutually_exclusive_group()
    group.add_argument("--deadline", type=float, default=None, help="unix time by which to stop starting members")
    group.add_argument("--time-left", type=float, default=None, help="seconds from now: the same as --deadline")
    r.add_argument("--first-estimate-s", type=float, default=60.0,
                   help="expected seconds of a 2dgs member, before any member was measured")
    s = sub.add_parser("score", help="LPIPS (VGG), PSNR and SSIM of the renders a run wrote")
    s.add_argument("data", type=Path)
    s.add_argument("renders", type=Path)
    s.add_argument("--resolution", type=int, default=None, help="as the run loaded DATA")
    s.add_argument("--json", type=Path, default=None)
    s.add_argument("--lpips-net", default="vgg", choices=("vgg", "alex"))
    args = ap.parse_args(argv)
    if args.cmd == "score":
        return score(args)
    if args.iterations < 1:
        ap.error("--iterations must be at least 1")
    args.json = args.json or args.work / "fox.json"
    return run(args)


if __name__ == "__main__":
    sys.exit(main())
