"""Is an SfM result believable? Checks of the fitted cameras and the reconstruction before anything is undistorted,
and the report of what SfM found: key numbers as text and a picture of cameras and points seen from above.

SfM can end with every photo registered and a sub-pixel reprojection error and still be wrong: on fine repeated
texture without EXIF a focal length half the true one with a strong radial term explains the matches just as well,
and undistorting with it folds each photo into ghost rings. The checks look for what such a fit leaves behind.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from ..io import atomic_path
from .camera_models import model_name, projection_profile, undistorted_size

FOCAL_RANGE = (0.5, 2.0)        # found / prior focal length outside this: implausible
DISTORTION_WARN = 0.05          # radial displacement at the corners (fraction of the radius): worth a warning
DISTORTION_MAX = 0.15           # ... implausible for a non-fisheye photo
CANVAS_MAX = 2.0                # undistorted image area / photo area above this: implausible (non-fisheye)
MIN_REGISTERED = 0.5            # fraction of the photos registered below this: implausible
MIN_POINTS_PER_IMAGE = 50       # median 3D points seen per registered photo below this: a warning
MAX_REPROJECTION_PX = 2.0       # mean reprojection error above this: a warning


@dataclass
class Finding:
    what: str             # fold | focal | distortion | canvas | registered | points | reprojection
    message: str
    implausible: bool     # True: the fit is probably wrong (a simpler camera is worth a try); False: a warning


@dataclass
class CameraFit:
    """One fitted camera next to what was expected of it."""

    camera_id: int
    model: str
    width: int
    height: int
    params: dict[str, float]
    focal: float                   # mean focal length found, pixels
    prior: float                   # the focal length SfM started from, pixels
    prior_source: str              # EXIF, given, or the usual guess
    fold_px: float | None          # see camera_models.projection_profile
    corner_px: float
    corner_distortion: float | None
    canvas: tuple[int, int] | None  # size of the undistorted image
    fisheye: bool = False

    @property
    def focal_ratio(self) -> float:
        return self.focal / self.prior


@dataclass
class SfMCheck:
    """What a reconstruction looks like, and what is wrong with it."""

    model: str
    cameras: list[CameraFit]
    num_images: int
    num_registered: int
    num_points: int
    points_per_image_median: float
    points_per_image_min: int
    reprojection_error: float
    findings: list[Finding] = field(default_factory=list)

    @property
    def implausible(self) -> list[Finding]:
        return [f for f in self.findings if f.implausible]

    @property
    def warnings(self) -> list[Finding]:
        return [f for f in self.findings if not f.implausible]

    def rank(self) -> tuple:
        """Smaller is better: no fold (unusable), fewer implausible findings, more photos registered."""
        folds = any(f.what == "fold" for f in self.findings)
        return (folds, len(self.implausible), -self.num_registered)

    def lines(self) -> list[str]:
        """The key numbers, a few lines of text."""
        out = []
        for c in self.cameras:
            terms = ", ".join(f"{k} {v:.4g}" for k, v in c.params.items()
                              if k not in ("f", "fx", "fy", "cx", "cy"))
            out.append(f"camera {c.camera_id} ({c.model}, {c.width}x{c.height}): focal {c.focal:.1f} px, prior "
                       f"{c.prior:.1f} px ({c.prior_source}): {c.focal_ratio:.2f}x")
            if c.fold_px is not None:
                shape = (f"folds back {c.fold_px:.0f} px from the centre, inside the photo (corners at "
                         f"{c.corner_px:.0f} px)")
            elif c.fisheye:
                shape = "fisheye projection"
            else:
                shape = f"{100 * (c.corner_distortion or 0.0):+.1f}% at the corners"
            canvas = ""
            if c.canvas and c.canvas != (c.width, c.height):
                area = c.canvas[0] * c.canvas[1] / (c.width * c.height)
                canvas = f"; undistorted image {c.canvas[0]}x{c.canvas[1]} ({area:.2f}x the photo's area)"
            out.append(f"  distortion {terms}: {shape}{canvas}" if terms or c.fisheye else "  no distortion")
        out.append(f"{self.num_registered}/{self.num_images} photos registered, {self.num_points} points, points per "
                   f"photo: median {self.points_per_image_median:.0f} (min {self.points_per_image_min}), "
                   f"reprojection error {self.reprojection_error:.2f} px")
        return out

    def to_json(self) -> dict:
        d = asdict(self)
        d["implausible"] = [f.message for f in self.implausible]
        d["warnings"] = [f.message for f in self.warnings]
        return d


def check_reconstruction(rec, priors: dict[int, tuple[float, str]], num_images: int) -> SfMCheck:
    """Assess a pycolmap.Reconstruction. priors: camera id -> (focal length in pixels SfM started from, its source)."""
    registered = [im for im in rec.images.values() if im.has_pose]
    used = sorted({im.camera_id for im in registered})
    fits = []
    for cid in used:
        cam = rec.cameras[cid]
        prior, source = priors.get(cid, (1.2 * max(cam.width, cam.height), "the usual guess 1.2 x max(width, height)"))
        names = [n.strip() for n in cam.params_info.split(",")]
        prof = projection_profile(cam)
        fits.append(CameraFit(cid, model_name(cam), cam.width, cam.height,
                              {n: float(v) for n, v in zip(names, cam.params)}, float(cam.mean_focal_length()),
                              float(prior), source, prof["fold_px"], prof["corner_px"], prof["corner_distortion"],
                              undistorted_size(cam), bool(cam.is_perspective_fisheye())))
    per_image = [im.num_points3D for im in registered] or [0]
    check = SfMCheck(model=", ".join(sorted({f.model for f in fits})) or "none", cameras=fits, num_images=num_images,
                     num_registered=len(registered), num_points=rec.num_points3D(),
                     points_per_image_median=float(np.median(per_image)), points_per_image_min=int(min(per_image)),
                     reprojection_error=float(rec.compute_mean_reprojection_error()) if registered else float("nan"))
    check.findings = _findings(check)
    return check


def _findings(c: SfMCheck) -> list[Finding]:
    out = []
    several = len(c.cameras) > 1
    for cam in c.cameras:
        who = f"camera {cam.camera_id}: " if several else ""
        if cam.fold_px is not None:
            out.append(Finding("fold", f"{who}the fitted {cam.model} distortion folds back {cam.fold_px:.0f} px from "
                                       f"the image centre, inside the photo (whose corners are {cam.corner_px:.0f} px "
                                       "away): undistorting would fold each photo onto itself (ghost rings)", True))
        lo, hi = FOCAL_RANGE
        if not lo <= cam.focal_ratio <= hi:
            out.append(Finding("focal", f"{who}the focal length found, {cam.focal:.0f} px, is {cam.focal_ratio:.2f}x "
                                        f"the prior {cam.prior:.0f} px ({cam.prior_source}); outside {lo}x..{hi}x "
                                        "it is more likely a wrong fit than the lens", True))
        d = cam.corner_distortion
        if d is not None and abs(d) > DISTORTION_WARN:
            strong = abs(d) > DISTORTION_MAX
            verdict = "implausible" if strong else "strong"
            out.append(Finding("distortion", f"{who}the fitted distortion moves the photo's corners by {100 * d:+.0f}% "
                                             f"of their distance from the centre ({verdict} for a non-fisheye lens)",
                               strong))
        if cam.canvas is not None:
            grow = cam.canvas[0] * cam.canvas[1] / (cam.width * cam.height)
            if grow > CANVAS_MAX:
                out.append(Finding("canvas", f"{who}undistorting would turn the {cam.width}x{cam.height} photos into "
                                             f"{cam.canvas[0]}x{cam.canvas[1]} images ({grow:.1f}x the area)",
                                   not cam.fisheye))
    if c.num_images and c.num_registered < MIN_REGISTERED * c.num_images:
        out.append(Finding("registered", f"only {c.num_registered} of {c.num_images} photos were registered", True))
    if c.num_registered and c.points_per_image_median < MIN_POINTS_PER_IMAGE:
        out.append(Finding("points", f"few points per photo (median {c.points_per_image_median:.0f}, under "
                                     f"{MIN_POINTS_PER_IMAGE}): the poses rest on little evidence; larger, sharper "
                                     "photos of a more textured subject help", False))
    if c.reprojection_error > MAX_REPROJECTION_PX:
        out.append(Finding("reprojection", f"mean reprojection error {c.reprojection_error:.2f} px (over "
                                           f"{MAX_REPROJECTION_PX} px)", False))
    return out


# --- the picture ------------------------------------------------------------------------------------------------

def write_report_png(rec, check: SfMCheck, path: Path, title: str = "") -> Path:
    """Cameras (frusta, pointing where they look) and points, seen from above, with the key numbers beside them.

    "Above" is against the mean of the cameras' up directions (their -y axes), the best guess of the world's up
    in an SfM frame that has none."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    ims = [im for im in rec.images.values() if im.has_pose]
    poses = [np.asarray(im.cam_from_world().matrix(), dtype=np.float64) for im in ims]
    centers = np.array([-P[:3, :3].T @ P[:3, 3] for P in poses]).reshape(-1, 3)
    up = -np.array([P[1, :3] for P in poses]).reshape(-1, 3).mean(0)
    up = up / np.linalg.norm(up) if np.linalg.norm(up) > 1e-9 else np.array([0.0, 0.0, 1.0])
    a = np.cross(up, [1.0, 0, 0] if abs(up[0]) < 0.9 else [0, 1.0, 0])
    a /= np.linalg.norm(a)
    b = np.cross(up, a)

    def plane(p):  # world points [N,3] -> coordinates on the ground plane [N,2]
        return np.stack([p @ a, p @ b], -1)

    ids = list(rec.points3D.keys())
    xyz = np.array([rec.points3D[i].xyz for i in ids]).reshape(-1, 3)
    rgb = np.array([rec.points3D[i].color for i in ids]).reshape(-1, 3) / 255.0
    fig, (ax, tx) = plt.subplots(1, 2, figsize=(11, 6), gridspec_kw={"width_ratios": [3, 2]})
    if len(xyz):
        # Keep the bulk of the cloud in view: far outliers would shrink everything else to a dot.
        lo, hi = np.percentile(xyz, 1, axis=0), np.percentile(xyz, 99, axis=0)
        keep = np.all((xyz >= lo - 0.1 * (hi - lo)) & (xyz <= hi + 0.1 * (hi - lo)), axis=1)
        p2 = plane(xyz[keep])
        ax.scatter(p2[:, 0], p2[:, 1], s=4, c=np.clip(rgb[keep], 0, 1), linewidths=0)
    span = np.ptp(plane(np.concatenate([centers, xyz[keep] if len(xyz) else centers])), axis=0).max()
    size = 0.08 * (span if span > 0 else 1.0)
    for im, P, c in zip(ims, poses, centers):
        cam = rec.cameras[im.camera_id]
        R = P[:3, :3]
        hw = 0.5 * cam.width / cam.focal_length_x
        corners = [c + size * R.T @ np.array([sx * hw, 0.0, 1.0]) for sx in (-1, 1)]
        tri = plane(np.array([corners[0], c, corners[1]]))
        ax.plot(tri[:, 0], tri[:, 1], color="tab:red", lw=1)
    if len(centers):
        c2 = plane(centers)
        ax.scatter(c2[:, 0], c2[:, 1], s=8, color="tab:red", zorder=3)
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_title(f"{len(ims)} cameras (red: centre and field of view) and {len(xyz)} points, seen from above")
    ax.set_xticks([])
    ax.set_yticks([])
    tx.axis("off")
    text = [title] if title else []
    text += check.lines()
    if check.findings:
        text += [""] + [("implausible: " if f.implausible else "warning: ") + f.message for f in check.findings]
    import textwrap

    wrapped = "\n".join(textwrap.fill(t, 60, subsequent_indent="    ") if t else "" for t in text)
    tx.text(0, 1, wrapped, va="top", ha="left", family="monospace", fontsize=7.5, transform=tx.transAxes)
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=110, format="png")
    plt.close(fig)
    return Path(path)
