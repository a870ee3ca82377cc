"""Model files: one table of the formats a model is read from and written to, and one way to open a model from a
path (`open_model`). Below the run folders and the exporters, which both open models through it.

`FORMATS` holds one `ModelFormat` per format: its name, the file names or first bytes it is told by, and a reader
and a writer, symmetric where the format allows (as PlayCanvas splat-transform's readers and writers chosen by
suffix):
  spz, sog, compressed-ply   read and written through splat-transform (splatzoo.splat_tools): a model is written as
                             our PLY, then converted; a file is converted to a PLY, then read as another tool's PLY
  splat, ksplat              read through splat-transform
  ply                        the PLY layout of splatzoo.model_ply (`save_ply`, `load_ply`), told by its first bytes
  szp, pt                    splatzoo's packed and torch model files (splatzoo.zoo `save_model`, `load_model`)
A folder format reads a folder rather than a file: run folders register theirs from splatzoo.runs, which this layer
imports by name (FOLDER_FORMAT_MODULES) the first time it is asked to open a folder, as it would a plugin, so it
never imports the layer above it when it is loaded. A file is told by the first format, in table order, that claims it; torch files
take whatever no other format claims.

Reading refuses a model that draws nothing, whatever its file (splatzoo.model_checks). A file splat-transform cannot
read is refused with its own message and the file's name and format, and every message names the file, never the
temporary PLY in between.
"""
from __future__ import annotations

import importlib
import tempfile
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

from .errors import DuplicateNameError, SplatzooError, UnknownNameError
from .model_ply import load_ply, save_ply


@dataclass(frozen=True)
class ModelFormat:
    """A model file format. `read(path) -> model`; a folder format's `read(path, latest=False) -> (model, the file
    read, a note)` (latest: the newest state of an unfinished folder rather than refusing it). `write(model, path,
    *, progress=None, **options) -> path` writes atomically (None: a format splatzoo only reads). A file is claimed
    by `detect(path)` when given, else by its first bytes `magic`, else by its name ending in one of `suffixes`
    (lower case), which also name the files the format writes."""

    name: str
    description: str
    read: Callable[..., Any]
    write: Callable[..., Path] | None = None
    suffixes: tuple[str, ...] = ()
    magic: bytes | None = None
    detect: Callable[[Path], bool] | None = None
    folder: bool = False

    def claims(self, path: Path, head: Callable[[], bytes]) -> bool:
        """Whether this format reads the file `path`; `head()` gives its first bytes."""
        if self.folder:
            return False
        if self.detect is not None:
            return self.detect(path)
        if self.magic is not None:
            return head().startswith(self.magic)
        return path.name.lower().endswith(self.suffixes)


# name -> format, in the order files are told in (a dict keeps it)
FORMATS: dict[str, ModelFormat] = {}
FOLDER_FORMAT_MODULES = ("splatzoo.runs",)  # modules whose import registers folder formats (run folders)


def register_format(fmt: ModelFormat) -> ModelFormat:
    if fmt.name in FORMATS:
        raise DuplicateNameError(f"model file format {fmt.name!r} is registered twice; rename one of them")
    FORMATS[fmt.name] = fmt
    return fmt


def format_named(name: str) -> ModelFormat:
    if name not in FORMATS:
        from .registry import closest

        raise UnknownNameError(f"unknown model file format {name!r}; known: {', '.join(FORMATS)}"
                               + closest(name, FORMATS))
    return FORMATS[name]


@dataclass
class OpenedModel:
    """What `open_model` found: the model, the path it was asked to open (a run folder or a model file), the file its
    parameters were read from (a run folder's model.pt), the format's name and a note on what was opened (e.g. an
    unfinished run's last checkpoint); "" when plain."""

    model: Any
    path: Path
    file: Path
    format: str
    note: str = ""


def format_of(path) -> ModelFormat:
    """The format `path` is read as: a file by the first format that claims it, anything else that exists by the
    folder format (a run folder)."""
    path = Path(path)
    try:
        is_file, exists = path.is_file(), path.exists()
    except OSError as e:
        raise SplatzooError(f"{str(path)[:200]} cannot be looked up ({e.strerror or e})") from None
    if is_file:
        first: list[bytes] = []

        def head() -> bytes:  # read only when a format asks for it (other tools' files are told by name)
            if not first:
                with open(path, "rb") as f:
                    first.append(f.read(8))
            return first[0]

        return next(fmt for fmt in FORMATS.values() if fmt.claims(path, head))
    if not exists:
        raise SplatzooError(f"{path} does not exist; pass a run directory written by `splatzoo train`, a model .pt "
                            "or a model .ply")
    for module in FOLDER_FORMAT_MODULES:  # run folders: their format registers itself when its module loads
        importlib.import_module(module)
    folders = [fmt for fmt in FORMATS.values() if fmt.folder]
    # a folder format with a detect() claims the folders it recognises; the one without (run folders) takes the rest
    folder = next((fmt for fmt in folders if fmt.detect is not None and fmt.detect(path)), None) or next(
        (fmt for fmt in folders if fmt.detect is None), None)
    if folder is None:
        raise SplatzooError(f"{path} is a folder, and no folder format is registered (run folders are read by "
                            "splatzoo.runs)")
    return folder


def open_model(path, *, backend: str | None = None, latest: bool = False) -> OpenedModel:
    """The model in `path`, a model file of any format in FORMATS or a run folder (its trained model.pt; with
    `latest`, an interrupted run's last checkpoint), on the device `backend` renders on (None: as read, on the CPU)."""
    path = Path(path)
    fmt = format_of(path)
    if fmt.folder:
        model, file, note = fmt.read(path, latest=latest)
    else:
        model, file, note = fmt.read(path), path, ""
    if backend is not None:
        from .rasterizers import select_backend

        model = model.to(select_backend(backend).torch_device())
    return OpenedModel(model, path, Path(file), fmt.name, note)


def load_model(path, *, backend: str | None = None):
    """The model in `path`: a model file of any format in FORMATS (.pt, .szp, .ply, .glb, .spz, .sog, .splat, .ksplat,
    compressed PLY) or a run folder. `splatzoo.load_model` is this; `splatzoo.zoo.load_model` reads torch and packed
    files only (the table's pt and szp reader)."""
    return open_model(path, backend=backend).model


def load_source(source):
    """(model, the file it was read from) of a run folder or a model file: `open_model` as a pair."""
    opened = open_model(source)
    return opened.model, opened.file


def write_model(model, path, *, format: str | None = None, progress=None, **options) -> Path:
    """Write `model` to `path` in `format` (a name in FORMATS; None: the format whose suffix `path` ends in, the
    longest that matches); `options` go to the format's writer. Returns the path."""
    path = Path(path)
    if format is None:
        name = path.name.lower()
        fitting = [(max(len(s) for s in fmt.suffixes if name.endswith(s)), fmt) for fmt in FORMATS.values()
                   if fmt.write is not None and name.endswith(fmt.suffixes)]
        if not fitting:
            known = ", ".join(s for fmt in FORMATS.values() if fmt.write is not None for s in fmt.suffixes)
            raise SplatzooError(f"cannot tell the model file format of {path} from its name; end it in one of {known}")
        fmt = max(fitting, key=lambda f: f[0])[1]
    else:
        fmt = format_named(format)
        if fmt.write is None:
            raise SplatzooError(f"model file format {fmt.name!r} is read, not written, by splatzoo")
    return Path(fmt.write(model, path, progress=progress, **options))


# --- the formats splatzoo reads and writes itself --------------------------------------------------------------

def _write_ply(model, path, *, progress=None, **options) -> Path:
    return save_ply(model, path, **options)


def _read_torch(path):
    from .zoo import load_model

    return load_model(path)


def _write_torch(model, path, *, progress=None) -> Path:
    from .zoo import save_model

    save_model(model, path)
    return Path(path)


def _packed(path: Path) -> bool:
    from .packing import SUFFIX, is_packed

    return path.suffix == SUFFIX or is_packed(path)


# --- the formats of other tools, through splat-transform -------------------------------------------------------

def _compressed(path: Path) -> bool:
    from .ply import compressed_ply

    return path.name.lower().endswith(".ply") and compressed_ply(path)


def _read_glb_splats(path):
    from .gltf_splats import read_glb_splats

    return read_glb_splats(path)


def _write_glb_splats(model, path, *, progress=None, **options) -> Path:
    from .gltf_splats import save_glb_splats

    return save_glb_splats(model, path, progress=progress, **options)


def _read_converted(source: Path):
    """The model of a splat file that splat-transform converts to a PLY for load_ply. Every message and note names
    `source`, never the temporary PLY (which is gone by the time anyone reads them)."""
    from .splat_tools import read_splat_file

    label = f"{source} (read through splat-transform)"
    with tempfile.TemporaryDirectory(prefix="splatzoo-load-") as folder:
        ply = read_splat_file(source, Path(folder) / "model.ply")
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            try:
                model = load_ply(ply)
            except SplatzooError as e:
                raise type(e)(str(e).replace(str(ply), label)) from None
    model.notes = [note.replace(str(ply), label) for note in model.notes]
    for w in caught:
        warnings.warn(str(w.message).replace(str(ply), label), w.category, stacklevel=3)
    means = model.per_primitive().get("means")
    n = model.num_primitives
    if means is not None and n > 1 and bool((means.detach() == means.detach()[:1]).all()):
        point = ", ".join(f"{float(x):.4g}" for x in means.detach()[0])
        raise SplatzooError(f"{label}: every one of its {n} splats lies at the one point ({point}): the file's "
                            "positions were lost (it is damaged or was written wrongly); export or download it again")
    return model


def _converted_writer(suffix: str, args: Callable[..., list[str]]):
    """A writer through splat-transform: the model as our PLY in a temporary folder, converted to `path`."""
    def write(model, path, *, progress=None, **options) -> Path:
        from .splat_tools import convert_file, find_splat_transform

        out = Path(path)
        cli = find_splat_transform()  # before any work: a missing tool is the likeliest failure
        with tempfile.TemporaryDirectory(prefix="splatzoo-export-") as folder:
            ply = save_ply(model, Path(folder) / "model.ply")
            if progress:
                progress(f"converting {model.num_primitives} primitives with {cli}")
            convert_file(ply, out, args=args(**options), suffix=suffix, label=f"the {model.name} model")
        if progress:
            progress(f"wrote {out}")
        return out
    return write


def _spz_args(version: int = 3) -> list[str]:
    return ["--spz-version", str(version)]


def _sog_args(sh_iterations: int = 10, gpu: str = "cpu") -> list[str]:
    return ["-g", str(gpu), "-i", str(sh_iterations)]


# the order is the order files are told in: suffixes of other tools' files first, then the first bytes of a PLY, and
# torch files last (they claim whatever is left)
for _fmt in (
        ModelFormat("spz", "Niantic's compressed splats (splat-transform)", _read_converted,
                    _converted_writer(".spz", _spz_args), (".spz",)),
        ModelFormat("sog", "PlayCanvas SOG (splat-transform)", _read_converted,
                    _converted_writer(".sog", _sog_args), (".sog",)),
        ModelFormat("splat", ".splat (antimatter15), read through splat-transform", _read_converted,
                    suffixes=(".splat",)),
        ModelFormat("ksplat", "GaussianSplats3D .ksplat, read through splat-transform", _read_converted,
                    suffixes=(".ksplat",)),
        ModelFormat("compressed-ply", "PlayCanvas / SuperSplat compressed PLY (splat-transform)", _read_converted,
                    _converted_writer(".compressed.ply", lambda: []), (".compressed.ply",), detect=_compressed),
        ModelFormat("glb-splat", "glTF binary with KHR_gaussian_splatting splats (splatzoo.gltf_splats)",
                    _read_glb_splats, _write_glb_splats, (".glb",), magic=b"glTF"),
        ModelFormat("ply", "the 3DGS/2DGS PLY with splatzoo's own properties (splatzoo.model_ply)", load_ply,
                    _write_ply, (".ply",), magic=b"ply"),
        ModelFormat("szp", "a model packed at its storage precision (splatzoo.packing)", _read_torch, _write_torch,
                    (".szp",), detect=_packed),
        ModelFormat("pt", "a model as a torch file (splatzoo.zoo.save_model)", _read_torch, _write_torch, (".pt",),
                    detect=lambda path: True)):
    register_format(_fmt)
del _fmt


def _read_nerfstudio(path, *, latest: bool = False):
    from .integrations.nerfstudio import open_nerfstudio_output

    return open_nerfstudio_output(path, latest=latest)


def _nerfstudio_folder(path: Path) -> bool:
    from .integrations.nerfstudio import is_nerfstudio_output

    return is_nerfstudio_output(path)


register_format(ModelFormat("nerfstudio", "an ns-train output folder of a splatzoo method (config.yml and "
                            "nerfstudio_models/, splatzoo.integrations.nerfstudio)", _read_nerfstudio,
                            detect=_nerfstudio_folder, folder=True))
