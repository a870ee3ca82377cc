"""SfM wall time against frame count, exhaustive against sequential matching, on frames of a smooth camera path.

    OMP_WAIT_POLICY=PASSIVE python benchmarks/bench_sfm.py [--frames 25,50,100] [--matching exhaustive,sequential]
        [--size 640x480] [--scene boots] [--work /tmp/bench-sfm] [--max-exhaustive 100] [--threads -1]

Each frame count renders the synthetic scene along one closed orbit (`splatzoo.data.video.orbit_cameras`: azimuth in
even steps through one turn, elevation swinging once between 22 and 42 degrees), frame_00001.png ... in order, as
the frames of a video walking around the object would be; the renders are kept in --work and reused. Then
`run_sfm(frames, matching=M)` for each strategy (exhaustive is skipped above --max-exhaustive frames: its pairs grow
as n^2). One row per run: wall time (and its extraction / matching / mapping parts), pairs matched, frames
registered, the focal length found against the true one, and the largest camera-centre error after a similarity
alignment to the true orbit, as a fraction of the orbit's radius. Rows are also appended as JSON to
--work/results.jsonl.
"""
from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np


def render(scene: str, frames: int, width: int, height: int, work: Path) -> tuple[Path, list]:
    from PIL import Image

    from splatzoo.data.video import orbit_cameras, orbit_frames

    folder = work / f"{scene}-{frames}-{width}x{height}" / "images"
    cams = orbit_cameras(scene, frames, width, height)
    if folder.is_dir() and len(list(folder.glob("*.png"))) == frames:
        return folder, cams
    folder.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    for cam, rgb in orbit_frames(scene, frames, width, height):
        Image.fromarray(rgb).save(folder / cam.name)
    print(f"rendered {frames} frames of {scene} at {width}x{height} in {time.perf_counter() - t0:.0f} s",
          file=sys.stderr, flush=True)
    return folder, cams


def run(images: Path, cams, matching: str, out: Path, threads: int) -> dict:
    from splatzoo.data.sfm import run_sfm, similarity_align

    t0 = time.perf_counter()
    res = run_sfm(images, out, matching=matching, overwrite=True, num_threads=threads,
                  progress=lambda m: print("    " + m, file=sys.stderr, flush=True) if "[" in m else None)
    wall = time.perf_counter() - t0
    truth = {c.name: c for c in cams}
    rec = res.reconstruction
    reg = [im for im in rec.images.values() if im.has_pose]
    est = np.array([im.projection_center() for im in reg])
    true = np.array([truth[im.name].center.double().numpy() for im in reg])
    s, R, t = similarity_align(est, true)
    err = np.linalg.norm(s * est @ R.T + t - true, axis=1)
    centres = np.array([c.center.double().numpy() for c in cams])
    radius = float(np.linalg.norm(centres - centres.mean(0), axis=1).max())
    f_true = float(cams[0].K[0, 0])
    f_found = float(np.mean([c.mean_focal_length() for c in rec.cameras.values()]))
    return {"frames": len(cams), "matching": res.matching, "pairs": res.num_pairs, "registered": res.num_registered,
            "wall_s": round(wall, 1), **{f"{k}_s": round(v, 1) for k, v in res.stage_seconds.items()},
            "focal_true": round(f_true, 1), "focal_found": round(f_found, 1),
            "focal_error_pct": round(100 * abs(f_found - f_true) / f_true, 2),
            "centre_error_max_pct": round(100 * float(err.max()) / radius, 3),
            "points": res.num_points, "reprojection_px": round(res.mean_reprojection_error, 3)}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", default="25,50,100")
    ap.add_argument("--matching", default="exhaustive,sequential")
    ap.add_argument("--size", default="640x480")
    ap.add_argument("--scene", default="boots")
    ap.add_argument("--work", default="/tmp/bench-sfm")
    ap.add_argument("--max-exhaustive", type=int, default=100)
    ap.add_argument("--threads", type=int, default=-1)
    args = ap.parse_args(argv)
    width, height = (int(v) for v in args.size.lower().split("x"))
    work = Path(args.work)
    work.mkdir(parents=True, exist_ok=True)
    print(f"# {datetime.date.today()} {platform.node()} {os.cpu_count()} cores, {args.scene} {width}x{height}, "
          f"threads {args.threads}; load average before: {os.getloadavg()[0]:.2f}")
    print("| frames | matching | pairs | registered | wall | extract / match / map | focal found (true) | "
          "focal error | centre error (of radius) |")
    print("|---|---|---|---|---|---|---|---|---|")
    for n in [int(v) for v in args.frames.split(",")]:
        images, cams = render(args.scene, n, width, height, work)
        for matching in args.matching.split(","):
            if matching == "exhaustive" and n > args.max_exhaustive:
                print(f"| {n} | exhaustive | {n * (n - 1) // 2} | skipped (over --max-exhaustive) | | | | | |",
                      flush=True)
                continue
            r = run(images, cams, matching, work / f"out-{n}-{matching}", args.threads)
            r.update(scene=args.scene, size=f"{width}x{height}", date=str(datetime.date.today()),
                     load_after=round(os.getloadavg()[0], 2))
            with open(work / "results.jsonl", "a") as fh:
                fh.write(json.dumps(r) + "\n")
            print(f"| {n} | {r['matching']} | {r['pairs']} | {r['registered']}/{n} | {r['wall_s']:.0f} s | "
                  f"{r['extract_s']:.0f} / {r['match_s']:.0f} / {r['map_s']:.0f} s | {r['focal_found']:.1f} "
                  f"({r['focal_true']:.1f}) | {r['focal_error_pct']:.2f}% | {r['centre_error_max_pct']:.2f}% |",
                  flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
