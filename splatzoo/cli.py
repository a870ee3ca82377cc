"""The `splatzoo` command line: a thin shell over functions a user can call from Python.

Heavy imports (open3d, pycolmap, cv2, the native extension) stay inside the commands.
"""
from __future__ import annotations

import os
import sys
from pathlib import Path
from typing import Optional

import typer

from .errors import SplatzooError

# plain help (rich_markup_mode=None): this typer's rich panels print every flag as `--flag <bool>`
app = typer.Typer(add_completion=False, no_args_is_help=True, pretty_exceptions_enable=False, rich_markup_mode=None,
                  help="splatzoo: surface splatting model zoo (2DGS, 3D Gabor splatting and plugins).")


@app.command("models")
def models_command(
    verbose: bool = typer.Option(False, "--verbose", "-v",
                                 help="also list the models' options: those several models share once, then each "
                                      "model's own"),
) -> None:
    """List the available models: name, origin (built-in or plugin) and description; broken plugins say why."""
    from .registry import MODELS

    entries = MODELS.entries()
    for entry in entries:
        if entry.broken:
            typer.echo(f"{entry.name:<14} {entry.origin:<24} BROKEN: {entry.error}")
        else:
            typer.echo(f"{entry.name:<14} {entry.origin:<24} {entry.spec.description}")
    if not verbose:
        return
    shared, own = option_groups({e.name: e.spec.config_cls for e in entries if not e.broken})
    typer.echo("\nModel options: train --model NAME --option VALUE, or NAME:option=value wherever a model is named.")
    if shared:
        typer.echo("\nShared by several models:")
        for names, rows in shared:
            typer.echo(f"{', '.join(names)}:")
            typer.echo("\n".join(_option_line(row) for row in rows))
    typer.echo("\nEach model's own:" if shared else "")
    for name, rows in own.items():
        if rows:
            typer.echo(f"{name}:")
            typer.echo("\n".join(_option_line(row) for row in rows))
    sharing = [name for name, rows in own.items() if not rows and any(name in names for names, _ in shared)]
    empty = [name for name, rows in own.items() if not rows and name not in sharing]
    if sharing:
        typer.echo(f"(only shared options: {', '.join(sharing)})")
    if empty:
        typer.echo(f"(no options: {', '.join(empty)})")


def option_groups(configs: dict) -> tuple[list, dict]:
    """Model options with those several models share stated once: {model: config class} -> (shared, own).
    shared: [(model names, rows)], the rows (flag, type name, default, help) that exactly those models have alike
    (flag, type, default and help), the widest groups first; own: {model: rows no other model has alike}."""
    from .options import option_fields

    rows = {name: [(flag, getattr(typ, "__name__", str(typ)), default, hlp)
                   for flag, typ, default, hlp in option_fields(cls)] for name, cls in configs.items()}
    holders: dict = {}
    for name, model_rows in rows.items():
        for row in model_rows:
            holders.setdefault(row, []).append(name)
    groups: dict = {}
    for row, names in holders.items():  # first seen first, so each group keeps its first model's field order
        if len(names) > 1:
            groups.setdefault(tuple(names), []).append(row)
    shared = sorted(groups.items(), key=lambda g: (-len(g[0]), g[0]))
    own = {name: [row for row in model_rows if len(holders[row]) == 1] for name, model_rows in rows.items()}
    return shared, own


def _option_line(row) -> str:
    flag, typ, default, hlp = row
    return f"  {flag} {typ.upper()}  {hlp} (default {default})"


def _print_version(value: bool) -> None:
    if value:
        from . import __version__

        typer.echo(f"splatzoo {__version__}")
        raise typer.Exit()


@app.callback()
def _root(
    version: bool = typer.Option(False, "--version", callback=_print_version, is_eager=True,
                                 help="Print the version and exit."),
) -> None:
    """splatzoo: surface splatting model zoo (2DGS, 3D Gabor splatting and plugins)."""


def _path_arg(value):
    """A path argument the file system can look up: a name longer than it allows (or a folder we may not read) is a
    usage error that names it, not an OSError from deep inside the command."""
    import errno

    for path in value if isinstance(value, (list, tuple)) else [value]:
        if path is None:
            continue
        try:
            os.stat(path)
        except OSError as e:
            if e.errno not in (errno.ENOENT, errno.ENOTDIR):  # missing: the command says what it needs there
                raise typer.BadParameter(f"{str(path)[:120]}{'...' if len(str(path)) > 120 else ''} cannot be "
                                         f"looked up ({e.strerror or e})") from None
    return value


# --- data commands (splatzoo sfm, splatzoo synth) ---------------------------------------------------------
# (data commands go here)
@app.command("sfm")
def sfm_command(
    images_dir: Path = typer.Argument(..., metavar="IMAGES", help="Folder of photos (png/jpg) of one static subject, "
                                      "or a video of it (mp4, mov, avi, ...: sharp frames are taken from it).",
                                      callback=_path_arg),
    out: Path = typer.Option(..., "--out", "-o", help="Dataset folder to create (images/, sparse/0/).",
                             callback=_path_arg),
    camera_model: str = typer.Option("SIMPLE_RADIAL", "--camera-model",
                                     help="COLMAP camera model to fit (case-insensitive): SIMPLE_RADIAL, SIMPLE_PINHOLE "
                                     "(no distortion), PINHOLE, OPENCV, OPENCV_FISHEYE, ...; non-pinhole models are "
                                     "undistorted when the dataset is loaded."),
    focal: Optional[float] = typer.Option(None, "--focal", metavar="PIXELS",
                                          help="Focal length of the photos in pixels, if known (lens mm / sensor width "
                                          "mm x image width): SfM holds it fixed in every pass, instead of starting "
                                          "from EXIF or 1.2 x the longer side and refining."),
    retry: bool = typer.Option(True, "--retry/--no-retry", help="When the fit looks implausible, map again with "
                               "SIMPLE_PINHOLE (focal held at --focal if given) and keep the better fit."),
    report: bool = typer.Option(True, "--report/--no-report", help="Write sfm_report.png (cameras and points seen "
                                "from above) and sfm_report.json into the output folder."),
    single_camera: bool = typer.Option(True, help="One camera shared by all photos of one size."),
    seed: int = typer.Option(0, help="Random seed for the mapper."),
    overwrite: bool = typer.Option(False, help="Replace an existing output folder."),
    matching: str = typer.Option("auto", "--matching", metavar="STRATEGY",
                                 help="Which image pairs to match: auto (exhaustive up to 40 photos; sequential for a "
                                 "video or file names numbered in sequence; vocabtree beyond), exhaustive (every "
                                 "pair), sequential (each frame with its neighbours in order, plus loop closure), "
                                 "vocabtree (each photo with those most like it), spatial (by EXIF GPS)."),
    vocab_tree: Optional[Path] = typer.Option(None, "--vocab-tree", metavar="PATH",
                                              help="A COLMAP vocabulary tree file (.bin) for vocabtree matching and "
                                              "loop closure; without it a small one is built from the photos."),
    fps: Optional[float] = typer.Option(None, "--fps", help="Video: frames to keep per second of video (default 2); "
                                        "the sharpest frame of each window is kept."),
    frames: Optional[int] = typer.Option(None, "--frames", help="Video: how many frames to keep, evenly spread over "
                                         "the clip (instead of --fps)."),
) -> None:
    """Structure from motion on the CPU (pycolmap): poses and a sparse point cloud from photos or a video, checked
    (distortion that folds, a focal far from the prior, few points) before the dataset is written."""
    from .data.sfm import run_sfm
    from .data.video import VIDEO_SUFFIXES, sfm_video

    options = dict(progress=typer.echo, camera_model=camera_model, single_camera=single_camera, seed=seed,
                   focal=focal, retry=retry, report=report, matching=matching, vocab_tree=vocab_tree)
    if images_dir.is_file() or (images_dir.suffix.lower() in VIDEO_SUFFIXES and not images_dir.is_dir()):
        res = sfm_video(images_dir, out, fps=fps, frames=frames, overwrite=overwrite, **options)
    else:
        if fps is not None or frames is not None:
            raise SplatzooError(f"--fps and --frames choose frames of a video, but {images_dir} is not a video file")
        res = run_sfm(images_dir, out, overwrite=overwrite, **options)
    if res.num_registered < res.num_images:
        typer.echo(f"warning: only {res.num_registered} of {res.num_images} images registered", err=True)


@app.command("synth")
def synth_command(
    name: Optional[str] = typer.Argument(None, metavar="SCENE", help="Scene name (see --list)."),
    out: Optional[Path] = typer.Option(None, "--out", "-o", help="Dataset folder to create.", callback=_path_arg),
    views: int = typer.Option(48, help="Number of views."),
    width: int = typer.Option(256, help="Image width in pixels."),
    height: int = typer.Option(256, help="Image height in pixels."),
    seed: int = typer.Option(0, help="Seed for camera jitter and point sampling."),
    sfm: bool = typer.Option(False, "--sfm", help="Recover poses and points with SfM instead of the true ones."),
    list_scenes: bool = typer.Option(False, "--list", help="List the synthetic scenes and exit."),
    overwrite: bool = typer.Option(False, help="Replace an existing output folder."),
    background: str = typer.Option("black", "--background", help="colour behind the object: black, white or R,G,B "
                                   "(an object photographed on a white sheet: white)"),
) -> None:
    """Render a synthetic high-frequency benchmark scene as a COLMAP dataset (with its true mesh)."""
    from .data.background import parse_background
    from .data.synthetic import list_scenes as scenes, make_synthetic_scene

    if list_scenes:
        for scene_name, description in scenes().items():
            typer.echo(f"{scene_name:<10} {description}")
        return
    if name is None or out is None:
        raise typer.BadParameter("give a scene NAME and --out DATA (or --list to see the scenes)")
    colour = parse_background(background)
    if not isinstance(colour, tuple):
        raise typer.BadParameter(f"--background {background}: a synthetic scene needs a colour (black, white, R,G,B)")
    make_synthetic_scene(name, out, views=views, width=width, height=height, seed=seed, sfm=sfm,
                         overwrite=overwrite, progress=typer.echo, background=colour)

# --- rasterizer benchmark (splatzoo bench) ----------------------------------------------------------------
# (bench command goes here)
def describe_path(path) -> str | None:
    """What `path` is when it is not a regular file or a folder ("does not exist", "is a FIFO (named pipe)", ...);
    None for a regular file or a folder."""
    import stat

    try:
        mode = os.stat(path).st_mode
    except FileNotFoundError:
        return "does not exist"
    except NotADirectoryError:
        return "does not exist (a folder on its way is a file)"
    except OSError as e:
        return f"cannot be looked up ({e.strerror or e})"
    if stat.S_ISREG(mode) or stat.S_ISDIR(mode):
        return None
    kinds = ((stat.S_ISFIFO, "a FIFO (named pipe)"), (stat.S_ISCHR, "a character device"),
             (stat.S_ISBLK, "a block device"), (stat.S_ISSOCK, "a socket"))
    return "is " + next((what for test, what in kinds if test(mode)), "not a regular file")


def check_output_file(path, option: str) -> Path:
    """Refuse, before any work, an output file that cannot be written: a folder, a FIFO or device, a path under a
    file, a folder that does not take new files (read-only, /proc). Writes nothing: a probe file is made in the
    nearest existing folder and removed at once."""
    import tempfile

    path = Path(path)
    what = describe_path(path)
    if what is None and path.is_dir():
        raise SplatzooError(f"{option} {path} is a folder; give a file name such as {path / 'results.json'}")
    if what is not None and not what.startswith("does not exist"):
        raise SplatzooError(f"{option} {path} {what}, not a file to write; give a file name in a folder you can "
                            "write to")
    folder = path.absolute().parent
    while not folder.exists() and folder != folder.parent:
        folder = folder.parent
    if not folder.is_dir():
        raise SplatzooError(f"{option} {path}: {folder} is a file, not a folder; give a path in a folder you can "
                            "write to")
    try:
        fd, probe = tempfile.mkstemp(prefix=".splatzoo-write-check.", dir=folder)
        os.close(fd)
        os.remove(probe)
    except OSError as e:
        raise SplatzooError(f"{option} {path} cannot be written: {folder} does not take new files "
                            f"({e.strerror or e}); give a path in a folder you can write to") from None
    return path


def available_memory() -> int | None:
    """Bytes of memory this machine can still hand out (Linux: MemAvailable), or None where unknown."""
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    try:
        return os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (ValueError, OSError, AttributeError):
        return None


def _bench_module(name: str):
    """benchmarks/<name>.py of the source checkout, imported."""
    import importlib.util

    bench_file = Path(__file__).resolve().parents[1] / "benchmarks" / f"{name}.py"
    if not bench_file.is_file():
        raise SplatzooError(f"{bench_file} not found: `splatzoo bench` runs from a source checkout of splatzoo")
    spec = importlib.util.spec_from_file_location(f"splatzoo_{name}", bench_file)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


# the options of each of bench's three benchmarks (the rasterizer's, --fps RUN and --training)
_BENCH_RASTER = {"repeats": "--repeats", "backends": "--backends", "waves": "--waves", "quick": "--quick",
                 "gpu": "--gpu"}
_BENCH_TRAINING = {"data": "--data", "size": "--size", "views": "--views", "iterations": "--iterations",
                   "models": "--models", "gsplat_examples": "--gsplat-examples"}


def _refuse_options(given: set[str], options: dict[str, str], what: str, why: str) -> None:
    """Options typed for another benchmark are refused by name, not ignored."""
    stray = [flag for name, flag in options.items() if name in given]
    if stray:
        one = len(stray) == 1
        raise SplatzooError(f"{' and '.join(stray)} {'does' if one else 'do'} not apply to {what} ({why}); drop "
                            f"{'it' if one else 'them'}")


@app.command("bench")
def bench_command(
    ctx: typer.Context,
    json_path: str = typer.Option("benchmarks/results/rasterizer.json", "--json", help="Where to write the JSON results."),
    repeats: int = typer.Option(3, help="Timed repeats per measurement (the median is reported), 1 to 1000."),
    backends: Optional[str] = typer.Option(None, help="Comma-separated subset of cuda,cpu,reference (default: all available)."),
    waves: str = typer.Option("0,4,4a", help="Comma-separated wave counts: 0 (2DGS), 4 (gabor), 4a (4 with mixed "
                              "per-surfel counts), 0t4 (a 4x4 texture); a trailing b: Beta kernels. The zoo's "
                              "members: 0,0b,4,6,0t4. At most 64 waves and 64x64 texels."),
    quick: bool = typer.Option(False, "--quick", help="Only the 128x128 scenes (5k surfels, sparse and dense)."),
    gpu: bool = typer.Option(False, "--gpu", help="The 1920x1080 scenes of 100k, 500k and 1M surfels (cuda)."),
    fps: Optional[Path] = typer.Option(None, "--fps", metavar="RUN", callback=_path_arg,
                                       help="Instead: the frame rate of a trained run, at its test views' size and at "
                                       "1080 lines, image-only (as a viewer shows it) and with every output."),
    backend: str = typer.Option("auto", "--backend", help="The backend of --fps and --training: auto, cpu or cuda."),
    training: bool = typer.Option(False, "--training", help="Instead: whole training runs of 2dgs and gabor at paper "
                                  "scale (benchmarks/bench_training.py): time, it/s, metrics, peak GPU memory, and a "
                                  "breakdown of a step."),
    data: Optional[Path] = typer.Option(None, "--data", callback=_path_arg,
                                        help="--training: a dataset (default: a synthetic scene)."),
    size: str = typer.Option("1920x1080", "--size", help="--training: the synthetic scene's WIDTHxHEIGHT (8 to "
                             "16384 a side)."),
    views: int = typer.Option(120, "--views", help="--training: the synthetic scene's views."),
    iterations: int = typer.Option(30000, "--iterations", help="--training: iterations per model."),
    models: str = typer.Option("2dgs,gabor", "--models", help="--training: comma-separated models."),
    gsplat_examples: Optional[Path] = typer.Option(None, "--gsplat-examples", callback=_path_arg,
                                                   help="--training: gsplat's examples folder, to run its 2DGS "
                                                   "trainer on the same data too."),
) -> None:
    """Benchmark the rasterizer backends (forward, forward+backward, pairs per second) and write a JSON report; or,
    with --fps RUN, the frame rate of a trained run; or, with --training, whole training runs.

    Everything asked for is checked before anything runs: an option of another benchmark, a bad list entry or an
    output file that cannot be written is an error, not a surprise at the end."""
    given = _given(ctx)
    if fps is not None and training:
        raise SplatzooError("--fps RUN and --training are different benchmarks; pass one of them")
    if training:
        _refuse_options(given, _BENCH_RASTER, "--training", "the rasterizer benchmark's options")
        bench = _bench_module("bench_training")
        argv = bench.check_request(data=data, size=size, views=views, iterations=iterations, models=models,
                                   backend=backend, gsplat_examples=gsplat_examples,
                                   synthetic="size" in given or "views" in given)
        if "json_path" in given:
            argv += ["--json", str(check_output_file(json_path, "--json"))]
        bench.run(argv, echo=typer.echo)
        return
    if fps is not None:
        _refuse_options(given, {**_BENCH_RASTER, **_BENCH_TRAINING, "json_path": "--json"}, "--fps RUN",
                        "it prints the run's frame rates and writes no file")
        from .evaluate import fps_report
        from .runs import load_run

        what = describe_path(fps)
        if what is not None or not fps.is_dir():
            raise SplatzooError(f"--fps {fps} {what or 'is a file'}; give a run folder written by `splatzoo train`")
        model, scene, _ = load_run(fps, backend)
        test_views = scene.test or scene.train
        for row in fps_report(model, [v.camera for v in test_views], scene.background, backend):
            typer.echo(f"{row['label']:>11s} {row['size']:>10s}: {row['fps_image']:7.2f} FPS image-only, "
                       f"{row['fps_full']:7.2f} FPS with every output ({backend} backend)")
        return

    _refuse_options(given, _BENCH_TRAINING, "the rasterizer benchmark", "options of --training")
    _refuse_options(given, {"backend": "--backend"}, "the rasterizer benchmark",
                    "it is for --fps RUN and --training; the rasterizer benchmark's backends are chosen with --backends")
    if quick and gpu:
        raise SplatzooError("--quick and --gpu choose different scenes: pass one of them")
    bench = _bench_module("bench_rasterizer")
    configs = bench.CONFIGS[:2] if quick else bench.GPU_CONFIGS if gpu else bench.CONFIGS
    chosen_backends, chosen_waves = bench.check_request(backends, waves, configs, repeats)
    check_output_file(json_path, "--json")
    bench.run_benchmark(backends=chosen_backends, waves=chosen_waves, configs=configs, repeats=repeats,
                        json_path=json_path, echo=typer.echo)


# --- training and evaluation (train, eval, render, compare) ---------------------------------------------
# (training commands go here)
def _scene_options(resolution: Optional[int], max_width: Optional[int], test_every: Optional[int],
                   background: Optional[str], white_background: bool = False) -> dict:
    opts = {}
    if resolution is not None:
        opts["resolution"] = resolution
    if max_width is not None:
        opts["max_width"] = max_width
    if test_every is not None:
        opts["test_every"] = test_every
    if white_background and background is not None and background.strip().lower() != "white":
        raise typer.BadParameter(f"--white-background and --background {background} disagree; pass one")
    if background is not None or white_background:
        from .data.background import parse_background

        opts["background"] = parse_background("white" if white_background else background)
    return opts


_RESOLUTION = typer.Option(None, "--resolution", "-r", help="downscale images by 1, 2, 4 or 8")
_MAX_WIDTH = typer.Option(None, "--max-width", help="downscale images to at most this width")
_TEST_EVERY = typer.Option(None, "--test-every", help="every N-th image (sorted by name) is a test view; 0: none")
_BACKGROUND = typer.Option(None, "--background", help="colour behind the surfels and behind RGBA images: auto (the "
                           "default: found in the image borders, or black), black, white, R,G,B, or random (a new "
                           "colour each training step; needs images with alpha)")
_WHITE = typer.Option(False, "--white-background", hidden=True, help="the same as --background white")
_BACKEND = typer.Option("auto", "--backend", "-b", help="rasterizer: auto, reference, cpu or cuda")
_SKIP_MISSING = typer.Option(False, "--skip-missing", help="leave out the frames of a transforms.json dataset whose "
                             "image is missing (the count and names are printed) instead of stopping")


_DATA_FOR_FILE = typer.Option(None, "--data", "-d", help="dataset to use when RUN is a model file (.ply, .pt), which "
                              "records none", callback=_path_arg)


def _model_file(run: Path, data: Optional[Path]) -> bool:
    """Whether RUN names a model file (then --data is needed); --data with a run folder is an error. A RUN that is
    neither (missing, a FIFO, a device, a folder that holds no run) is named for what it is."""
    what = describe_path(run)
    if what == "does not exist":
        from .registry import closest

        try:
            near = closest(run.name, [p.name for p in run.parent.iterdir()])
        except OSError:
            near = ""
        raise SplatzooError(f"{run} does not exist; give a run folder written by `splatzoo train` (its --out) "
                            f"or a model file (.ply, .pt) with --data{near}")
    if what is not None:
        raise SplatzooError(f"{run} {what}, not a run folder or a model file; give a run folder written by "
                            "`splatzoo train` (its --out) or a model file (.ply, .pt) with --data")
    if run.is_file():
        return True
    from .integrations.nerfstudio import is_nerfstudio_output

    if is_nerfstudio_output(run):  # a model without its dataset on record, as a model file
        return True
    if data is not None:
        from .runs import Run

        if Run(run).status in ("new", "foreign"):
            raise SplatzooError(f"{run} is a folder that holds no splatzoo run (no config.json), and --data scores a "
                                "model file: give the model file itself (.ply, .pt) with --data, or a run folder "
                                "written by `splatzoo train` without --data")
        raise typer.BadParameter(f"--data is for a model file; the run {run} is scored on its own dataset, drop --data")
    return False


_STRATEGY = typer.Option("auto", "--strategy", help="how densification grows the count. auto (default): the "
                         "model's own choice (frequency for neural-gabor, adc for the others); adc: 2DGS's adaptive "
                         "density control (clone, split, prune, opacity resets); mcmc: grow 5% a step to the budget, "
                         "then relocate dead surfels onto live ones; frequency: Neural Gabor splatting's, grow where "
                         "the render's frequency bands differ from the photos', opacities decay instead of resets")
_STORE = typer.Option("float32", "--store", help="the precision the model is stored at: float32, float16 or 8bit "
                      "(positions at 16 bits, the rest 8 bits over each value's range); the end of training runs "
                      "through the stored values, and the run's model (model.pt, model.szp) and numbers are the "
                      "stored model's")
_STORE_FINETUNE = typer.Option(0.1, "--store-finetune", help="fraction of the run, at its end, trained through the "
                               "stored values (with --store below float32)")
_TRAIN_FIELDS = ("iterations", "backend", "seed", "densify", "strategy", "densify_views", "num_primitives",
                 "max_primitives", "lambda_dist", "lambda_normal", "checkpoint_every", "checkpoint_minutes", "batch_size",
                 "nproc", "antialias", "random_downscale", "store", "store_finetune", "max_bytes")


def _size_arg(value: Optional[str]) -> Optional[int]:
    """--max-bytes: a size in bytes, with a unit or without (200kB, 1.5MB, 120000)."""
    if value is None:
        return None
    from .compare import parse_size

    return parse_size(value, "--max-bytes")


def _given(ctx: typer.Context) -> set[str]:
    """The parameters typed on the command line (not defaults): a resumed run takes the rest from its record."""
    return {name for name in ctx.params if getattr(ctx.get_parameter_source(name), "name", "") == "COMMANDLINE"}


_ANTIALIAS = typer.Option(True, "--antialias/--no-antialias", help="train and render with the pixel-footprint "
                          "filter: alias-free when rendered smaller than trained (off: 2DGS's screen filter, 1.1-1.3x "
                          "faster on the CPU)")
_RANDOM_DOWNSCALE = typer.Option(0.0, "--random-downscale", help="fraction of training views rendered at 1/2 or 1/4 "
                                 "size against the area-averaged image (with --antialias)")
_MAX_BYTES = typer.Option(None, "--max-bytes", callback=_size_arg, help="a byte budget for the stored model (200kB, "
                          "1.5MB): from half-way it sheds its weakest surfels or, for beta-gabor and gabor-adaptive, "
                          "its faintest waves, whichever costs the training views least, until its file fits. It "
                          "starts from at most twice the surfels that fit (--num-primitives overrides), and "
                          "densification grows it to no more")
_INIT_FROM = typer.Option(None, "--init-from", metavar="FILE", callback=_path_arg, help="start from the surfels of a "
                          "model file (.ply from `splatzoo export` or another 2DGS/3DGS tool, or a .pt) instead of the "
                          "dataset's points; the model and its options are the file's")


@app.command("train", context_settings={"allow_extra_args": True, "ignore_unknown_options": True})
def train_command(
    ctx: typer.Context,
    data: Optional[Path] = typer.Argument(None, metavar="DATA", help="COLMAP folder (images/ + sparse/0/) or Blender "
                                          "folder (transforms_*.json); with --resume, the run's own dataset by default",
                                          callback=_path_arg),
    model: str = typer.Option("gabor", "--model", "-m", help="model name, with options either following it "
                              "(--n-waves 8) or inline as in compare (gabor:n_waves=8); see `splatzoo models -v`"),
    iterations: int = typer.Option(30000, "--iterations", "-i", help="training iterations; the schedule scales with it"),
    out: Optional[Path] = typer.Option(None, "--out", "-o", help="run directory (default runs/<model>)",
                                       callback=_path_arg),
    backend: str = _BACKEND,
    resolution: Optional[int] = _RESOLUTION,
    max_width: Optional[int] = _MAX_WIDTH,
    test_every: Optional[int] = _TEST_EVERY,
    background: Optional[str] = _BACKGROUND,
    white_background: bool = _WHITE,
    densify: bool = typer.Option(True, "--densify/--no-densify", help="densification (off: a fixed count)"),
    strategy: str = _STRATEGY,
    densify_views: int = typer.Option(20, "--densify-views", help="--strategy frequency: training views rendered "
                                      "at each densification step (all of them when there are fewer)"),
    num_primitives: Optional[int] = typer.Option(None, "--num-primitives", "-n",
                                                 help="start from exactly N primitives (subsampled initial points)"),
    max_primitives: Optional[int] = typer.Option(None, "--max-primitives", help="cap densification at N primitives "
                                                 "(default: one per 128 training pixels)"),
    seed: int = typer.Option(0, "--seed", help="random seed (initial points, view order, initialisation)"),
    resume: bool = typer.Option(False, "--resume", help="continue the interrupted run in --out with its own settings"),
    overwrite: bool = typer.Option(False, "--overwrite", help="replace the run already in --out"),
    lambda_dist: float = typer.Option(0.0, "--lambda-dist", help="depth-distortion weight (2DGS default 0)"),
    lambda_normal: float = typer.Option(0.05, "--lambda-normal", help="normal-consistency weight"),
    checkpoint_every: int = typer.Option(2000, "--checkpoint-every", help="write a checkpoint every N iterations"),
    checkpoint_minutes: float = typer.Option(5.0, "--checkpoint-minutes",
                                             help="also write one every M minutes (0: off); Ctrl-C always writes one"),
    batch_size: int = typer.Option(1, "--batch-size", help="views per step on each process (learning rates x "
                                   "sqrt(views per step), Adam betas to that power)"),
    nproc: int = typer.Option(1, "--nproc", help="data-parallel processes (torch.distributed: gloo on CPU, NCCL "
                              "on CUDA); each renders --batch-size views per step"),
    antialias: bool = _ANTIALIAS,
    random_downscale: float = _RANDOM_DOWNSCALE,
    store: str = _STORE,
    store_finetune: float = _STORE_FINETUNE,
    max_bytes: Optional[str] = _MAX_BYTES,
    viewer: bool = typer.Option(False, "--viewer", help="watch training live in the browser (see `splatzoo view`); "
                                "it stays open after training until Ctrl-C"),
    viewer_port: int = typer.Option(8080, "--viewer-port", help="port of the live viewer"),
    viewer_host: str = typer.Option("127.0.0.1", "--viewer-host", help="address the live viewer listens on"),
    skip_missing: bool = _SKIP_MISSING,
    init_from: Optional[Path] = _INIT_FROM,
) -> None:
    """Train a model on a dataset. Model options follow the model name, e.g. `--model gabor --n-waves 8`.

    The fixed-count comparison of the paper: `--no-densify --num-primitives N`. Ctrl-C (or SIGTERM) stops after
    the current iteration with a checkpoint; `--resume` continues from it.
    """
    from .options import model_spec

    given = _given(ctx)
    data, extra = _data_and_model_args(data, ctx.args)
    model, inline_options = model_spec(model)
    if init_from is not None and "model" not in given and not resume:  # the file's model
        from .runs import initial_model

        model = initial_model(init_from).name
    out = out or Path("runs") / model
    values = {k: v for k, v in ctx.params.items() if k in _TRAIN_FIELDS}
    watch = _start_viewer(out, nproc, viewer_host, viewer_port, backend) if viewer else None
    try:
        scene_options = _scene_options(resolution, max_width, test_every, background, white_background)
        if skip_missing:
            scene_options["skip_missing"] = True
        result = _train(extra, data, model, inline_options, out, resume, overwrite, given, values, scene_options,
                        watch, init_from)
    except BaseException:
        if watch is not None:
            watch.viewer.stop()
        raise
    _report(result)
    if watch is not None:
        _keep_viewer_open(watch)


def _start_viewer(out, nproc: int, host: str, port: int, backend: str):
    """--viewer: the live viewer of the run in `out`, started and its address said (one process only)."""
    from .viewer import TrainingWatch

    if nproc > 1:
        raise typer.BadParameter("the live viewer watches one process; drop --viewer or --nproc")
    watch = TrainingWatch(Path(out).name, host=host, port=port, backend=backend, snapshot_dir=Path(out) / "renders")
    typer.echo(f"live viewer: {watch.viewer.url}")
    return watch


def _keep_viewer_open(watch) -> None:
    """After training, the live viewer serves on until Ctrl-C."""
    typer.echo(f"training finished; the viewer stays open at {watch.viewer.url} (Ctrl-C to stop)")
    try:
        watch.viewer.serve_forever()
    except KeyboardInterrupt:
        typer.echo("viewer stopped")


def _data_and_model_args(data: Optional[Path], args: list[str]) -> tuple[Optional[Path], list[str]]:
    """The command line puts the first word it does not know in DATA: `train --n-waves 8 DATA` gives DATA
    '--n-waves'. Such a word goes back to the model options, where the real DATA is found again among them."""
    if data is not None and str(data).startswith("-"):
        return None, [str(data), *args]
    return data, list(args)


def _model_options(model: str, inline: dict, args: list[str], data: Optional[Path]) -> tuple[dict, Optional[Path]]:
    """The model options typed inline and as flags (each once), and DATA when it came among the flags."""
    from .options import merge_options, parse_model_args

    words: list[str] = []
    options = merge_options(inline, parse_model_args(model, args, positionals=words), model)
    if data is None and words:
        data, words = Path(_path_arg(words[0])), words[1:]
    if words:
        raise typer.BadParameter(f"unexpected argument(s) {' '.join(map(repr, words))}: give one DATA folder "
                                 f"({data}) and the model's options as flags (e.g. --n-waves 8)")
    return options, data


def _train(extra, data, model, inline_options, out, resume, overwrite, given, values, scene_options, watch,
           init_from=None):
    from .runs import Run, train
    from .training import TrainConfig

    if resume:  # only what was typed is checked against the run; the rest comes from its record
        run = Run(out)
        options_model = model if "model" in given or run.status in ("new", "foreign") else run.record()["model"]
        options, data = _model_options(options_model, inline_options, extra, data)
        result = train(data, model if "model" in given else None, options,
                       {k: v for k, v in values.items() if k in given}, out, resume=True,
                       scene_options={k: v for k, v in scene_options.items()
                                      if {"resolution": {"resolution"}, "max_width": {"max_width"},
                                          "test_every": {"test_every"}, "skip_missing": {"skip_missing"},
                                          "background": {"background", "white_background"}}[k] & given},
                       watch=watch, init_from=init_from)
    else:
        options, data = _model_options(model, inline_options, extra, data)
        if data is None:
            raise typer.BadParameter("give the dataset folder DATA (only --resume can take it from the run)")
        result = train(data, model, options, TrainConfig(**values), out,
                       overwrite=overwrite, scene_options=scene_options, watch=watch, init_from=init_from)
    return result


def _report(result) -> None:
    m = result.metrics
    if m:
        typer.echo(f"{result.model.name}: PSNR {_fmt(m.get('psnr'), '.2f')}  SSIM {_fmt(m.get('ssim'), '.4f')}  "
                   f"LPIPS {_fmt(m.get('lpips'), '.4f')}  {m['num_primitives']} primitives"
                   + (f"  {100 * m['wave_fraction']:.1f}% of the waves kept" if (m.get("wave_fraction") or 1.0) < 1.0
                      else "")
                   + f"  {_fmt(m.get('fps'), '.1f')} FPS  {m['size_bytes'] / 1e6:.3f} MB"
                   + (f" ({m['stored_bytes'] / 1e6:.3f} MB stored as {m['precision']}"
                      + (f", {m['psnr'] - m['float32_psnr']:+.2f} dB against float32" if m.get("float32_psnr")
                         is not None and m.get("psnr") is not None else "") + ")"
                      if m.get("precision", "float32") != "float32" else "")
                   + f"  -> {result.run_dir}")


def _fmt(value, spec: str) -> str:
    return "-" if value is None else format(value, spec)


@app.command("eval")
def eval_command(
    run: Path = typer.Argument(..., metavar="RUN", help="run directory written by `splatzoo train`, or a model file "
                               "(.ply, .pt) with --data", callback=_path_arg),
    data: Optional[Path] = _DATA_FOR_FILE,
    backend: str = _BACKEND,
    lpips_net: str = typer.Option("vgg", "--lpips-net", help="vgg or alex"),
    lpips_convention: str = typer.Option("3dgs", "--lpips-convention",
                                         help="3dgs ([0,1] inputs, as the paper's tables) or standard ([-1,1])"),
    scale: Optional[str] = typer.Option(None, "--scale", help="also render smaller, e.g. 0.5,0.25, and score "
                                        "against area-averaged images and the model's own full-size render"),
    out: Optional[Path] = typer.Option(None, "--out", "-o", help="metrics file to write (default RUN/metrics.json); "
                                       "elsewhere, the run is only read (read-only media)", callback=_path_arg),
    skip_missing: bool = _SKIP_MISSING,
) -> None:
    """Evaluate a trained run on its test views; prints a table and writes RUN/metrics.json. A model file (.ply from
    `splatzoo export` or another 2DGS/3DGS tool, or a .pt) is scored on the test views of --data."""
    from .evaluate import metrics_table, parse_scales, scales_table
    from .runs import evaluate_file, evaluate_run

    scales = parse_scales(scale) if scale is not None else ()
    if _model_file(run, data):
        metrics = evaluate_file(run, data, backend=backend, lpips_net=lpips_net, lpips_convention=lpips_convention,
                                scales=scales, out=out, scene_options={"skip_missing": True} if skip_missing else {})
        typer.echo(metrics_table(metrics))
        if scales:
            typer.echo(scales_table(metrics))
        if out is not None:
            typer.echo(f"wrote {out}")
        return
    metrics = evaluate_run(run, backend=backend, lpips_net=lpips_net, lpips_convention=lpips_convention,
                           scales=scales, out=out, skip_missing=skip_missing)
    typer.echo(metrics_table(metrics))
    if scales:
        typer.echo(scales_table(metrics))
    typer.echo(f"wrote {out if out is not None else Path(run) / 'metrics.json'}")


@app.command("render")
def render_command(
    run: Path = typer.Argument(..., metavar="RUN", help="run directory written by `splatzoo train`, or a model file "
                               "(.ply, .pt) with --data", callback=_path_arg),
    data: Optional[Path] = _DATA_FOR_FILE,
    split: str = typer.Option("test", "--split", help="test or train views"),
    video: bool = typer.Option(False, "--video", help="also write an orbit video (renders/orbit.webm, VP9: plays in browsers)"),
    frames: int = typer.Option(60, "--frames", min=1, max=100000, help="frames of the orbit video"),
    backend: str = _BACKEND,
    out: Optional[Path] = typer.Option(None, "--out", "-o", help="folder to write into (default RUN/renders); "
                                       "elsewhere, the run is only read (read-only media)", callback=_path_arg),
    skip_missing: bool = _SKIP_MISSING,
) -> None:
    """Render a trained run's views to PNG (and an orbit video); a model file (.ply, .pt) from the views of --data
    (into --out, default <file>_renders beside it)."""
    from .runs import render_file, render_run

    if _model_file(run, data):
        paths = render_file(run, data, split=split, video=video, backend=backend, frames=frames, out=out,
                            scene_options={"skip_missing": True} if skip_missing else {})
        typer.echo(f"wrote {len(paths)} files under {out if out is not None else run.parent / (run.stem + '_renders')}")
        return
    paths = render_run(run, split=split, video=video, backend=backend, frames=frames, out=out,
                       skip_missing=skip_missing)
    typer.echo(f"wrote {len(paths)} files under {out if out is not None else Path(run) / 'renders'}")


@app.command("view")
def view_command(
    runs: list[Path] = typer.Argument(..., metavar="RUN", help="run folders (a folder of runs, such as runs/compare, "
                                      "stands for all of them), or model files (.ply, .pt: no training cameras)",
                                      callback=_path_arg),
    port: int = typer.Option(8080, "--port", "-p", help="port to serve on"),
    host: str = typer.Option("127.0.0.1", "--host", help="address to listen on (127.0.0.1: this machine only; "
                             "0.0.0.0 opens the viewer to the network)"),
    backend: str = _BACKEND,
) -> None:
    """Look at trained runs in the browser: orbit and fly, training cameras, render modes, runs side by side."""
    from .viewer import view

    viewer = view(runs, host=host, port=port, backend=backend)
    typer.echo(f"viewer: {viewer.url}  ({len(viewer.sources)} model{'s' if len(viewer.sources) > 1 else ''}; "
               "Ctrl-C to stop)")
    try:
        viewer.serve_forever()
    except KeyboardInterrupt:
        typer.echo("viewer stopped")


@app.command("compare")
def compare_command(
    models: list[str] = typer.Argument(..., metavar="MODEL", help="models to compare, e.g. gabor 2dgs (options: gabor:n_waves=8)"),
    data: Optional[Path] = typer.Option(None, "--data", "-d", help="dataset (default: a built-in synthetic scene)",
                                        callback=_path_arg),
    scene: str = typer.Option("sweater", "--scene", help="built-in synthetic scene when --data is not given"),
    out: Path = typer.Option(Path("runs/compare"), "--out", "-o", help="output folder", callback=_path_arg),
    iterations: Optional[int] = typer.Option(None, "--iterations", "-i", help="iterations per model (30000; quick 1500)"),
    num_primitives: Optional[int] = typer.Option(None, "--num-primitives", "-n", help="equal primitive count for all"),
    densify: bool = typer.Option(False, "--densify/--no-densify", help="densify (off: the paper's fixed-count protocol)"),
    strategy: str = _STRATEGY,
    quick: bool = typer.Option(False, "--quick", help="small scene and short schedule: a few minutes on 2 cores"),
    equal_bytes: bool = typer.Option(False, "--equal-bytes", help="equal model size instead of equal count: the first "
                                     "model gets --num-primitives (default: every initial point) and its trained size "
                                     "(after pruning waves, if adaptive) is the budget; each other model gets as many "
                                     "as fit in it"),
    antialias: bool = typer.Option(True, "--antialias/--no-antialias", help="train and render every model with the "
                                   "pixel-footprint filter (off: 2DGS's screen filter)"),
    random_downscale: float = typer.Option(0.0, "--random-downscale", help="fraction of training views rendered at "
                                           "1/2 or 1/4 size against the area-averaged image (with --antialias)"),
    budgets: Optional[str] = typer.Option(None, "--budgets", help="rate-distortion curves: train every model at "
                                          "every budget, each a fraction of the first model's stored size at its "
                                          "count or a size (5%,25%,100% or 20kB,200kB); writes rate.png and a rate "
                                          "table"),
    budget_start: Optional[float] = typer.Option(None, "--budget-start", help="with --budgets: each budgeted run "
                                                 "starts with this many times the primitives that fit its budget "
                                                 "(default: each model's own: 3 for 2dgs and beta, for beta-gabor 3 "
                                                 "falling to 1.4 as the budget holds 80 to 1,864 surfels, 2 for the "
                                                 "others) "
                                                 "and sheds those that cost its views least down to it from half-way "
                                                 "(1: start with what fits)"),
    store: str = _STORE,
    lpips_net: str = typer.Option("vgg", "--lpips-net", help="the network LPIPS is scored with: vgg (the papers' "
                                  "tables) or alex (the weights a GPU check carries); a finished run scored with the "
                                  "other is scored again, not retrained"),
    seed: int = typer.Option(0, "--seed", help="random seed (initial points, view order, initialisation)"),
    overwrite: bool = typer.Option(False, "--overwrite", help="retrain runs in --out that were made with other "
                                   "settings or by other splatzoo code (without it other settings are an error; "
                                   "runs with the same settings are reused, those by other code named in the report)"),
    backend: str = _BACKEND,
    resolution: Optional[int] = _RESOLUTION,
    max_width: Optional[int] = _MAX_WIDTH,
    test_every: Optional[int] = _TEST_EVERY,
    background: Optional[str] = _BACKGROUND,
    white_background: bool = _WHITE,
    skip_missing: bool = _SKIP_MISSING,
) -> None:
    """Train several models with identical data, initial points and budget; write compare.json, report.md,
    compare.png and convergence.png. `splatzoo compare gabor baseline-a baseline-b baseline-c 2dgs` is the
    paper's ablation."""
    from .compare import compare

    scene_options = _scene_options(resolution, max_width, test_every, background, white_background)
    if skip_missing:
        scene_options["skip_missing"] = True
    compare(models, data, out, iterations=iterations, num_primitives=num_primitives, densify=densify, quick=quick,
            strategy=strategy, seed=seed, backend=backend, synthetic_scene=scene, overwrite=overwrite,
            equal_bytes=equal_bytes, antialias=antialias, random_downscale=random_downscale,
            scene_options=scene_options, budgets=budgets, store=store, budget_start=budget_start, lpips_net=lpips_net)
    typer.echo((out / "report.md").read_text())
    typer.echo(f"wrote {out}: compare.json, report.md, compare.png, convergence.png"
               f"{', rate.png' if budgets else ''}, runs/<model>/")


@app.command("sweep", context_settings={"allow_extra_args": True, "ignore_unknown_options": True})
def sweep_command(
    ctx: typer.Context,
    data: Optional[Path] = typer.Argument(None, metavar="DATA", help="dataset (default: a built-in synthetic scene, see --scene)",
                                          callback=_path_arg),
    model: str = typer.Option("gabor", "--model", "-m", help="wave model swept over --n-waves (0 = the 2dgs model); "
                              "options follow it (--prune-waves 0.01) or inline (gabor:prune_waves=0.01)"),
    n_waves: str = typer.Option("0,1,2,4,8", "--n-waves", help="comma-separated wave counts"),
    num_primitives: str = typer.Option("1000,2000,4000", "--num-primitives", "-n",
                                       help="comma-separated fixed primitive counts"),
    scene: str = typer.Option("sweater", "--scene", help="built-in synthetic scene when DATA is not given"),
    out: Path = typer.Option(Path("runs/sweep"), "--out", "-o", help="output folder", callback=_path_arg),
    iterations: Optional[int] = typer.Option(None, "--iterations", "-i", help="iterations per run (30000; quick 400)"),
    quick: bool = typer.Option(False, "--quick", help="small synthetic scene (96x96) and a short schedule"),
    seed: int = typer.Option(0, "--seed", help="random seed (initial points, view order, initialisation)"),
    overwrite: bool = typer.Option(False, "--overwrite", help="retrain runs in --out that were made with other settings"),
    antialias: bool = typer.Option(True, "--antialias/--no-antialias", help="train and render every run with the "
                                   "pixel-footprint filter (off: 2DGS's screen filter)"),
    backend: str = _BACKEND,
    resolution: Optional[int] = _RESOLUTION,
    max_width: Optional[int] = _MAX_WIDTH,
    test_every: Optional[int] = _TEST_EVERY,
    background: Optional[str] = _BACKGROUND,
    white_background: bool = _WHITE,
) -> None:
    """Measure the speed / accuracy trade: train every (n_waves, primitives) pair without densification and write
    sweep.json, pareto.png and report.md. Other model options follow, e.g. `--prune-waves 0.01`."""
    from .options import model_spec
    from .sweep import sweep

    model, inline_options = model_spec(model)
    data, extra = _data_and_model_args(data, ctx.args)
    options, data = _model_options(model, inline_options, extra, data)
    sweep(data, out, model=model, n_waves=n_waves, num_primitives=num_primitives, iterations=iterations,
          quick=quick, seed=seed, backend=backend, synthetic_scene=scene, model_options=options, overwrite=overwrite,
          antialias=antialias, scene_options=_scene_options(resolution, max_width, test_every, background, white_background))
    typer.echo((out / "report.md").read_text())
    typer.echo(f"wrote {out}: sweep.json, report.md, pareto.png")


# --- mesh extraction and export (extract-mesh, export) -----------------------------------------------------
# (mesh commands go here)
@app.command("extract-mesh")
def extract_mesh_command(
    run: Path = typer.Argument(..., metavar="RUN", help="run directory written by `splatzoo train`",
                               callback=_path_arg),
    out: Optional[Path] = typer.Option(None, "--out", "-o", help="mesh file to write (default RUN/mesh.ply)",
                                       callback=_path_arg),
    voxel_size: Optional[float] = typer.Option(None, "--voxel-size", help="TSDF voxel size in world units "
                                               "(default: max(depth_trunc/1024, one pixel at the object))"),
    sdf_trunc: Optional[float] = typer.Option(None, "--sdf-trunc", help="TSDF truncation distance (default 5 voxels)"),
    depth_trunc: Optional[float] = typer.Option(None, "--depth-trunc", help="ignore depth beyond this (default 2x the "
                                                "camera distance to the look-at point)"),
    depth: str = typer.Option("median", "--depth", help="median (sharp, 2DGS for objects) or expected depth"),
    alpha_threshold: float = typer.Option(0.5, "--alpha-threshold", help="fuse only pixels at least this opaque"),
    keep_largest: bool = typer.Option(False, "--keep-largest", help="keep only the largest connected component"),
    backend: str = _BACKEND,
) -> None:
    """Extract a coloured triangle mesh: render depth from the training cameras and fuse it (TSDF)."""
    from .mesh import extract_mesh_from_run

    extract_mesh_from_run(run, out, backend=backend, progress=lambda msg: typer.echo(msg, err=True),
                          voxel_size=voxel_size, sdf_trunc=sdf_trunc, depth_trunc=depth_trunc, depth=depth,
                          alpha_threshold=alpha_threshold, keep_largest=keep_largest)


@app.command("export")
def export_command(
    run: Optional[Path] = typer.Argument(None, metavar="RUN", help="run directory written by `splatzoo train`, or a "
                                         "model file (.pt or .ply)", callback=_path_arg),
    out: Optional[Path] = typer.Option(None, "--out", "-o", help="file to write (its suffix follows the format: .ply, "
                                       ".spz, .sog, ...)", callback=_path_arg),
    format: str = typer.Option("ply", "--format", "-f", metavar="FORMAT",
                               help="export format, with options inline as for models (baked:max_splats=16000); "
                               "`--format help` or --list shows them all"),
    list_formats: bool = typer.Option(False, "--list", help="list the export formats and their options, and exit"),
) -> None:
    """Export a trained model: a PLY that every 3DGS/2DGS tool reads (the default; Gabor waves ride along as extra
    properties), SPZ, SOG, a baked or meshed model (see --list)."""
    from .export import EXPORTERS, describe_format, export

    if list_formats or format.strip().lower() in ("help", "list", "?"):
        for entry in EXPORTERS.entries():
            if entry.broken:
                typer.echo(f"{entry.name:<15} {entry.origin:<24} BROKEN: {entry.error}")
                continue
            spec = entry.spec
            typer.echo(f"{entry.name:<15} {', '.join(spec.suffixes):<16} {spec.description}")
            typer.echo(describe_format(spec))
        return
    if run is None or out is None:
        raise typer.BadParameter("give a RUN (or model file) and --out FILE (or --list to see the formats)")
    path = export(run, out, format, progress=lambda msg: typer.echo(msg, err=True))
    typer.echo(f"wrote {path}")


def main() -> None:
    """Entry point: splatzoo's own errors become one clear line and exit code 2 (no traceback); an interrupted
    training exits 130 (SIGINT) or 143 (SIGTERM) after saying how to resume."""
    import signal

    # SIGTERM unwinds like Ctrl-C (temporary files and folders are removed on the way out) instead of killing
    signal.signal(signal.SIGTERM, _on_signal)
    signal.signal(signal.SIGINT, _on_signal)
    try:
        app()
    except SplatzooError as e:
        from .training.distributed import launched_world

        interrupted = hasattr(e, "exit_code")  # runs.TrainingInterrupted: not an error, a stop on request
        rank = int(os.environ.get("RANK", "0")) if launched_world() else None  # one of torchrun's processes
        if not (interrupted and rank):  # every rank stops alike: rank 0 alone says how to resume
            typer.echo(str(e) if interrupted else f"error{'' if rank is None else f' (rank {rank})'}: {e}", err=True)
        code = getattr(e, "exit_code", 2)
        # an interrupt outside the training loop (the final evaluation) reports 130 whichever signal it was
        sys.exit(_received_signal[0] if interrupted and code == 130 and _received_signal else code)
    except SystemExit as e:
        # the command line layer ends an interrupt with exit 130 (or "Aborted!", 1); say which signal it was
        sys.exit(_received_signal[0] if _received_signal and e.code in (1, 130) else e.code)


_received_signal: list[int] = []


def _on_signal(signum, frame):
    _received_signal[:] = [128 + signum]
    raise KeyboardInterrupt


if __name__ == "__main__":
    main()
