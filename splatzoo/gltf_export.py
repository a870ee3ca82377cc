"""The `glb-splat` export: any splatzoo model as a glTF KHR_gaussian_splatting file (splatzoo.gltf_splats holds the
file format, which stores plain surfels). Richer members are baked into plain surfels first (splatzoo.bake), and
viewer="3dgs" sizes the surfels for viewers that dilate every splat (splatzoo.export.compensate_viewer_dilation).
This module sits above both, so the file format below stays free of training code."""
from __future__ import annotations

import copy
from dataclasses import dataclass, field
from pathlib import Path

from .bake import BakeOptions, bake_model, bake_options, cameras_to_bake_from, orbit_cameras_around
from .errors import SplatzooError
from .export import compensate_viewer_dilation
from .gltf_splats import check_glb_path, save_glb_splats
from .model_files import open_model

VIEWER_RULES = ("exact", "3dgs")


def write_glb_splats(model, path, *, cameras=None, viewer: str = "exact", color: bool = True, bake=None,
                     progress=None) -> Path:
    """Write `model` to the .glb `path` (atomically) as KHR_gaussian_splatting splats, the layout of the module
    docstring. Returns the path.

    A plain `2dgs` model is written as it is. Any other model is baked into plain surfels first by
    `splatzoo.bake.bake_model`, fitted to its renders from `cameras` (a list of splatzoo Cameras, e.g. the run's
    training views; None: cameras around the model) with `bake` (a splatzoo.bake.BakeOptions, or a dict of its
    fields). viewer: "exact" writes the surfels as trained; "3dgs" sizes them for viewers that add 0.3 px^2 to each
    splat and keep its opacity (GaussianSplats3D-like; PlayCanvas draws the exact file closer to splatzoo, see the
    module docstring), at the scale `cameras` saw them
    (`splatzoo.export.compensate_viewer_dilation`; needs `cameras`). color: also write the COLOR_0 fallback.
    progress: a callable receiving messages, or True to print them."""
    if viewer not in VIEWER_RULES:
        raise SplatzooError(f"glb-splat: viewer={viewer!r} is not known; use one of {', '.join(VIEWER_RULES)}")
    path = check_glb_path(path)
    cameras = list(cameras) if cameras is not None else None
    if viewer != "exact" and not cameras:
        raise SplatzooError(f"glb-splat: viewer={viewer} sizes each surfel at the cameras that trained it: pass "
                            "cameras (the run's training views), or write viewer=exact")
    body = {"viewer": viewer}
    if getattr(model, "name", "") != "2dgs":
        options = bake if isinstance(bake, BakeOptions) else bake_options(**(bake or {}))
        source_name = getattr(model, "name", "") or type(model).__name__
        model, report = bake_model(model, cameras or orbit_cameras_around(model), options, progress=progress)
        body.update(bakedFrom=source_name, bakeDb=round(float(report["bake_db"]), 3))
    if viewer != "exact":
        model = copy.deepcopy(model)  # the caller's model keeps its surfels
        compensate_viewer_dilation(model, cameras, viewer)
    body = {"antialias": bool(getattr(model, "antialias", False)), **body}
    return save_glb_splats(model, path, color=color, surfel=body, progress=progress)


# --- the exporter ----------------------------------------------------------------------------------------------

def export_glb_splats(source, out, *, progress=None, viewer: str = "exact", color: bool = True, **bake) -> Path:
    """The `glb-splat` export: the model of `source` (a run folder or a model file) written to the .glb `out` by
    `write_glb_splats`, rich members baked from the run's training cameras (or cameras around the model), viewer
    "3dgs" sized at the training cameras (a run folder only). `bake`: splatzoo.bake.BakeOptions fields."""
    source, out = Path(source), Path(out)
    options = bake_options(**bake)
    if viewer != "exact" and not source.is_dir():
        raise SplatzooError(f"glb-splat:viewer={viewer} sizes each surfel at its training cameras: export from the "
                            f"run folder, not the file {source}")
    read = source / "model.pt" if source.is_dir() else source
    if out.exists() and out.resolve() == read.resolve():
        raise SplatzooError(f"refusing to export onto the model being read ({read}); choose another --out")
    opened = open_model(source, backend=options.backend)
    return write_glb_splats(opened.model, out, cameras=cameras_to_bake_from(opened), viewer=viewer, color=color,
                            bake=options, progress=progress)


@dataclass
class GlbSplatOptions(BakeOptions):
    """The options of the glb-splat export: the bake's (used for models other than 2dgs), viewer and color."""

    viewer: str = field(default="exact", metadata={
        "help": "exact: the trained surfels (read back exactly; what PlayCanvas draws closest to splatzoo); 3dgs: "
                "sized for viewers that add 0.3 px^2 to every splat and keep its opacity, from the run's training "
                "cameras"})
    color: bool = field(default=True, metadata={"help": "also write COLOR_0, the colour of readers that draw points"})

    def validate(self) -> GlbSplatOptions:
        super().validate()
        if self.viewer not in VIEWER_RULES:
            raise SplatzooError(f"glb-splat option viewer must be one of {', '.join(VIEWER_RULES)}, got "
                                f"{self.viewer!r}")
        return self
