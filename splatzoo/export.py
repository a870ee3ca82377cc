"""Model export: a registry of formats (`splatzoo export RUN --format FMT --out FILE`) and the products derived from a
model for other tools (a PLY made for a viewer's dilation, a baked model, a textured mesh).

Formats
-------
`EXPORTERS` holds one `ExporterSpec` per format: name, description, file suffix(es), an options dataclass and a
function `fn(source, out, *, progress=None, **options) -> Path`, where `source` is a run folder or a model file (.pt
or .ply). Built-ins: `ply` (the layout of splatzoo.model_ply, or with viewer=3dgs|mip made for a viewer that dilates
every splat), `spz`, `sog` and `compressed-ply` (model file formats of splatzoo.model_files, written through PlayCanvas
splat-transform), and `baked` (splatzoo.bake) and `mesh-glb`, `mesh-obj` (splatzoo.mesh_texture), imported only when
used. Plugins add formats through the entry-point group `splatzoo.exporters`, whose value is an `ExporterSpec`.
Options use the model-option syntax: `--format baked:max_splats=16000`.

Model files themselves are read and written below this module: the PLY layout in splatzoo.model_ply, every format and
`open_model` in splatzoo.model_files. Their names that were long imported from here (save_ply, load_ply, load_source,
model_columns, flatten_gaussians, read_ply_vertices, ...) still are.
"""
from __future__ import annotations

import dataclasses
import math
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import torch

from .errors import PluginError, SplatzooError
from .model_checks import check_in_view
# model files, long imported from this module (the names stay importable here)
from .model_files import load_source, open_model, write_model  # noqa: F401
from .model_ply import (FLAT_LOG_SCALE, FORMAT_VERSION, RENDER_MODE_COMMENT, SATURATED_LOGIT,  # noqa: F401
                        flatten_gaussians, load_ply, model_columns, save_ply)
from .ply import read_ply_vertices, write_ply_vertices  # noqa: F401
from .options import model_spec, option_value
from .registry import Registry
from .runs import Run

# --- the exporter registry -------------------------------------------------------------------------------------

@dataclass
class ExporterSpec:
    """An export format. `fn(source, out, *, progress=None, **options) -> Path` writes `out` (atomically) from
    `source`, a run folder or a model file (.pt or .ply). `options` is a dataclass of the format's options (or None:
    none). Built-ins whose code lives in an optional module give `fn` and `options` as "module:name" strings, imported
    when the format is first used."""

    name: str
    fn: Callable[..., Path] | str
    options: type | str | None = None
    description: str = ""
    suffixes: tuple[str, ...] = (".ply",)
    extra: dict = field(default_factory=dict)

    def _resolve(self, target):
        if not isinstance(target, str):
            return target
        import importlib

        module, _, attr = target.partition(":")
        try:
            loaded = importlib.import_module(module)
        except ModuleNotFoundError as e:
            if not e.name or module.startswith(e.name):
                raise SplatzooError(f"export format {self.name!r} needs {module}, which this splatzoo installation "
                                    "does not have; update splatzoo (or pick another --format, see "
                                    "`splatzoo export --list`)") from None
            raise SplatzooError(f"export format {self.name!r} needs the Python package {e.name}, which is not "
                                f"installed: pip install {e.name} (or pick another --format)") from None
        try:
            return getattr(loaded, attr)
        except AttributeError:
            raise SplatzooError(f"export format {self.name!r}: {module} has no {attr}; this splatzoo installation "
                                "is incomplete, update it") from None

    def function(self) -> Callable[..., Path]:
        return self._resolve(self.fn)

    def options_class(self) -> type | None:
        return self._resolve(self.options)


def _validate_exporter_spec(obj: Any, name: str) -> ExporterSpec:
    if callable(obj) and not isinstance(obj, (ExporterSpec, type)):
        obj = obj()
    if not isinstance(obj, ExporterSpec):
        raise PluginError(f"entry point must name a splatzoo.export.ExporterSpec, got {type(obj).__name__}")
    if obj.name != name:
        raise PluginError(f"entry point name {name!r} differs from the spec's name {obj.name!r}")
    return obj


EXPORTERS: Registry[ExporterSpec] = Registry("export format", entry_point_group="splatzoo.exporters",
                                             validate=_validate_exporter_spec)


def register_exporter(spec: ExporterSpec) -> ExporterSpec:
    return EXPORTERS.register(spec.name, spec)


def list_formats() -> list[str]:
    return EXPORTERS.names()


def export_options(spec: ExporterSpec, options: dict):
    """The format's options dataclass with `options` (strings from the command line, or values) applied."""
    cls = spec.options_class()
    if cls is None:
        if options:
            raise SplatzooError(f"export format {spec.name!r} has no options; got {', '.join(options)}")
        return None
    fields = {f.name: f for f in dataclasses.fields(cls)}
    unknown = [k for k in options if k not in fields]
    if unknown:
        from .registry import closest

        raise SplatzooError(f"export format {spec.name!r} has no option(s) {', '.join(unknown)}; its options are: "
                            f"{', '.join(fields) or 'none'}" + closest(unknown[0], fields))
    hints = typing.get_type_hints(cls)
    values = {key: option_value(f"export format {spec.name!r}", key, hints.get(key), value, fields[key].default)
              for key, value in options.items()}
    try:
        return cls(**values)
    except (TypeError, ValueError) as e:
        raise SplatzooError(f"export format {spec.name!r}: {e}") from None


def describe_format(spec: ExporterSpec) -> str:
    """One line per option: name, type, default, help (or a note that the format's module is missing)."""
    try:
        cls = spec.options_class()
    except SplatzooError as e:
        return f"    (unavailable: {e})"
    if cls is None:
        return "    (no options)"
    hints = typing.get_type_hints(cls)
    rows = []
    for f in dataclasses.fields(cls):
        default = f.default if f.default is not dataclasses.MISSING else (
            f.default_factory() if f.default_factory is not dataclasses.MISSING else None)
        typ = hints.get(f.name, str)
        text = f.metadata.get("help", "")
        said = "(default" in text  # a help that states its own default
        rows.append(f"    {f.name}={getattr(typ, '__name__', str(typ)).upper()}  {text}"
                    + ("" if said else f" (default {default})"))
    return "\n".join(rows) if rows else "    (no options)"


def parse_format(text: str) -> tuple[ExporterSpec, object]:
    """'baked:max_splats=16000' -> (the spec, its options dataclass); the model-option syntax."""
    name, options = model_spec(text)
    spec = EXPORTERS.get(name)
    return spec, export_options(spec, options)


def _suffix_ok(out: Path, suffixes: tuple[str, ...]) -> bool:
    return any(out.name.lower().endswith(s.lower()) and len(out.name) > len(s) for s in suffixes)


def check_export_target(spec: ExporterSpec, out: Path, model_path: Path | None = None) -> None:
    """`--out RUN/model.pt` would replace the trained model: export writes only files with the format's suffix, and
    never over the file it reads."""
    if out.is_dir():
        raise SplatzooError(f"cannot write the export to {out}: it is a folder; give a file name such as "
                            f"{out / ('model' + (spec.suffixes or ('.ply',))[0])}")
    if spec.suffixes and not _suffix_ok(out, spec.suffixes):
        stem = out.name[:-len(out.suffix)] if out.suffix else (out.name or "model")
        suggestion = out.parent / f"{stem}{spec.suffixes[0]}"
        raise SplatzooError(f"export writes a {spec.suffixes[0][1:].upper()} file for --format {spec.name}, so --out "
                            f"must end in {' or '.join(spec.suffixes)}; got {out}. Name the file e.g. {suggestion}")
    if model_path is None:
        return
    same = out.resolve() == Path(model_path).resolve()
    if not same and out.exists():
        try:
            same = out.samefile(model_path)
        except OSError:
            same = False
    if same:
        raise SplatzooError(f"refusing to export onto the model being read ({model_path}); choose another --out, "
                            f"e.g. {Path(model_path).with_name(Path(model_path).stem + '-export' + spec.suffixes[0])}")


def _source_file(source: Path) -> Path | None:
    """The file a source will be read from (for the never-over-the-input check), without loading it."""
    source = Path(source)
    try:
        if source.is_dir():
            return source / "model.pt"
        return source if source.exists() else None
    except OSError:
        return None


def export(source, out, format: str = "ply", *, progress=None, **options) -> Path:
    """Export the model of `source` (a run folder, a model .pt or .ply) to `out` in `format` (a name, or a name with
    options: 'baked:max_splats=16000'); keyword `options` add to those. Returns the written path."""
    name, inline = model_spec(format)
    spec = EXPORTERS.get(name)
    opts = export_options(spec, {**inline, **options})
    out = Path(out)
    check_export_target(spec, out, _source_file(Path(source)))
    kwargs = dataclasses.asdict(opts) if opts is not None else {}
    return Path(spec.function()(Path(source), out, progress=progress, **kwargs))


# --- built-in formats ------------------------------------------------------------------------------------------

@dataclass
class PlyOptions:
    ascii: bool = field(default=False, metadata={"help": "write an ASCII PLY (larger, slower; to read by eye)"})
    viewer: str = field(default="exact", metadata={
        "help": "exact: the trained surfels (load_ply restores the model; for viewers set as splatzoo renders, e.g. "
                "Spark blurAmount 0.1, GaussianSplats3D antialiased with kernel2DSize 0.1); 3dgs: scales and "
                "opacities made for viewers that add 0.3 px^2 to every splat and keep its opacity (GaussianSplats3D's "
                "and SuperSplat's defaults), from the run's training cameras; a file for viewing, not for load_ply"})


VIEWER_DILATION = 0.3  # px^2 a 3DGS-style viewer adds to every splat's screen covariance
_VIEWER_FIX = ("Export it with ply:viewer=exact (the surfels as trained) instead, or from a run whose training cameras "
               "see the model")
VIEWER_RULES = ("exact", "3dgs", "mip")


def training_view_scale(means: torch.Tensor, axes: torch.Tensor, cameras) -> tuple[torch.Tensor, torch.Tensor]:
    """Where each surfel was seen in training, as medians over `cameras`: px2 [N], its world area per pixel^2
    ((depth / focal)^2), and fore [N,2], how much of each axis' length (axes [N,3,2], unit) survives on screen,
    squared (1 - (axis . view direction)^2, at least 0.05)."""
    px2, fore = [], []
    for cam in cameras:
        w2c = cam.world_to_camera.double()
        z = means @ w2c[2, :3] + w2c[2, 3]
        focal = math.sqrt(float(cam.K[0, 0]) * float(cam.K[1, 1]))
        px2.append(torch.where(z > 0.05, (z / focal) ** 2, torch.nan))
        d = torch.nn.functional.normalize(means - torch.linalg.inv(w2c)[:3, 3], dim=1)
        fore.append(1 - torch.einsum("nk,nki->ni", d, axes) ** 2)
    return torch.stack(px2).nanmedian(0).values, torch.stack(fore).median(0).values.clamp(0.05, 1.0)


@torch.no_grad()
def compensate_viewer_dilation(model, cameras, rule: str = "3dgs") -> None:
    """Rewrite the scales and opacities of `model` (in place) so that a viewer that adds VIEWER_DILATION px^2 to each
    splat draws it about as splatzoo does, at the scale the surfel was trained at (`training_view_scale`).

    s_i, axis i's variance on screen (px^2), becomes s_i' = max(s_i - (0.3 - f), s_i / 4), f the model's own footprint
    (0.1 px^2 when anti-aliased, else 0); the opacity keeps the splat's mass on screen (o sqrt(s0 s1)): rule "3dgs"
    (the viewer keeps the opacity) o' = o sqrt(s0 s1 / ((s0' + 0.3)(s1' + 0.3))), rule "mip" (the viewer rescales it
    by sqrt(s0' s1' / ((s0' + 0.3)(s1' + 0.3))), as Spark does) o' = o sqrt(s0 s1 / (s0' s1')); at most 0.99.

    A model none of whose surfels the cameras see (model_checks.check_in_view), or that would come out with every
    opacity below 1/255, is refused before anything changes: its file would show nothing."""
    from .geometry import quat_to_rotmat

    if rule not in VIEWER_RULES[1:]:
        raise SplatzooError(f"unknown viewer rule {rule!r}; known: {', '.join(VIEWER_RULES[1:])}")
    per = model.per_primitive()
    if "log_scales" not in per or "logit_opacity" not in per or "quats" not in per:
        raise SplatzooError(f"model {model.name!r} has no log_scales, logit_opacity and quats to compensate")
    means, quats = per["means"].double().cpu(), per["quats"].double().cpu()
    cameras = list(cameras)
    # a model no camera sees would be sized by guesswork and come out invisible: refused, saying where it is
    check_in_view(model, cameras, f"ply:viewer={rule} of the {model.name} model", fix=_VIEWER_FIX)
    axes = quat_to_rotmat(torch.nn.functional.normalize(quats, dim=1))[:, :, :2]
    px2, fore = training_view_scale(means, axes, cameras)
    px2 = torch.nan_to_num(px2, nan=float(px2.nanmedian()) if px2.isfinite().any() else 1.0)
    footprint = model.raster_settings.pixel_filter if getattr(model, "antialias", False) else 0.0
    log_scales = per["log_scales"].double().cpu()
    s = torch.exp(2 * log_scales) / px2[:, None] * fore
    shrunk = torch.maximum(s - (VIEWER_DILATION - footprint), s / 4)
    kept = s.prod(1) / ((shrunk + VIEWER_DILATION).prod(1) if rule == "3dgs" else shrunk.prod(1))
    opacity = (torch.sigmoid(per["logit_opacity"].double().cpu()) * kept.sqrt()).clamp(1e-6, 0.99)
    if float(opacity.max()) < model.raster_settings.alpha_min:
        raise SplatzooError(f"ply:viewer={rule}: made for the viewer's dilation, every one of the {model.name} "
                            f"model's {model.num_primitives} surfels would have an opacity below 1/255 (each is far "
                            f"under a pixel in the training views), so the file would show nothing. {_VIEWER_FIX}")
    new_scales = 0.5 * torch.log(shrunk * px2[:, None] / fore)
    like = per["log_scales"]
    model.replace_parameters({"log_scales": new_scales.to(like), "logit_opacity":
                              torch.logit(opacity).to(per["logit_opacity"])})


def export_ply(source, out, *, progress=None, ascii: bool = False, viewer: str = "exact") -> Path:
    """The `ply` format: the layout of the module docstring, which `load_ply` reads back exactly (viewer="exact"), or
    made for a viewer's dilation rule (`compensate_viewer_dilation`, from the run's training cameras)."""
    out = Path(out)
    if viewer not in VIEWER_RULES:
        raise SplatzooError(f"ply: viewer={viewer!r} is not known; use one of {', '.join(VIEWER_RULES)}")
    opened = open_model(source)
    model = opened.model
    check_export_target(EXPORTERS.get("ply"), out, opened.file)
    if viewer != "exact":
        if not Path(source).is_dir():
            raise SplatzooError(f"ply:viewer={viewer} sizes each surfel at its training cameras: export from the run "
                                f"folder, not the file {source}")
        compensate_viewer_dilation(model, [v.camera for v in Run(source).scene().train], viewer)
    path = save_ply(model, out, text=ascii, comments=[f"splatzoo viewer {viewer}"] if viewer != "exact" else ())
    if progress:
        progress(f"{model.num_primitives} {model.name} primitives" + (f", made for {viewer} viewers" if
                                                                       viewer != "exact" else ""))
    return path


def export_run(run, out) -> Path:
    """Export the trained model of a run directory, or a model .pt (or .ply) file, to the PLY `out`."""
    out = Path(out)
    check_export_target(EXPORTERS.get("ply"), out, _source_file(Path(run)))
    return export_ply(run, out)


@dataclass
class SpzOptions:
    version: int = field(default=3, metadata={
        "help": "SPZ version to write: 3 (gzip; what Spark 2.2 and most viewers read) or 4 (splat-transform and "
                "newer readers only)"})

    def __post_init__(self):
        if self.version not in (3, 4):
            raise ValueError(f"version must be 3 or 4, got {self.version}")


@dataclass
class SogOptions:
    sh_iterations: int = field(default=10, metadata={"help": "k-means iterations of the SH compression"})
    gpu: str = field(default="cpu", metadata={"help": "device of the compression: cpu, or a GPU adapter index "
                                                      "(see `splat-transform --list-gpus`)"})

    def __post_init__(self):
        if self.sh_iterations < 1:
            raise ValueError(f"sh_iterations must be at least 1, got {self.sh_iterations}")
        if self.gpu != "cpu" and not str(self.gpu).isdigit():
            raise ValueError(f"gpu must be cpu or an adapter index, got {self.gpu!r}")


def _converted(out_format: str):
    """The exporter of a model file format that model_files writes (through splat-transform): the format's options
    go to its writer."""
    def convert(source, out, *, progress=None, **options) -> Path:
        out = Path(out)
        opened = open_model(source)
        check_export_target(EXPORTERS.get(out_format), out, opened.file)
        return write_model(opened.model, out, format=out_format, progress=progress, **options)
    return convert


register_exporter(ExporterSpec(
    "ply", export_ply, PlyOptions, "the 3DGS/2DGS PLY every splat tool reads; splatzoo's own properties (Gabor "
    "waves, plugin parameters) ride along so load_ply restores the model exactly", (".ply",)))
register_exporter(ExporterSpec(
    "spz", _converted("spz"), SpzOptions,
    "Niantic's compressed splats (about 10x smaller), through PlayCanvas splat-transform; surfels as flat Gaussians, "
    "Gabor waves as their mean colour", (".spz",)))
register_exporter(ExporterSpec(
    "sog", _converted("sog"), SogOptions, "PlayCanvas SOG (WebP textures in one file, about 15-20x smaller), "
    "through splat-transform; Gabor waves as their mean colour", (".sog",)))
register_exporter(ExporterSpec(
    "compressed-ply", _converted("compressed-ply"), None,
    "PlayCanvas / SuperSplat compressed PLY (chunked, quantised), through splat-transform", (".compressed.ply",)))
register_exporter(ExporterSpec(
    "baked", "splatzoo.bake:export_baked", "splatzoo.bake:BakeOptions",
    "wave models baked into plain 2DGS surfels in a standard PLY, for viewers that know no Gabor waves", (".ply",)))
register_exporter(ExporterSpec(
    "glb-splat", "splatzoo.gltf_export:export_glb_splats", "splatzoo.gltf_export:GlbSplatOptions",
    "glTF 2.0 binary with the Khronos KHR_gaussian_splatting extension (PlayCanvas, Babylon.js, CesiumJS, three.js): "
    "surfels as ellipses with a flat third axis, flagged as surfels; rich members baked first", (".glb",)))
register_exporter(ExporterSpec(
    "mesh-glb", "splatzoo.mesh_texture:export_textured_mesh", "splatzoo.mesh_texture:TexturedMeshOptions",
    "a textured triangle mesh (glTF binary): the TSDF mesh with a UV atlas and a texture baked from the model's "
    "renders", (".glb",)))
register_exporter(ExporterSpec(
    "mesh-obj", "splatzoo.mesh_texture:export_textured_mesh", "splatzoo.mesh_texture:TexturedMeshOptions",
    "the textured mesh as OBJ + MTL + PNG (written beside each other)", (".obj",)))
