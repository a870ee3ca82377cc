"""Whether a model can draw anything: the one check every way into splatzoo applies to a model (a model file, a PLY,
a splat file read through splat-transform), and the checks of a model against the dataset it is to be scored,
rendered or trained on.

- `drawing_problem(model)`: why the model, as its parameters stand, draws nothing from anywhere (0 surfels, every
  position non-finite, every opacity below what the rasterizer draws, every surfel collapsed to a point), or None.
  `check_draws` refuses such a model by name.
- `repair_geometry(model)`: what a file's surfels hold that the rasterizer would otherwise change without a word
  (a zero quaternion, a log-scale beyond the largest size drawn, some surfels collapsed to a point), each as a note
  with its count; zero quaternions are made the identity, which is what they were drawn as.
- `check_fits_scene(model, scene, what)`: a model none of whose surfels any training camera sees, or with more
  surfels than the training views have pixels, refused with the count and the bound.
"""
from __future__ import annotations

import math

import torch

from .errors import SplatzooError

# A surfel whose log-scales (log sigma) both lie below this has collapsed to a point: a size under 1e-13 of the scene's
# units, which viewers store as exactly zero (Spark encodes a scale below exp(-30) as 0). With the pixel-footprint
# filter it draws nothing at all.
COLLAPSED_LOG_SCALE = -30.0
# No training camera sees a surfel farther than this many scene extents (the radius of the camera centres): there a
# surfel the size of the scene covers well under a pixel of any photo, and positions in float32 lose their meaning.
DEPTH_LIMIT_EXTENTS = 1e4
# A surfel's centre counts as in view within this many image sizes of the image's edge (a large surfel just outside
# the frame still covers it).
VIEW_MARGIN = 1.0
# A model may hold at most this many surfels per training pixel of the dataset it is fitted, scored or rendered on.
SURFELS_PER_PIXEL = 1
# A quaternion shorter than this is no rotation: the rasterizer normalises it by at least this length, so it is
# drawn as (close to) the identity.
ZERO_QUATERNION = 1e-12


def _per_primitive(model) -> dict[str, torch.Tensor]:
    per = model.per_primitive() if hasattr(model, "per_primitive") else dict(model.named_parameters())
    return {k: v.detach() for k, v in per.items()}


def drawing_problem(model) -> str | None:
    """Why `model` draws nothing from any camera, naming the parameter and the count; None when it can draw."""
    try:
        n = model.num_primitives
    except StopIteration:  # a plugin without per-primitive tensors: nothing to count
        return None
    if n == 0:
        return "it holds 0 surfels, so it draws nothing (there is nothing to score, view, export or train from)"
    per = _per_primitive(model)
    means = per.get("means")
    if means is not None and means.dim() == 2 and means.shape[0] == n:
        finite = torch.isfinite(means).all(1)
        if not bool(finite.any()):
            return (f"means: every one of its {n} surfels has a non-finite (NaN or inf) position, so it draws nothing "
                    "(the run diverged or the file is damaged)")
    why = model.draws_nothing() if hasattr(model, "draws_nothing") else None
    if why:
        return why
    log_scales = per.get("log_scales")
    if log_scales is not None and log_scales.dim() == 2 and log_scales.shape[0] == n and log_scales.shape[1]:
        largest = log_scales.double().amax(1)
        if bool((largest < COLLAPSED_LOG_SCALE).all()):
            return (f"log_scales: every one of its {n} surfels has collapsed to a point (log-scales at most "
                    f"{float(largest.max()):.4g}, below {COLLAPSED_LOG_SCALE:g}: a size under "
                    f"{math.exp(COLLAPSED_LOG_SCALE):.0e}), so it draws nothing and cannot learn (the run diverged or "
                    "the file is damaged)")
    return None


def check_draws(model, where: str, fix: str) -> None:
    """Refuse a model that draws nothing (`drawing_problem`): a SplatzooError "`where`: the problem; `fix`"."""
    problem = drawing_problem(model)
    if problem:
        raise SplatzooError(f"{where}: {problem}; {fix}")


@torch.no_grad()
def repair_geometry(model) -> list[str]:
    """Notes, each with its count, on what the model's surfels hold that the rasterizer changes: zero quaternions
    (set here to the identity, the rotation they were drawn with), log-scales above the largest size drawn (drawn at
    that size) and surfels collapsed to a point (drawn as a pixel-sized dot at most). Empty when there is nothing to
    say. For models read from files: a trained model holds none of these."""
    from .models.base import LOG_MAX_SCALE

    notes = []
    per = _per_primitive(model)
    n = model.num_primitives
    quats = per.get("quats")
    if quats is not None and quats.dim() == 2 and quats.shape[1] == 4 and n:
        zero = quats.double().norm(dim=1) < ZERO_QUATERNION
        if bool(zero.any()):
            fixed = quats.clone()
            fixed[zero] = torch.tensor([1.0, 0.0, 0.0, 0.0], dtype=fixed.dtype, device=fixed.device)
            model.replace_parameters({"quats": fixed})
            notes.append(f"{int(zero.sum())} of its {n} surfels have a zero rotation quaternion (no orientation); "
                         "they were given the identity rotation (facing +z), which is how they would be drawn. "
                         "Check the tool that wrote the file")
    log_scales = per.get("log_scales")
    if log_scales is not None and log_scales.dim() == 2 and log_scales.shape[1] and n:
        s = log_scales.double()
        huge = (s > LOG_MAX_SCALE).any(1)
        if bool(huge.any()):
            notes.append(f"{int(huge.sum())} of its {n} surfels have log-scales above {LOG_MAX_SCALE:.4g} (largest "
                         f"{float(s.max()):.4g}): they are drawn at the largest size the rasterizer draws, "
                         f"{math.exp(LOG_MAX_SCALE):.0e}, across every view. Remove them (or export the model again)")
        collapsed = s.amax(1) < COLLAPSED_LOG_SCALE
        if bool(collapsed.any()) and not bool(collapsed.all()):
            notes.append(f"{int(collapsed.sum())} of its {n} surfels have collapsed to a point (log-scales below "
                         f"{COLLAPSED_LOG_SCALE:g}): they draw at most a dot, nothing with the pixel-footprint filter. "
                         "Remove them (or export the model again)")
    return notes


# --- a model against a dataset -----------------------------------------------------------------------------------

def _training_views(scene) -> list:
    return list(scene.train) or list(getattr(scene, "test", []))


PIXELS_PER_SURFEL = 128       # densification's default budget: one surfel per this many training pixels


def densify_budget(scene, initial: int) -> int:
    """The primitive count densification may reach when --max-primitives is not given: one surfel per
    PIXELS_PER_SURFEL training pixels (3DGS's converged scenes hold about one Gaussian per 100), and at least
    twice the initial count."""
    pixels = sum(v.camera.width * v.camera.height for v in scene.train)
    return max(pixels // PIXELS_PER_SURFEL, 2 * initial)


def surfel_limit(scene) -> int:
    """The most surfels a model fitted, scored or rendered on `scene` may hold: SURFELS_PER_PIXEL per pixel of its
    training views."""
    return SURFELS_PER_PIXEL * sum(v.camera.width * v.camera.height for v in _training_views(scene))


def check_surfel_count(model, scene, what: str) -> None:
    """Refuse a model with more surfels than the scene's training views have pixels (`surfel_limit`), naming the
    count and the bound: such a model cannot be fitted to those images, and drawing it costs far more than they are
    worth (an evaluation of ten million surfels on a 64x64 dataset seems to hang)."""
    views = _training_views(scene)
    n, limit = model.num_primitives, surfel_limit(scene)
    if n > limit:
        sizes = sorted({f"{v.camera.width}x{v.camera.height}" for v in views})
        raise SplatzooError(
            f"{what}: its {n:,} surfels are more than the {limit:,} pixels of the dataset's {len(views)} training "
            f"view(s) ({', '.join(sizes[:3])}{' ...' if len(sizes) > 3 else ''}): at most {SURFELS_PER_PIXEL} surfel "
            f"per training pixel can be fitted to or seen in them (training grows a model to one surfel per "
            f"{PIXELS_PER_SURFEL} pixels, {densify_budget(scene, 0):,} here). Use the dataset the model was made for "
            "(or a higher --resolution), or a model with fewer surfels")


@torch.no_grad()
def seen_surfels(means: torch.Tensor, cameras, *, near: float, far: float, margin: float = VIEW_MARGIN) -> torch.Tensor:
    """[N] bool: which surfel centres (means [N,3]) some camera sees, in front of it between depths `near` and `far`
    and within `margin` image sizes of its image."""
    means = means.detach().cpu().double()
    seen = torch.zeros(means.shape[0], dtype=torch.bool)
    for cam in cameras:
        w2c = cam.world_to_camera.detach().double().cpu()
        K = cam.K.detach().double().cpu()
        z = means @ w2c[2, :3] + w2c[2, 3]
        rows = ((z > near) & (z < far) & ~seen).nonzero().squeeze(1)  # NaN is never in range
        if not rows.numel():
            continue
        p, z = means[rows] @ w2c[:2, :3].T + w2c[:2, 3], z[rows]
        u = (K[0, 0] * p[:, 0] + K[0, 1] * p[:, 1]) / z + K[0, 2]
        v = K[1, 1] * p[:, 1] / z + K[1, 2]
        inside = (u > -margin * cam.width) & (u < (1 + margin) * cam.width)
        inside &= (v > -margin * cam.height) & (v < (1 + margin) * cam.height)
        seen[rows[inside]] = True
    return seen


def depth_limit(cameras, points=None) -> float:
    """The farthest depth at which a training camera is taken to see a surfel: DEPTH_LIMIT_EXTENTS scene extents."""
    from .data.scene import camera_extent

    return DEPTH_LIMIT_EXTENTS * camera_extent(list(cameras), points)


def check_in_view(model, cameras, what: str, *, far: float | None = None,
                  fix: str = "Use the dataset the model was made for, or bring the model into this dataset's frame "
                             "(the same coordinates and units as its cameras)") -> None:
    """Refuse a model none of whose surfels lies in front of any of `cameras` (the training cameras), within
    `far` (default: `depth_limit`) and near the image: it draws nothing there, so scores, renders and training from
    it mean nothing. The message says where the surfels are and where the cameras look."""
    cameras = list(cameras)
    per = _per_primitive(model)
    means = per.get("means")
    if not cameras or means is None or means.dim() != 2 or means.shape[1] != 3 or not means.shape[0]:
        return
    settings = getattr(model, "raster_settings", None)
    near = float(getattr(settings, "near", 0.2))
    far = depth_limit(cameras) if far is None else far
    m = means.cpu().double()
    # the cameras one at a time: a model in view is usually seen by the first, so this stops early
    for cam in cameras:
        if bool(seen_surfels(m, [cam], near=near, far=far).any()):
            return
    m = m[torch.isfinite(m).all(1)]
    centres = torch.stack([c.center.detach().double().cpu() for c in cameras])
    middle = centres.mean(0)
    where = ""
    if m.shape[0]:
        centre = m.median(0).values
        distance = float((m - middle).norm(dim=1).min())
        where = (f" (their median position ({', '.join(f'{x:.4g}' for x in centre.tolist())}), the nearest "
                 f"{distance:.4g} from the cameras' centre ({', '.join(f'{x:.4g}' for x in middle.tolist())}))")
    raise SplatzooError(f"{what}: none of its {model.num_primitives:,} surfels lies in front of any of the "
                        f"{len(cameras)} training camera(s), between depth {near:g} and {far:.4g} and within the "
                        f"image{where}, so it draws nothing in these views. {fix}")


def check_fits_scene(model, scene, what: str) -> None:
    """Refuse a model that cannot be scored, rendered or trained on `scene` (its training views): more surfels than
    the views have pixels (`check_surfel_count`), or none of its surfels in front of a training camera within
    DEPTH_LIMIT_EXTENTS scene extents (`check_in_view`). `what` names the model in the message (e.g.
    "--init-from model.ply")."""
    check_surfel_count(model, scene, what)
    views = _training_views(scene)
    far = DEPTH_LIMIT_EXTENTS * float(scene.extent) if getattr(scene, "extent", None) else None
    check_in_view(model, [v.camera for v in views], what, far=far)
