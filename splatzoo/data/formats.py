"""The registry of dataset formats and `load_scene`, which picks a format by looking at the folder.

Each reader module declares its layout as a `DatasetFormat` (name, detect, load, needs); the built-in ones
(COLMAP, Blender) are registered here, and `register_format` adds another from Python:

    register_format(DatasetFormat("mine", detect=lambda p: (p / "mine.json").is_file(), load=load_mine,
                                  needs="mine.json and its images"))
"""
from __future__ import annotations

from pathlib import Path

from ..errors import DataError
from ..registry import Registry
from . import blender, colmap
from .scene import DatasetFormat, MissingMaskError, Scene, check_cameras, image_size

FORMATS: Registry[DatasetFormat] = Registry("dataset format")


def register_format(fmt: DatasetFormat) -> DatasetFormat:
    """Add a dataset format; a second format under one name is an error."""
    if not isinstance(fmt, DatasetFormat):
        raise TypeError(f"register_format expects a DatasetFormat, got {type(fmt).__name__}")
    return FORMATS.register(fmt.name, fmt)


def list_formats() -> list[DatasetFormat]:
    """Every registered format, in the order detection tries them."""
    return sorted((e.spec for e in FORMATS.entries() if e.spec is not None), key=lambda f: (f.priority, f.name))


def known_formats_text() -> str:
    """'colmap (images/ ...); blender (...)': the formats and what each needs, for messages."""
    return "; ".join(f"{f.name} ({f.needs})" for f in list_formats())


register_format(colmap.FORMAT)
register_format(blender.FORMAT)


def detect_format(path) -> str:
    """The name of the format of dataset folder `path`; a DataError says what a dataset folder must contain."""
    path = Path(path)
    try:
        path.stat()
    except (FileNotFoundError, NotADirectoryError):
        pass
    except OSError as e:  # a name longer than the file system allows, a folder we may not read, ...
        raise DataError(f"dataset folder {str(path)[:200]} cannot be looked up ({e.strerror or e}); check the "
                        "path") from None
    if not path.exists():
        raise DataError(f"dataset folder {path} does not exist; check the path (create one with "
                        "`splatzoo sfm IMAGES --out DATA` or `splatzoo synth NAME --out DATA`)")
    if not path.is_dir():
        raise DataError(f"{path} is a file, not a dataset folder; pass the folder of a dataset. Known formats: "
                        f"{known_formats_text()}")
    for fmt in list_formats():
        if fmt.detect(path):
            return fmt.name
    if not any(path.iterdir()):
        raise DataError(f"dataset folder {path} is empty; put a dataset there (known formats: "
                        f"{known_formats_text()}) or run `splatzoo sfm` on a folder of photos")
    raise DataError(f"{path} is not a dataset folder that splatzoo recognises. Known formats: {known_formats_text()}. "
                    f"For a folder of photos run `splatzoo sfm {path} --out DATA` first")


def _takes(load, keyword: str) -> bool:
    """Whether a format's reader accepts `keyword` (readers registered before it existed do not)."""
    import inspect

    try:
        params = inspect.signature(load).parameters
    except (TypeError, ValueError):
        return False
    return keyword in params or any(p.kind is p.VAR_KEYWORD for p in params.values())


DEFAULT_MAX_WIDTH = 1600  # pixels; wider photos are downscaled unless --resolution or --max-width is given


def load_scene(path, *, resolution: int | None = None, max_width: int | None = None, test_every: int = 8,
               background="auto", masks: bool | str = "auto", format: str | None = None,
               skip_missing: bool = False) -> Scene:
    """Load a dataset folder in any registered format (COLMAP, Blender/NeRF-synthetic, ...), detected automatically.

    resolution: downscale factor 1, 2, 4 or 8 (uses images_<n>/ when present); max_width caps the width. With
    neither, images wider than DEFAULT_MAX_WIDTH are downscaled to it (scene.notes says so); resolution=1 keeps them.
    test_every: images sorted by name, index % test_every == 0 go to `test` (0: no test split; Blender
    datasets with transforms_test.json use their own split). background: the colour behind the surfels and behind
    RGBA images: "auto" (found in the images, see data/background.py), "random", "black", "white", "R,G,B" or an RGB
    tuple in [0,1]; the scene says what it chose in `background_note`.
    masks: expose per-view masks (masks/<name> files, else the image alpha channel); "auto": when the folder has
    masks/.
    format: a registered format name, to skip detection.
    skip_missing: leave out the frames of a transforms file whose image is missing (scene.notes lists them) instead
    of stopping with an error; formats whose reader has no such option say so in scene.notes.
    """
    from .background import _has_alpha as has_alpha, choose_background, parse_background

    from .scene import scene_option_problem

    for key, value in (("resolution", resolution), ("max_width", max_width), ("test_every", test_every),
                       ("skip_missing", skip_missing)):
        problem = scene_option_problem(key, value)  # before a folder is read: the same words for every format
        if problem:
            raise DataError(problem)
    path = Path(path).expanduser()
    option = parse_background(background)
    if format is None:
        format = detect_format(path)
    elif not path.is_dir():
        detect_format(path)  # the missing-folder / not-a-folder messages
    capped = resolution is None and max_width is None  # large photos are downscaled unless asked otherwise
    fmt = FORMATS.get(format)
    reader = fmt.load
    skipping = _takes(reader, "skip_missing")
    # masks="auto": a dataset's masks/ (or the masks its format names, e.g. a transforms file's mask_path) are read
    # when present (eval measures opacity inside them; --background random replaces the backdrop through them, see
    # data/background.py); an incomplete masks/ folder is left out, not an error, but a mask the files name must exist
    auto_masks = masks == "auto"
    if auto_masks:
        masks = fmt.has_masks(path) if fmt.has_masks is not None else (path / "masks").is_dir()

    def read(masks: bool):
        return reader(path, resolution=resolution, max_width=DEFAULT_MAX_WIDTH if capped else max_width,
                      test_every=test_every, background=option if isinstance(option, tuple) else (0.0, 0.0, 0.0),
                      masks=masks, **({"skip_missing": True} if skip_missing and skipping else {}))

    try:
        scene = read(masks)
    except DataError as e:
        if not (auto_masks and masks and "mask" in str(e)) or isinstance(e, MissingMaskError):
            raise
        scene = read(False)
        scene.notes.append(f"masks/ not used: {str(e).split(';')[0]}")
    if skip_missing and not skipping:
        scene.notes.append(f"skip_missing does not apply to {format} datasets: their reader leaves out no frames")
    check_cameras(scene.views, path)
    if capped and scene.views:
        view = scene.views[0]
        source_width = (view.pixels.shape[1] if view.pixels is not None else
                        image_size(view.path)[0] if view.path is not None else view.camera.width)
        if source_width > view.camera.width:
            scene.notes.append(f"the images are {source_width} px wide: training at {view.camera.width} px (about "
                               f"{DEFAULT_MAX_WIDTH} px, as 3DGS tools do; memory and time grow with the pixels). "
                               "Pass --resolution 1 for full size or --max-width N")
    colour, random, note = choose_background(option, scene.train, scene.colors)
    for view in scene.views:
        view.background = colour
    scene.background, scene.random_background, scene.background_note = colour, random, note
    scene.masked_backdrop = random and bool(scene.train) and not has_alpha(scene.train[0])
    if note:
        scene.notes.append(f"background: {note}")
    return scene
