"""Evaluation and renders of a finished run on its own dataset, or of a model file on a dataset named with it."""
from __future__ import annotations

from pathlib import Path

from .errors import SplatzooError
from .io import write_json
from .model_checks import check_fits_scene
from .model_files import open_model
from .run_folder import Run

def load_run(run_dir, backend: str | None = None):
    """(model, scene, config record) of a finished run; with a backend name ("auto" too), the model is on the
    device that backend renders on."""
    return Run(run_dir).load(backend)


def evaluate_run(run_dir, *, backend: str = "auto", lpips_net: str | None = None,
                 lpips_convention: str | None = None, scales=(), out=None, skip_missing: bool = False) -> dict:
    """Evaluate a finished run on its test views and write RUN/metrics.json (or the file `out`: the run is then only
    read, so it may be on read-only media); `scales` (each below 1) adds the metrics of smaller renders against
    area-averaged images (evaluate_scales) as its "scales" entry. skip_missing: leave out views whose image has gone
    missing (see load_scene)."""
    from .evaluate import LPIPS_CONVENTION, checked_lpips_net, evaluate, evaluate_scales

    lpips_net = checked_lpips_net(lpips_net)
    run = Run(run_dir)
    target = Path(out) if out is not None else run.metrics_path
    with run.writing("splatzoo eval", target, "--out FILE.json"):
        model, scene, record = run.load(backend, skip_missing=skip_missing)
        old = run.metrics() if run.metrics_path.exists() else None
        metrics = evaluate(model, scene, backend=backend, train_seconds=(old or {}).get("train_seconds"),
                           iterations=record["train"].get("iterations"), lpips_net=lpips_net,
                           lpips_convention=lpips_convention or LPIPS_CONVENTION)
        if old and old.get("float32_psnr") is not None:  # what storage cost: the same model, the same test views
            metrics["float32_psnr"] = old["float32_psnr"]
        if scales:
            metrics["scales"] = evaluate_scales(model, scene, scales, backend=backend, lpips_net=lpips_net,
                                                lpips_convention=lpips_convention or LPIPS_CONVENTION)
        write_json(target, metrics)
    return metrics


def render_run(run_dir, *, split: str = "test", video: bool = False, backend: str = "auto",
               frames: int = 60, out=None, skip_missing: bool = False) -> list[Path]:
    """Write the split's renders as PNG (and an orbit video, WebM) into RUN/renders (or the folder `out`: the run
    is then only read); returns the written paths."""
    _check_split(split)
    run = Run(run_dir)
    folder = Path(out) if out is not None else run.renders_dir
    with run.writing("splatzoo render", folder, "--out FOLDER"):
        model, scene, _ = run.load(backend, skip_missing=skip_missing)
        return _render_views(model, scene, folder, split=split, video=video, backend=backend, frames=frames)


def _check_split(split: str) -> None:
    if split not in ("test", "train"):
        raise SplatzooError(f"unknown split {split!r}; use test or train")


def _render_views(model, scene, folder: Path, *, split: str, video: bool, backend: str, frames: int) -> list[Path]:
    """The split's renders as PNG in `folder` and, with `video`, an orbit of the training cameras as WebM."""
    from .evaluate import orbit_cameras, resolve_backend, save_test_renders, write_video

    paths = save_test_renders(model, scene, folder, backend=backend, split=split)
    if video:
        cams = orbit_cameras([v.camera for v in scene.train], frames)
        paths.append(write_video(model, cams, scene.background, folder / "orbit.webm",
                                 backend=resolve_backend(backend, next(model.parameters()).device)))
    return paths


# --- model files (.ply, .pt) with a dataset named on the command line --------------------------------------------

def _file_and_scene(path, data, backend: str, scene_options: dict | None):
    """(model on the backend's device, scene) of a model file and the dataset it is scored or rendered on."""
    from .data import load_scene
    from .rasterizers import select_backend

    if data is None:
        how = "splatzoo.load_ply" if Path(path).suffix.lower() == ".ply" else "splatzoo.load_model"
        raise SplatzooError(f"{path} is a model file, not a run folder: it records no dataset, so pass the one to use "
                            f"with --data DATA (in Python, {how} reads it)")
    model = open_model(path).model
    scene = load_scene(data, **(scene_options or {}))
    check_fits_scene(model, scene, str(path))
    return model.to(select_backend(backend).torch_device()), scene


def evaluate_file(path, data, *, backend: str = "auto", lpips_net: str | None = None,
                  lpips_convention: str | None = None, scales=(), out=None, scene_options: dict | None = None) -> dict:
    """Evaluate the model file `path` (.ply or .pt) on the test views of the dataset `data`; the metrics are
    returned, and written to the JSON file `out` when given."""
    from .evaluate import LPIPS_CONVENTION, checked_lpips_net, evaluate, evaluate_scales

    lpips_net = checked_lpips_net(lpips_net)
    model, scene = _file_and_scene(path, data, backend, scene_options)
    metrics = evaluate(model, scene, backend=backend, lpips_net=lpips_net,
                       lpips_convention=lpips_convention or LPIPS_CONVENTION)
    if scales:
        metrics["scales"] = evaluate_scales(model, scene, scales, backend=backend, lpips_net=lpips_net,
                                            lpips_convention=lpips_convention or LPIPS_CONVENTION)
    if out is not None:
        write_json(out, metrics)
    return metrics


def render_file(path, data, *, split: str = "test", video: bool = False, backend: str = "auto", frames: int = 60,
                out=None, scene_options: dict | None = None) -> list[Path]:
    """Render the model file `path` (.ply or .pt) from the split's views of the dataset `data` into the folder `out`
    (default: <file name>_renders beside the file); returns the written paths."""
    _check_split(split)
    path = Path(path)
    model, scene = _file_and_scene(path, data, backend, scene_options)
    folder = Path(out) if out is not None else path.parent / f"{path.stem}_renders"
    return _render_views(model, scene, folder, split=split, video=video, backend=backend, frames=frames)

