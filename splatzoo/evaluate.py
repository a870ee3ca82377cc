"""Evaluation of a trained model: image metrics on the test views, render speed, size; renders and videos.
(Runs on disk are loaded and evaluated through splatzoo.runs.)"""
from __future__ import annotations

import math
import time
from pathlib import Path

import numpy as np
import torch

from .errors import SplatzooError
from .io import atomic_path
from .rasterizers import resolve_backend
from .types import Camera

LPIPS_NET = "vgg"
LPIPS_CONVENTION = "3dgs"  # the 2DGS/3DGS metrics script (and the paper's tables) feed [0,1] images to VGG


def checked_lpips_net(net: str | None) -> str:
    """The LPIPS network a command scores with (None: LPIPS_NET), refused before any training if unknown."""
    from .metrics import check_lpips_net

    net = LPIPS_NET if net is None else net
    check_lpips_net(net)
    return net


def lpips_net_of(metrics: dict) -> str | None:
    """The LPIPS network a metrics.json was scored with (its conventions' 'v0.1 NET, ...'), None if it does not say."""
    told = str((metrics.get("conventions") or {}).get("lpips", "")).split(",")[0].split()
    return told[1] if len(told) == 2 and told[0] == "v0.1" else None


def _device(model) -> torch.device:
    return next(model.parameters()).device


@torch.no_grad()
def measure_fps(model, cameras: list[Camera], background, backend: str, min_frames: int = 10, *,
                image_only: bool = True) -> float:
    """Frames per second of image-only renders (rgb and alpha, what a viewer shows; image_only=False: every output,
    as training's forward) over the cameras (cycled to at least min_frames), after one warm-up pass."""
    if not cameras:
        return float("nan")
    device = _device(model)
    cams = [c.to(device, torch.float32) for c in cameras]
    bg = torch.tensor(background, dtype=torch.float32, device=device)
    for c in cams[:2]:
        model.render(c, background=bg, backend=backend, image_only=image_only)
    frames = max(min_frames, len(cams))
    sync = torch.cuda.synchronize if device.type == "cuda" else (lambda: None)
    sync()
    t0 = time.perf_counter()
    for i in range(frames):
        model.render(cams[i % len(cams)], background=bg, backend=backend, image_only=image_only)
    sync()
    return frames / (time.perf_counter() - t0)


def fps_report(model, cameras: list[Camera], background, backend: str, *, height: int = 1080,
               min_frames: int = 10) -> list[dict]:
    """A trained model's frame rate at its cameras' size and at `height` lines (the cameras scaled, aspect kept):
    image-only renders (what a viewer shows) and full renders (every output, as training's forward), one row each."""
    rows = []
    for label, cams in (("own size", cameras), (f"{height} lines", [c.scaled(height / c.height) for c in cameras])):
        if not cams:
            continue
        row = {"size": f"{cams[0].width}x{cams[0].height}", "label": label}
        for key, image_only in (("fps_image", True), ("fps_full", False)):
            row[key] = measure_fps(model, cams, background, backend, min_frames, image_only=image_only)
        rows.append(row)
    return rows


OBJECT_MASK = 0.99  # mask values from here up are the object's interior (edges are partly backdrop)


@torch.no_grad()
def evaluate(model, scene, *, backend: str = "auto", train_seconds: float | None = None,
             iterations: int | None = None, lpips_net: str = LPIPS_NET, lpips_convention: str = LPIPS_CONVENTION,
             split: str = "test") -> dict:
    """metrics.json content: psnr, ssim, lpips (means over the split's views), fps, train_seconds,
    num_primitives, size_bytes (its parameters as float32), stored_bytes and precision (the size of its packed file
    at its precision), iterations, model, backend, and the metric conventions used; object_alpha, the mean rendered
    alpha over the pixels inside the views' masks (None without masks): how opaque the object's surfaces are, which a
    viewer with another background shows."""
    from .metrics import lpips, psnr, ssim
    from .zoo import stored_bytes

    backend = resolve_backend(backend, _device(model))
    views = scene.test if split == "test" and scene.test else scene.train
    used = "test" if views is scene.test else "train"
    ps, ss, ls = [], [], []
    covered, inside = 0.0, 0  # rendered alpha summed over the object's pixels, where the views have masks
    for v in views:
        out = model.render(v.camera, background=scene.background, backend=backend, image_only=True)
        pred, gt = out.image(), v.image_float()
        mask = v.mask() if v.use_mask else None
        if mask is not None:
            on = mask >= OBJECT_MASK
            covered += float(out.alpha.detach().cpu()[on].double().sum())
            inside += int(on.sum())
        ps.append(psnr(pred, gt))
        ss.append(ssim(pred, gt))
        ls.append(lpips(pred, gt, net=lpips_net, convention=lpips_convention) if min(gt.shape[:2]) >= 32 else float("nan"))
    finite = [p for p in ps if math.isfinite(p)]
    return {
        "psnr": float(np.mean(finite)) if finite else float("inf"),
        "ssim": float(np.mean(ss)), "lpips": float(np.mean(ls)),
        "fps": measure_fps(model, [v.camera for v in views], scene.background, backend),
        "train_seconds": train_seconds, "num_primitives": model.num_primitives, "size_bytes": model.size_bytes(),
        "stored_bytes": stored_bytes(model), "precision": model.precision,
        "iterations": iterations, "model": model.name, "backend": backend, "split": used, "views": len(views),
        "object_alpha": covered / inside if inside else None,
        **(model.summary() if hasattr(model, "summary") else {}),
        "resolution": [views[0].camera.width, views[0].camera.height] if views else None,
        "conventions": {"psnr": "mean of per-image PSNR", "ssim": "3DGS: 11x11 Gaussian, sigma 1.5, zero padding",
                        "lpips": f"v0.1 {lpips_net}, {lpips_convention} input convention"},
    }


def parse_scales(text: str) -> list[float]:
    """'0.5,0.25' -> [0.5, 0.25]: render scales below 1 (`splatzoo eval --scale`)."""
    try:
        scales = [float(x) for x in text.split(",") if x.strip()]
    except ValueError:
        raise SplatzooError(f"--scale takes numbers separated by commas, such as 0.5,0.25; got {text!r}") from None
    bad = [s for s in scales if not (0 < s < 1)]
    if not scales or bad:
        raise SplatzooError(f"--scale: each scale must be between 0 and 1 (a render smaller than the test images), "
                            f"got {text!r}")
    return scales


def area_resize(img: torch.Tensor, width: int, height: int) -> torch.Tensor:
    """float [H,W,C] averaged over the area each output pixel covers (exact box means for integer factors)."""
    import cv2

    out = cv2.resize(img.numpy().astype(np.float32), (width, height), interpolation=cv2.INTER_AREA)
    return torch.from_numpy(out.reshape(height, width, -1))


@torch.no_grad()
def evaluate_scales(model, scene, scales, *, backend: str = "auto", lpips_net: str = LPIPS_NET,
                    lpips_convention: str = LPIPS_CONVENTION) -> dict:
    """Quality when rendered smaller than the test images: per scale, PSNR/SSIM/LPIPS of the small render against
    the area-averaged ground truth, and "consistency": PSNR of the small render against the area average of the
    model's own full-size render (an alias-free renderer scores high; a point-sampled one is dark and noisy)."""
    from .metrics import lpips, psnr, ssim

    backend = resolve_backend(backend, _device(model))
    views = scene.test or scene.train
    scores = {scale: {"psnr": [], "ssim": [], "lpips": [], "consistency_psnr": []} for scale in scales}
    sizes = {}
    for v in views:  # each view's image and full-size render once, for every scale
        image, full = v.image_float(), model.render(v.camera, background=scene.background, backend=backend, image_only=True).image()
        for scale in scales:
            cam = v.camera.scaled(scale)
            sizes[scale] = [cam.width, cam.height]
            small = model.render(cam, background=scene.background, backend=backend, image_only=True).image()
            gt = area_resize(image, cam.width, cam.height)
            r = scores[scale]
            r["psnr"].append(psnr(small, gt))
            r["ssim"].append(ssim(small, gt))
            r["lpips"].append(lpips(small, gt, net=lpips_net, convention=lpips_convention)
                              if min(gt.shape[:2]) >= 32 else float("nan"))
            r["consistency_psnr"].append(psnr(small, area_resize(full, cam.width, cam.height)))
    return {f"{scale:g}": {**{k: float(np.mean(x)) for k, x in scores[scale].items()}, "resolution": sizes[scale]}
            for scale in scales}


def scales_table(m: dict) -> str:
    """The "scales" entry of metrics.json as aligned rows."""
    rows = [f"{'scale':<7}{'size':>10}{'PSNR':>8}{'SSIM':>8}{'LPIPS':>8}{'vs own full-size render':>26}"]
    for key, r in m.get("scales", {}).items():
        size = f"{r['resolution'][0]}x{r['resolution'][1]}"
        rows.append(f"{key:<7}{size:>10}{r['psnr']:>8.2f}{r['ssim']:>8.4f}{r['lpips']:>8.4f}"
                    f"{r['consistency_psnr']:>23.2f} dB")
    return "\n".join(rows)


def metrics_table(m: dict) -> str:
    """A metrics.json record as a short aligned table for a terminal (the JSON file keeps every field)."""
    def num(key, fmt):
        v = m.get(key)
        return "-" if v is None else format(v, fmt)

    res = m.get("resolution")
    rows = [("model", f"{m.get('model', '-')} ({m.get('num_primitives', '-')} primitives, "
                      f"{(m.get('size_bytes') or 0) / 1e6:.2f} MB)"),
            ("views", f"{m.get('views', '-')} {m.get('split', '')} views" + (f" at {res[0]}x{res[1]}" if res else "")),
            ("PSNR", f"{num('psnr', '.2f')} dB"), ("SSIM", num("ssim", ".4f")),
            ("LPIPS", f"{num('lpips', '.4f')} ({m.get('conventions', {}).get('lpips', '')})"),
            ("render", f"{num('fps', '.1f')} FPS ({m.get('backend', '-')} backend)"),
            *([("opacity", f"{m['object_alpha']:.3f} mean alpha on the object (inside the masks)")]
              if m.get("object_alpha") is not None else []),
            *([("training", f"{num('train_seconds', '.0f')} s, {m.get('iterations', '-')} iterations")]
              if m.get("iterations") is not None else [])]
    width = max(len(k) for k, _ in rows)
    return "\n".join(f"{k:<{width}}  {v}" for k, v in rows)


def to_uint8(img: torch.Tensor) -> np.ndarray:
    return (img.clamp(0, 1).numpy() * 255 + 0.5).astype(np.uint8)


def write_png(path, img) -> None:
    import cv2

    arr = to_uint8(img) if isinstance(img, torch.Tensor) else img
    with atomic_path(path, suffix=".png") as tmp:
        if not cv2.imwrite(str(tmp), np.ascontiguousarray(arr[..., ::-1])):
            raise SplatzooError(f"could not write image {path}")


@torch.no_grad()
def save_test_renders(model, scene, out_dir, *, backend: str = "auto", split: str = "test") -> list[Path]:
    backend = resolve_backend(backend, _device(model))
    views = scene.test if split == "test" else scene.train
    out_dir = Path(out_dir) / split
    paths = []
    for v in views:
        p = out_dir / (Path(v.name).stem + ".png")
        write_png(p, model.render(v.camera, background=scene.background, backend=backend, image_only=True).image())
        paths.append(p)
    return paths


def orbit_cameras(cameras: list[Camera], frames: int = 60) -> list[Camera]:
    """Cameras on a circle through the mean camera height, looking at the point the cameras look at most."""
    from .geometry import look_at_point

    centers = torch.stack([c.center.double() for c in cameras])
    target = look_at_point(cameras)
    up = -torch.stack([c.R[1].double() for c in cameras]).mean(0)  # image up (-y) averaged
    up = up / up.norm()
    rel = centers - target
    height = (rel @ up).mean()
    radius = (rel - (rel @ up)[:, None] * up).norm(dim=1).mean()
    e1 = rel[0] - (rel[0] @ up) * up
    e1 = e1 / e1.norm()
    e2 = torch.linalg.cross(up, e1)
    ref = cameras[0]
    fov = 2 * math.degrees(math.atan(ref.width / (2 * float(ref.K[0, 0]))))
    cams = []
    for i in range(frames):
        a = 2 * math.pi * i / frames
        eye = target + up * height + radius * (math.cos(a) * e1 + math.sin(a) * e2)
        cams.append(Camera.look_at(eye, target, up=-up, fov_deg=fov, width=ref.width, height=ref.height,
                                   name=f"orbit_{i:03d}"))
    return cams


@torch.no_grad()
def write_video(model, cameras: list[Camera], background, path, *, backend: str) -> Path:
    """Render `cameras` into a video at `path`: WebM (VP9, else VP8) plays in every current browser; OpenCV's
    wheels carry no H.264 encoder and their mp4 (mp4v) plays in video players only, so it is the last resort
    (written beside `path` as .mp4). Returns the written path."""
    import cv2

    size = (cameras[0].width, cameras[0].height)

    class NoEncoder(Exception):
        pass

    path = Path(path)
    for target, fourcc in ((path, "VP90"), (path, "VP80"), (path.with_suffix(".mp4"), "mp4v")):
        try:
            with atomic_path(target, suffix=target.suffix) as tmp:  # an exception inside leaves no file behind
                writer = cv2.VideoWriter(str(tmp), cv2.VideoWriter_fourcc(*fourcc), 30, size)
                if not writer.isOpened():
                    raise NoEncoder
                for c in cameras:
                    frame = to_uint8(model.render(c, background=background, backend=backend, image_only=True).image())
                    writer.write(np.ascontiguousarray(frame[..., ::-1]))
                writer.release()
            return target
        except NoEncoder:
            continue
    raise SplatzooError("OpenCV can write no video format here (VP9, VP8 or mp4v); render PNGs without --video")
