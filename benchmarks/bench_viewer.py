"""Interactivity of `splatzoo view`: frames per second while orbiting and time to the full-size frame, measured end
to end through a headless Chromium (the page's camera messages, the server's renders, the images sent back).

    python benchmarks/bench_viewer.py [--surfels 20000] [--width 1280 --height 720] [--seconds 6]

Trains gabor (K=4) on the built-in sweater scene at 256 px with a fixed count of surfels (a short run: surfel sizes
and opacities of a trained model, not of an initial one), opens the viewer in Chromium at the given page size and
orbits the camera about the scene at 60 camera updates per second (a dragging mouse) for `--seconds` seconds (moving frames at the
viewer's default moving size, longer side 256 px). Then it stops and times the full-size frame. Also prints the
render time alone of one frame at both sizes, to show where the time goes.
"""
from __future__ import annotations

import argparse
import math
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--surfels", type=int, default=20000)
    ap.add_argument("--width", type=int, default=1280)
    ap.add_argument("--height", type=int, default=720)
    ap.add_argument("--seconds", type=float, default=6.0)
    ap.add_argument("--iterations", type=int, default=300)
    ap.add_argument("--backend", default="cpu")
    args = ap.parse_args(argv)

    from playwright.sync_api import sync_playwright

    from splatzoo.data.synthetic import make_synthetic_scene
    from splatzoo.runs import train
    from splatzoo.training import TrainConfig
    from splatzoo.viewer import SETTLE_SECONDS, browser_camera, fit_size, render_frame, view

    with tempfile.TemporaryDirectory() as tmp:
        data = make_synthetic_scene("sweater", Path(tmp) / "data", views=24, width=256, height=256)
        cfg = TrainConfig(iterations=args.iterations, num_primitives=args.surfels, densify=False, backend=args.backend)
        train(data, "gabor", {}, cfg, Path(tmp) / "run", progress=False, evaluate_at_end=False)
        viewer = view([Path(tmp) / "run"], port=0, backend=args.backend)
        model = viewer.sources[0].model()
        print(f"gabor K=4, {model.num_primitives} surfels, page {args.width}x{args.height}, backend {args.backend}")
        try:
            with sync_playwright() as p:
                browser = p.chromium.launch(executable_path=shutil.which("chromium"),
                                            args=["--use-angle=swiftshader", "--enable-unsafe-swiftshader"])
                page = browser.new_page(viewport={"width": args.width, "height": args.height})
                page.goto(viewer.url)
                while not viewer.sessions:
                    time.sleep(0.05)
                session = next(iter(viewer.sessions.values()))
                session.full_sent.wait(120)
                c = session.client.camera
                center = viewer.focus
                radius = float(np.linalg.norm(c.position - center))
                height = float((c.position - center)[1])
                start_moving = dict(session.frames)
                t0 = time.monotonic()
                steps = 0
                while time.monotonic() - t0 < args.seconds:  # orbit about the focus, 60 camera updates a second
                    a = 2 * math.pi * (time.monotonic() - t0) / args.seconds
                    r = math.sqrt(max(radius ** 2 - height ** 2, 1e-6))
                    c.position = center + np.array([r * math.sin(a), height, -r * math.cos(a)])
                    c.look_at = center
                    steps += 1
                    time.sleep(1 / 60)
                orbit = time.monotonic() - t0
                moving_frames = session.frames["moving"] - start_moving["moving"]
                session.full_sent.clear()
                stopped = time.monotonic()
                session.full_sent.wait(120)
                to_full = time.monotonic() - stopped
                full_cam, _ = session.last_full
                browser.close()
        finally:
            viewer.stop()
        small = browser_camera(c.wxyz, c.position, c.fov, *fit_size(full_cam.width, full_cam.height, 256))
        timings = {}
        for name, cam in (("moving", small), ("full", full_cam)):
            render_frame(model, cam, "rgb", backend=args.backend)
            t = time.perf_counter()
            for _ in range(3):
                render_frame(model, cam, "rgb", backend=args.backend)
            timings[name] = (time.perf_counter() - t) / 3
        print("| measure | value |")
        print("|---|---|")
        print(f"| frames per second while orbiting ({small.width}x{small.height}) | {moving_frames / orbit:.1f} |")
        print(f"| camera updates sent per second | {steps / orbit:.1f} |")
        print(f"| time from the camera stopping to the full-size frame ({full_cam.width}x{full_cam.height}) | "
              f"{to_full:.2f} s (of which {SETTLE_SECONDS:.2f} s waiting for the camera to settle) |")
        print(f"| render alone, {small.width}x{small.height} | {1000 * timings['moving']:.0f} ms |")
        print(f"| render alone, {full_cam.width}x{full_cam.height} | {1000 * timings['full']:.0f} ms |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
