"""Structure from motion on the CPU with pycolmap: photos in, a COLMAP dataset out, checked.

SIFT features, exhaustive matching and incremental mapping. The result folder is what `load_scene` reads:
DATA/images/ (a copy of the photos), DATA/sparse/0/ (binary model) and DATA/database.db, plus the report
DATA/sfm_report.png (cameras and points from above, key numbers) and DATA/sfm_report.json. Cameras default to
SIMPLE_RADIAL, one shared by all photos of one size (one phone or camera), so load_scene undistorts them.

Before the model is written its cameras are checked (sfm_checks.py): a focal length far from the prior (EXIF, a
given --focal, else 1.2 x the larger image side), distortion that folds back inside the photo or is implausibly
strong, an undistorted image much larger than the photo, few photos registered. An implausible fit is mapped
again with SIMPLE_PINHOLE (one focal length, no distortion, principal point at the centre) from the same
features and matches, and the better of the two is kept; a fit that still folds is an error.
"""
from __future__ import annotations

import shutil
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import DataError
from ..io import write_json
from .camera_models import all_models, model_name, undistortable_models
from .colmap import import_pycolmap, quiet_colmap
from .scene import image_size, list_images
from .sfm_checks import SfMCheck, check_reconstruction, write_report_png
from .staging import finish_output, prepare_output, replace_dir, temp_dir_beside

SIMPLE_MODEL = "SIMPLE_PINHOLE"       # what an implausible fit is retried with
REPORT_PNG, REPORT_JSON = "sfm_report.png", "sfm_report.json"


@dataclass
class SfMResult:
    """What SfM did. Usable as a path (os.fspath) to the dataset folder."""

    path: Path
    num_images: int
    num_registered: int
    num_points: int
    mean_reprojection_error: float
    seconds: float
    reconstruction: object = None   # the pycolmap.Reconstruction
    check: SfMCheck | None = None   # the checks of the kept fit (findings: what is still doubtful)
    camera_model: str = ""          # the model of the kept fit
    retried: bool = False           # True when the first fit was implausible and SIMPLE_PINHOLE was tried

    def __fspath__(self) -> str:
        return str(self.path)

    def summary(self) -> str:
        focal = ""
        if self.check is not None and self.check.cameras:
            focal = "focal " + ", ".join(f"{c.focal:.0f}" for c in self.check.cameras) + f" px ({self.camera_model}), "
        return (f"registered {self.num_registered}/{self.num_images} images, {self.num_points} points, {focal}"
                f"reprojection error {self.mean_reprojection_error:.2f} px, {self.seconds:.1f} s -> {self.path}")


def similarity_align(src: np.ndarray, dst: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """Umeyama (1991) least-squares similarity: s, R, t minimising sum |s R src_i + t - dst_i|^2."""
    src, dst = np.asarray(src, np.float64), np.asarray(dst, np.float64)
    if len(src) < 3:
        raise DataError(f"a similarity alignment needs at least 3 point pairs, got {len(src)}")
    mu_s, mu_d = src.mean(0), dst.mean(0)
    xs, xd = src - mu_s, dst - mu_d
    cov = xd.T @ xs / len(src)
    U, S, Vt = np.linalg.svd(cov)
    D = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:   # reflection: flip the weakest axis
        D[2, 2] = -1
    R = U @ D @ Vt
    var_s = (xs ** 2).sum() / len(src)
    s = float(np.trace(np.diag(S) @ D) / var_s) if var_s > 0 else 1.0
    t = mu_d - s * R @ mu_s
    return s, R, t


def _say(progress):
    if callable(progress):
        return progress
    if progress:
        return lambda msg: print(msg, file=sys.stderr, flush=True)
    return lambda msg: None


def _check_images(images_dir: Path) -> list[Path]:
    images_dir = Path(images_dir)
    if not images_dir.exists():
        raise DataError(f"image folder {images_dir} does not exist; pass the folder that holds your photos")
    if not images_dir.is_dir():
        raise DataError(f"{images_dir} is a file; pass the folder that holds your photos")
    names = list_images(images_dir)
    if not names:
        raise DataError(f"image folder {images_dir} is empty (no .png/.jpg images); copy your photos there")
    if len(names) < 2:
        raise DataError(f"image folder {images_dir} holds only {len(names)} image; SfM needs at least 2 "
                        "overlapping photos (20+ around the subject works best)")
    for n in names:
        image_size(images_dir / n)        # corrupt files stop here, named, instead of deep inside COLMAP
    return names


def _camera_model(name: str) -> str:
    """The COLMAP camera model name, checked: SfM can fit it and load_scene can undistort it."""
    known = all_models()
    model = str(name).strip().upper()
    if model not in known:
        import difflib

        close = difflib.get_close_matches(model, known, n=1)
        raise DataError(f"unknown camera model {name!r}{f' (did you mean {close[0]}?)' if close else ''}; the usual "
                        "choices are SIMPLE_RADIAL (the default: one focal length, one radial term), SIMPLE_PINHOLE "
                        "(no distortion), PINHOLE, OPENCV (two radial and two tangential terms) and OPENCV_FISHEYE; "
                        f"pycolmap knows {', '.join(known)}")
    if model not in undistortable_models():
        raise DataError(f"camera model {model} cannot be undistorted into pinhole images, which training needs; "
                        f"choose one of {', '.join(undistortable_models())}")
    return model


def _priors(db_path: Path, focal: float | None) -> dict[int, tuple[float, str]]:
    """camera id -> (focal length SfM starts from, where it comes from), after feature extraction; with `focal`
    given, the database's cameras are set to it first."""
    pycolmap = import_pycolmap()
    priors = {}
    db = pycolmap.Database.open(str(db_path))
    try:
        for cam in db.read_all_cameras():
            if focal is not None:
                params = np.asarray(cam.params, dtype=np.float64)
                params[list(cam.focal_length_idxs())] = focal
                cam.params = params.tolist()
                cam.has_prior_focal_length = True
                db.update_camera(cam)
                priors[cam.camera_id] = (float(focal), "given")
            elif cam.has_prior_focal_length:
                priors[cam.camera_id] = (float(cam.mean_focal_length()), "from EXIF")
            else:
                priors[cam.camera_id] = (float(cam.mean_focal_length()), "the usual guess 1.2 x max(width, height)")
    finally:
        db.close()
    return priors


def _set_cameras(db_path: Path, cameras: dict[int, object]) -> dict[int, object]:
    """Replace the database's cameras (id -> pycolmap.Camera); returns the ones replaced."""
    pycolmap = import_pycolmap()
    db = pycolmap.Database.open(str(db_path))
    try:
        old = {c.camera_id: c for c in db.read_all_cameras()}
        for cam in cameras.values():
            db.update_camera(cam)
    finally:
        db.close()
    return old


def _simple_cameras(old: dict[int, object], priors: dict[int, tuple[float, str]]) -> dict[int, object]:
    pycolmap = import_pycolmap()
    out = {}
    for cid, cam in old.items():
        f = priors.get(cid, (1.2 * max(cam.width, cam.height), ""))[0]
        new = pycolmap.Camera(model=SIMPLE_MODEL, width=cam.width, height=cam.height,
                              params=[f, cam.width / 2, cam.height / 2], camera_id=cid)
        new.has_prior_focal_length = cam.has_prior_focal_length
        out[cid] = new
    return out


def _map(db: Path, images: Path, work: Path, *, num_threads: int, seed: int, refine_focal: bool, say):
    """Incremental mapping; the largest model (None when nothing registered) and how many models were made."""
    pycolmap = import_pycolmap()
    opts = pycolmap.IncrementalPipelineOptions()
    opts.num_threads = num_threads
    opts.random_seed = seed
    opts.ba_refine_focal_length = refine_focal
    opts.mapper.abs_pose_refine_focal_length = refine_focal
    count = [0]

    def next_image():  # called as the mapper moves on to each next image
        count[0] += 1
        if count[0] % 5 == 0:
            say(f"      mapping: {count[0]} images tried so far")
    try:
        models = pycolmap.incremental_mapping(db, images, work, options=opts, next_image_callback=next_image)
    finally:
        shutil.rmtree(work, ignore_errors=True)
    if not models:
        return None, 0
    return max(models.values(), key=lambda r: (r.num_reg_images(), r.num_points3D())), len(models)


def _say_check(say, check: SfMCheck) -> None:
    for line in check.lines():
        say("      " + line)


def sfm_in_place(dataset: Path, *, camera_model: str = "SIMPLE_RADIAL", single_camera: bool = True,
                 num_threads: int = -1, seed: int = 0, progress=None, focal: float | None = None,
                 retry: bool = True, report: bool = True) -> SfMResult:
    """Run SfM on dataset/images, writing dataset/database.db, dataset/sparse/0 (the largest model) and, with
    `report`, dataset/sfm_report.png and .json. See run_sfm for the options."""
    pycolmap = import_pycolmap()

    say = _say(progress)
    t0 = time.perf_counter()
    dataset = Path(dataset)
    images = dataset / "images"
    camera_model = _camera_model(camera_model)
    names = _check_images(images)
    sizes = {image_size(images / n) for n in names}
    if focal is not None:
        if isinstance(focal, bool) or not isinstance(focal, (int, float)) or not np.isfinite(focal) or focal <= 0:
            raise DataError(f"focal={focal!r}: give the focal length in pixels of the photos, a positive number "
                            "(for a 36 mm-equivalent lens of F mm: F / 36 x the photo's width)")
        if len(sizes) > 1:
            listing = ", ".join(f"{w}x{h}" for w, h in sorted(sizes))
            raise DataError(f"a focal length in pixels fits photos of one size, but {images} holds several "
                            f"({listing}); resize the photos to one size or leave out --focal")
        focal = float(focal)
    db = dataset / "database.db"
    db.unlink(missing_ok=True)
    if not single_camera:
        mode = pycolmap.CameraMode.PER_IMAGE
    else:  # one camera for all photos; AUTO groups them by size when sizes differ
        mode = pycolmap.CameraMode.SINGLE if len(sizes) == 1 else pycolmap.CameraMode.AUTO
    try:
        pycolmap.set_random_seed(seed)
        reader = pycolmap.ImageReaderOptions()
        reader.camera_model = camera_model
        extract = pycolmap.FeatureExtractionOptions()
        extract.num_threads = num_threads
        extract.use_gpu = False
        match = pycolmap.FeatureMatchingOptions()
        match.num_threads = num_threads
        match.use_gpu = False
        with quiet_colmap(2):  # its warnings are about GPU/threads/RAM, not about the result
            say(f"[1/3] extracting SIFT features from {len(names)} images ...")
            pycolmap.extract_features(db, images, camera_mode=mode, reader_options=reader,
                                      extraction_options=extract, device=pycolmap.Device.cpu)
            priors = _priors(db, focal)
            say(f"[2/3] matching {len(names) * (len(names) - 1) // 2} image pairs ...")
            pycolmap.match_exhaustive(db, matching_options=match, device=pycolmap.Device.cpu)
            say(f"[3/3] incremental mapping ({camera_model} camera) ...")
            # a given focal is held in every pass (refined, it drifts away: 230 px asked, 117-127 px found)
            rec, n_models = _map(db, images, dataset / ".sfm-models", num_threads=num_threads, seed=seed,
                                 refine_focal=focal is None, say=say)
            check = check_reconstruction(rec, priors, len(names)) if rec is not None else None
            if check is not None:
                _say_check(say, check)
            retried = False
            simpler = camera_model != SIMPLE_MODEL or focal is not None
            if retry and simpler and (check is None or check.implausible):
                retried = True
                why = "; ".join(f.message for f in check.implausible) if check else "nothing was registered"
                hold = f", focal length held at the given {focal:g} px" if focal is not None else ""
                say(f"the {camera_model} fit looks implausible ({why}); mapping again with {SIMPLE_MODEL} (one focal "
                    f"length, no distortion, principal point at the image centre{hold}) ...")
                old = _set_cameras(db, _simple_cameras(_read_cameras(db), priors))
                rec2, n2 = _map(db, images, dataset / ".sfm-models-retry", num_threads=num_threads, seed=seed,
                                refine_focal=focal is None, say=say)
                check2 = check_reconstruction(rec2, priors, len(names)) if rec2 is not None else None
                if check2 is not None:
                    _say_check(say, check2)
                # On a tie the simpler camera wins (it cannot fold, and has fewer ways to be wrong) unless it explains
                # the photos much worse, as it does for a lens with real distortion.
                if check2 is not None and (check is None or (
                        check2.rank() <= check.rank()
                        and check2.reprojection_error <= max(1.5 * check.reprojection_error,
                                                             check.reprojection_error + 0.5))):
                    say(f"kept the {SIMPLE_MODEL} fit")
                    rec, check, n_models = rec2, check2, n2
                else:
                    say(f"kept the {camera_model} fit (the {SIMPLE_MODEL} one is worse)")
                    _set_cameras(db, old)   # the database describes the model that is kept
    except DataError:
        raise
    except Exception as e:
        raise DataError(f"SfM failed on {images}: {e}") from None
    finally:
        for junk in (".sfm-models", ".sfm-models-retry"):
            shutil.rmtree(dataset / junk, ignore_errors=True)
    if rec is None:
        raise DataError(f"SfM registered no images in {images}: no image pair had enough matched features. "
                        "Take more photos with large overlap of a textured, static subject and run again")
    if rec.num_points3D() == 0:
        raise DataError(f"SfM on {images} triangulated no points; take photos with more texture and overlap")
    folds = [f for f in check.findings if f.what == "fold"]
    if folds:
        raise DataError(f"SfM on {images} found cameras that cannot be used: {folds[0].message}. Run it again with "
                        f"--camera-model {SIMPLE_MODEL}, and --focal PIXELS if you know the lens "
                        f"({'' if retry else 'or without --no-retry, '}nothing was written)")
    kept = ", ".join(sorted({model_name(c) for c in rec.cameras.values()}))
    for f in check.findings:
        say(("warning: the fit may be wrong: " if f.implausible else "warning: ") + f.message)
    if check.implausible:
        say("warning: check the cameras in the report before training; if you know the lens, run again with "
            f"--camera-model {SIMPLE_MODEL} --focal PIXELS. Fine repeated patterns and symmetric subjects mislead SfM: "
            "photos that also show some irregular texture help")
    out = dataset / "sparse" / "0"
    if out.parent.exists():
        shutil.rmtree(out.parent)
    out.mkdir(parents=True)
    rec.write_binary(str(out))
    res = SfMResult(dataset, len(names), rec.num_reg_images(), rec.num_points3D(),
                    float(rec.compute_mean_reprojection_error()), time.perf_counter() - t0, rec, check, kept, retried)
    if report:
        info = {"camera_model_asked": camera_model, "camera_model": kept, "retried": retried,
                "focal_given": focal, **check.to_json()}
        write_json(dataset / REPORT_JSON, info)
        if not retried:
            title = f"SfM with {kept} cameras"
        elif kept == camera_model:
            title = f"SfM with {kept} cameras (implausible, and a {SIMPLE_MODEL} retry was worse)"
        else:
            title = f"SfM with {kept} cameras (after an implausible {camera_model} fit)"
        write_report_png(rec, check, dataset / REPORT_PNG, title=title)
    if n_models > 1:
        say(f"note: SfM split the photos into {n_models} models; kept the largest")
    if res.num_registered < len(names):
        say(f"note: {len(names) - res.num_registered} image(s) could not be registered and are left out")
    return res


def _read_cameras(db_path: Path) -> dict[int, object]:
    pycolmap = import_pycolmap()
    db = pycolmap.Database.open(str(db_path))
    try:
        return {c.camera_id: c for c in db.read_all_cameras()}
    finally:
        db.close()


def run_sfm(images_dir, out_dir, *, progress=True, camera_model: str = "SIMPLE_RADIAL", single_camera: bool = True,
            num_threads: int = -1, seed: int = 0, overwrite: bool = False, focal: float | None = None,
            retry: bool = True, report: bool = True) -> SfMResult:
    """Recover cameras and a sparse point cloud from a folder of photos; write a COLMAP dataset to out_dir.

    camera_model: the COLMAP model to fit (SIMPLE_RADIAL; SIMPLE_PINHOLE, PINHOLE, OPENCV, OPENCV_FISHEYE, ...).
    focal: the focal length in pixels of the photos, when known: SfM starts from it (instead of EXIF or
    1.2 x the larger side) and the checks compare against it. retry: map again with SIMPLE_PINHOLE when the fit
    is implausible (holding the focal length at `focal` when given). report: write sfm_report.png / .json.
    progress: True prints steps to stderr, a callable receives each message, False is silent; the checks'
    findings are in the result's `check` either way.
    If images_dir is already out_dir/images the photos are not copied; only sparse/, database.db and the report
    are added. Nothing is written at out_dir until SfM has finished. Returns an SfMResult (also usable as a path).
    """
    say = _say(progress)
    images_dir, out_dir = Path(images_dir).expanduser(), Path(out_dir).expanduser()
    camera_model = _camera_model(camera_model)
    names = _check_images(images_dir)
    in_place = (out_dir / "images").exists() and (out_dir / "images").resolve() == images_dir.resolve()
    if in_place:
        if (out_dir / "sparse").exists() and not overwrite:
            raise DataError(f"{out_dir / 'sparse'} already exists; pass --overwrite to replace the model")
        tmp = temp_dir_beside(out_dir / "sparse")
    else:
        tmp = prepare_output(out_dir, overwrite)
    try:
        if in_place:
            (tmp / "images").symlink_to(images_dir.resolve(), target_is_directory=True)
        else:
            say(f"copying {len(names)} images to {out_dir / 'images'}")
            for n in names:
                dst = tmp / "images" / n
                dst.parent.mkdir(parents=True, exist_ok=True)
                shutil.copy2(images_dir / n, dst)
        try:
            res = sfm_in_place(tmp, camera_model=camera_model, single_camera=single_camera,
                               num_threads=num_threads, seed=seed, progress=say, focal=focal, retry=retry,
                               report=report)
        except DataError as e:  # name the user's folder, not our temporary copy
            raise DataError(str(e).replace(str(tmp / "images"), str(images_dir))) from None
        if in_place:
            (tmp / "images").unlink()
            replace_dir(tmp / "sparse", out_dir / "sparse")
            for name in ("database.db", REPORT_PNG, REPORT_JSON):
                if (tmp / name).exists():
                    (tmp / name).replace(out_dir / name)
                else:   # no stale report of an earlier run
                    (out_dir / name).unlink(missing_ok=True)
            shutil.rmtree(tmp, ignore_errors=True)
        else:
            finish_output(tmp, out_dir)
    finally:
        if tmp.exists():
            if (tmp / "images").is_symlink():
                (tmp / "images").unlink()
            shutil.rmtree(tmp, ignore_errors=True)
    res.path = out_dir
    say(res.summary())
    return res
