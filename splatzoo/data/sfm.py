"""Structure from motion on the CPU with pycolmap: photos in, a COLMAP dataset out.

SIFT features, exhaustive matching and incremental mapping. The result folder is what `load_scene` reads:
DATA/images/ (a copy of the photos), DATA/sparse/0/ (binary model) and DATA/database.db. Cameras default to
SIMPLE_RADIAL, one shared by all photos of one size (one phone or camera), so load_scene undistorts them.
"""
from __future__ import annotations

import shutil
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import DataError
from .colmap import import_pycolmap, quiet_colmap
from .scene import image_size, list_images
from .staging import prepare_output, finish_output, replace_dir, temp_dir_beside


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

    def __fspath__(self) -> str:
        return str(self.path)

    def summary(self) -> str:
        return (f"registered {self.num_registered}/{self.num_images} images, {self.num_points} points, "
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


def sfm_in_place(dataset: Path, *, camera_model: str = "SIMPLE_RADIAL", single_camera: bool = True,
                 num_threads: int = -1, seed: int = 0, progress=None) -> SfMResult:
    """Run SfM on dataset/images, writing dataset/database.db and dataset/sparse/0 (the largest model)."""
    pycolmap = import_pycolmap()
    say = _say(progress)
    t0 = time.perf_counter()
    dataset = Path(dataset)
    images = dataset / "images"
    names = _check_images(images)
    db = dataset / "database.db"
    db.unlink(missing_ok=True)
    sizes = {image_size(images / n) for n in names}
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
            say(f"[2/3] matching {len(names) * (len(names) - 1) // 2} image pairs ...")
            pycolmap.match_exhaustive(db, matching_options=match, device=pycolmap.Device.cpu)
            say("[3/3] incremental mapping ...")
            opts = pycolmap.IncrementalPipelineOptions()
            opts.num_threads = num_threads
            opts.random_seed = seed
            count = [0]

            def next_image():  # called as the mapper moves on to each next image
                count[0] += 1
                if count[0] % 5 == 0:
                    say(f"      mapping: {count[0]} images tried so far")
            work = dataset / ".sfm-models"
            models = pycolmap.incremental_mapping(db, images, work, options=opts, next_image_callback=next_image)
    except DataError:
        raise
    except Exception as e:
        raise DataError(f"SfM failed on {images}: {e}") from None
    finally:
        shutil.rmtree(dataset / ".sfm-models", ignore_errors=True)
    if not models:
        raise DataError(f"SfM registered no images in {images}: no image pair had enough matched features. "
                        "Take more photos with large overlap of a textured, static subject and run again")
    rec = max(models.values(), key=lambda r: (r.num_reg_images(), r.num_points3D()))
    if rec.num_points3D() == 0:
        raise DataError(f"SfM on {images} triangulated no points; take photos with more texture and overlap")
    out = dataset / "sparse" / "0"
    if out.parent.exists():
        shutil.rmtree(out.parent)
    out.mkdir(parents=True)
    rec.write_binary(str(out))
    res = SfMResult(dataset, len(names), rec.num_reg_images(), rec.num_points3D(),
                    float(rec.compute_mean_reprojection_error()), time.perf_counter() - t0, rec)
    if len(models) > 1:
        say(f"note: SfM split the photos into {len(models)} models; kept the largest")
    if res.num_registered < len(names):
        say(f"note: {len(names) - res.num_registered} image(s) could not be registered and are left out")
    return res


def run_sfm(images_dir, out_dir, *, progress=True, camera_model: str = "SIMPLE_RADIAL", single_camera: bool = True,
            num_threads: int = -1, seed: int = 0, overwrite: bool = False) -> SfMResult:
    """Recover cameras and a sparse point cloud from a folder of photos; write a COLMAP dataset to out_dir.

    progress: True prints steps to stderr, a callable receives each message, False is silent.
    If images_dir is already out_dir/images the photos are not copied; only sparse/ and database.db are added.
    Nothing is written at out_dir until SfM has finished. Returns an SfMResult (also usable as a path).
    """
    say = _say(progress)
    images_dir, out_dir = Path(images_dir).expanduser(), Path(out_dir).expanduser()
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
                               num_threads=num_threads, seed=seed, progress=say)
        except DataError as e:  # name the user's folder, not our temporary copy
            raise DataError(str(e).replace(str(tmp / "images"), str(images_dir))) from None
        if in_place:
            (tmp / "images").unlink()
            replace_dir(tmp / "sparse", out_dir / "sparse")
            (tmp / "database.db").replace(out_dir / "database.db")
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
