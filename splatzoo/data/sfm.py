"""Structure from motion on the CPU with pycolmap: photos in, a COLMAP dataset out, checked.

SIFT features, matching of the image pairs a strategy chooses (below) and incremental mapping. The result folder is
what `load_scene` reads:
DATA/images/ (a copy of the photos), DATA/sparse/0/ (binary model) and DATA/database.db, plus the report
DATA/sfm_report.png (cameras and points from above, key numbers) and DATA/sfm_report.json. Cameras default to
SIMPLE_RADIAL, one shared by all photos of one size (one phone or camera), so load_scene undistorts them.

Before the model is written its cameras are checked (sfm_checks.py): a focal length far from the prior (EXIF, a
given --focal, else 1.2 x the larger image side), distortion that folds back inside the photo or is implausibly
strong, an undistorted image much larger than the photo, few photos registered. An implausible fit is mapped
again with SIMPLE_PINHOLE (one focal length, no distortion, principal point at the centre) from the same
features and matches, and the better of the two is kept; a fit that still folds is an error.

Which pairs are matched (`matching`, as COLMAP recommends): `exhaustive` matches every pair (n(n-1)/2: fine for a few
dozen photos, hours for thousands); `sequential` matches each frame with its next 10 and its 2^k-th neighbours in
frame order, plus loop closure (every 10th frame is looked up in a vocabulary tree and matched with the frames most
like it, so a path that comes back to where it started closes); `vocabtree` matches each photo with the photos a
vocabulary tree finds most similar; `spatial` matches photos near each other by their GPS (EXIF). `auto` picks
exhaustive up to 40 photos, sequential for the frames of a video or file names numbered in sequence
(frame_0001.jpg, ...), and the vocabulary tree beyond. The vocabulary tree is built here from the photos' own SIFT
features (a few seconds; nothing is downloaded) unless a tree file is given (`vocab_tree`, e.g. COLMAP's
vocab_tree_flickr100K_words256K.bin). The chosen pairs are matched in chunks so progress and time left can be shown.
"""
from __future__ import annotations

import contextlib
import itertools
import math
import os
import re
import shutil
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import DataError
from ..io import say_progress as _say, write_json
from .camera_models import all_models, model_name, undistortable_models
from .colmap import import_pycolmap, quiet_colmap
from .scene import image_size, list_images
from .sfm_checks import SfMCheck, check_reconstruction, write_report_png
from .staging import finish_output, prepare_output, replace_dir, temp_dir_beside

SIMPLE_MODEL = "SIMPLE_PINHOLE"       # what an implausible fit is retried with
REPORT_PNG, REPORT_JSON = "sfm_report.png", "sfm_report.json"

MATCHING = {
    "auto": "exhaustive up to 40 photos; sequential for video frames or numbered file names; vocabulary tree beyond",
    "exhaustive": "every pair of photos: the most thorough; n(n-1)/2 pairs, so for up to a few hundred photos",
    "sequential": "each frame with its next 10 and its 2^k-th neighbours in frame order, plus loop closure",
    "vocabtree": "each photo with the photos a vocabulary tree finds most like it (for hundreds of photos and more)",
    "spatial": "each photo with its nearest neighbours by GPS position (photos must carry GPS in their EXIF)",
}
EXHAUSTIVE_MAX = 40            # auto: exhaustive up to this many photos
SEQUENTIAL_OVERLAP = 10        # sequential: each frame with its next 10 (and its 2^k-th, k < 10)
LOOP_PERIOD = 10               # loop closure: every 10th frame is looked up in the vocabulary tree ...
LOOP_IMAGES = 25               # ... and matched with the 25 frames most like it
VOCAB_DESCRIPTORS = 50_000     # a tree built here: from at most this many descriptors ...
VOCAB_WORDS = 1024             # ... into at most this many visual words (about 2 s on 2 cores)


class VocabTreeError(DataError):
    """No usable vocabulary tree for image retrieval: the file given is not one, or none was given and this pycolmap
    cannot build one."""


@dataclass
class MatchingChoice:
    """The pairing strategy for a set of photos and why it was chosen."""

    strategy: str                       # exhaustive | sequential | vocabtree | spatial
    reason: str
    order: list[str] = field(default_factory=list)   # sequential: the names in frame order
    asked: str = "auto"


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
    matching: str = ""              # the pairing strategy used (exhaustive, sequential, vocabtree, spatial)
    num_pairs: int = 0              # image pairs matched
    stage_seconds: dict = field(default_factory=dict)   # extract, match, map: wall time of each stage

    def __fspath__(self) -> str:
        return str(self.path)

    def summary(self) -> str:
        focal = ""
        if self.check is not None and self.check.cameras:
            focal = "focal " + ", ".join(f"{c.focal:.0f}" for c in self.check.cameras) + f" px ({self.camera_model}), "
        pairs = f" ({self.matching} matching, {self.num_pairs} pairs)" if self.matching else ""
        return (f"registered {self.num_registered}/{self.num_images} images{pairs}, {self.num_points} points, {focal}"
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


# --- which pairs to match -----------------------------------------------------------------------------------------

_NUMBERED = re.compile(r"^(.*?)(\d+)(\D*)$")


def numbered_sequence(names) -> list[str] | None:
    """The names in frame order when they all follow one pattern with a running number (frame_0001.jpg ...,
    IMG_7.JPG, IMG_12.JPG: by number, not as text), else None."""
    names = [str(n) for n in names]
    if len(names) < 3:
        return None
    parsed = [_NUMBERED.match(n.replace("\\", "/")) for n in names]
    if not all(parsed):
        return None
    if len({(m.group(1), m.group(3).lower()) for m in parsed}) != 1:
        return None
    numbers = [int(m.group(2)) for m in parsed]
    if len(set(numbers)) != len(numbers):
        return None
    return [n for _, n in sorted(zip(numbers, names))]


def _unknown_matching(matching) -> DataError:
    import difflib

    close = difflib.get_close_matches(str(matching).strip().lower(), MATCHING, n=1)
    hint = f" (did you mean {close[0]}?)" if close else ""
    choices = "; ".join(f"{k}: {v}" for k, v in MATCHING.items())
    return DataError(f"unknown matching strategy {matching!r}{hint}; choose one of {', '.join(MATCHING)} ({choices})")


def choose_matching(names, matching: str = "auto", *, video: bool = False) -> MatchingChoice:
    """Which image pairs to match for these photo names (paths relative to the image folder).

    auto: the frames of a video (`video`), or more than EXHAUSTIVE_MAX names numbered in sequence, are matched
    sequentially; up to EXHAUSTIVE_MAX photos exhaustively; more, in no order, with a vocabulary tree."""
    asked = str(matching).strip().lower() if isinstance(matching, str) else matching
    if asked not in MATCHING:
        raise _unknown_matching(matching)
    names = [str(n) for n in names]
    numbered = numbered_sequence(names)
    order = numbered or sorted(names)
    n = len(names)
    if asked == "auto":
        if video:
            return MatchingChoice("sequential", "frames of a video", order, asked)
        if n <= EXHAUSTIVE_MAX:
            return MatchingChoice("exhaustive", f"{n} photos (up to {EXHAUSTIVE_MAX}: every pair)", order, asked)
        if numbered:
            return MatchingChoice("sequential", f"{n} photos with file names numbered in sequence "
                                  f"({numbered[0]} ... {numbered[-1]}); if they were not taken along a path, "
                                  "use --matching vocabtree or exhaustive", order, asked)
        return MatchingChoice("vocabtree", f"{n} photos (over {EXHAUSTIVE_MAX}) in no numbered order", order, asked)
    why = {"exhaustive": "asked", "sequential": "asked; frames in " + ("number order" if numbered else "name order"),
           "vocabtree": "asked", "spatial": "asked"}[asked]
    return MatchingChoice(asked, why, order, asked)


def sequential_pairs(order: list, overlap: int = SEQUENTIAL_OVERLAP, quadratic: bool = True) -> list[tuple]:
    """Each item with its next `overlap` and (quadratic) its 2^k-th neighbours, k < overlap: COLMAP's sequential
    pairs, in the order given (which need not be the names' text order)."""
    pairs = []
    n = len(order)
    for i in range(n):
        js = set(range(i + 1, min(n, i + overlap + 1)))
        if quadratic:
            js |= {i + 2 ** k for k in range(overlap) if i + 2 ** k < n}
        pairs += [(order[i], order[j]) for j in sorted(js)]
    return pairs


def _has_gps(path: Path) -> bool:
    from PIL import Image

    try:
        with Image.open(path) as im:
            gps = im.getexif().get_ifd(0x8825)
    except Exception:
        return False
    return bool(gps) and all(k in gps for k in (2, 4, 6))   # latitude, longitude, altitude: COLMAP reads all three


def check_spatial(images: Path, names) -> None:
    """`spatial` matching needs a position prior (GPS in EXIF) for the photos; refuse clearly when none has one."""
    with_gps = sum(_has_gps(Path(images) / n) for n in names)
    if with_gps == 0:
        raise DataError(f"--matching spatial pairs photos by their GPS positions, but none of the {len(names)} photos "
                        f"in {images} carries GPS (latitude, longitude and altitude) in its EXIF (screenshots, renders and "
                        "most edited or exported photos lose it); use --matching auto, sequential (frames in order), vocabtree or exhaustive")
    if with_gps < len(names):
        raise DataError(f"--matching spatial pairs photos by their GPS positions, but only {with_gps} of {len(names)} "
                        f"photos in {images} carry GPS in their EXIF; the others would match nothing. Use --matching "
                        "auto, vocabtree or exhaustive")


def check_vocab_tree(path) -> Path:
    """A vocabulary tree file the user gave: it must be a local file (a URL would make COLMAP download it)."""
    p = Path(path).expanduser()
    if not p.is_file():
        raise VocabTreeError(f"vocabulary tree {path} is not a file; give the path of a COLMAP vocabulary tree (.bin, "
                             "e.g. vocab_tree_flickr100K_words256K.bin from COLMAP's releases, downloaded by hand), or "
                             "leave out --vocab-tree to build one from the photos")
    return p


@contextlib.contextmanager
def quiet_stdio():
    """Silence what C++ code prints straight to the process's stdout/stderr (file descriptors 1 and 2)."""
    sys.stdout.flush()
    sys.stderr.flush()
    saved = []
    try:
        with open(os.devnull, "w") as null:
            for fd in (1, 2):
                saved.append((fd, os.dup(fd)))
                os.dup2(null.fileno(), fd)
            yield
    finally:
        for fd, copy in saved:
            os.dup2(copy, fd)
            os.close(copy)


def build_vocab_tree(db_path: Path, out: Path, *, num_threads: int = -1, seed: int = 0,
                     max_descriptors: int = VOCAB_DESCRIPTORS, max_words: int = VOCAB_WORDS) -> Path:
    """Build a small vocabulary tree from the SIFT descriptors in the database (a random sample of at most
    `max_descriptors`) and write it to `out`. Raises VocabTreeError when this pycolmap cannot build one."""
    pycolmap = import_pycolmap()
    index_cls = getattr(pycolmap, "VisualIndex", None)
    if index_cls is None or not hasattr(index_cls, "build"):
        raise VocabTreeError(f"this pycolmap ({getattr(pycolmap, '__version__', '?')}) cannot build a vocabulary tree "
                             "and none was given: pass --vocab-tree PATH (a COLMAP vocabulary tree .bin, e.g. "
                             "vocab_tree_flickr100K_words256K.bin from COLMAP's releases, downloaded by hand; it is "
                             "never fetched at run time), or use --matching sequential or exhaustive")
    rng = np.random.default_rng(seed)
    db = pycolmap.Database.open(str(db_path))
    try:
        ids = [im.image_id for im in db.read_all_images()]
        counts = np.array([db.num_descriptors_for_image(i) for i in ids], dtype=np.int64)
        keep = max(1, int(math.ceil(max_descriptors / max(1, len(ids)))))
        parts = []
        for i, c in zip(ids, counts):
            if c == 0:
                continue
            d = np.asarray(db.read_descriptors(i).to_float().data, dtype=np.float32)
            parts.append(d[rng.choice(len(d), keep, replace=False)] if len(d) > keep else d)
    finally:
        db.close()
    if not parts:
        raise DataError(f"no SIFT features were found in the photos (database {db_path}); photos of a textured "
                        "subject are needed")
    data = np.ascontiguousarray(np.concatenate(parts))
    opts = index_cls.BuildOptions()
    # faiss wants about 40 training points per word; a small tree is enough to find neighbours in one capture
    opts.num_visual_words = int(min(max_words, max(16, len(data) // 40)))
    opts.num_iterations = 10
    opts.num_rounds = 1
    opts.num_threads = num_threads
    try:
        index = index_cls.create(128, 64)
        with quiet_stdio():  # faiss prints a sizing warning for the tree's small second level
            index.build(opts, pycolmap.FeatureDescriptorsFloat(pycolmap.FeatureExtractorType.SIFT, data))
        index.write(str(out))
    except Exception as e:
        raise VocabTreeError(f"building a vocabulary tree from the photos failed ({e}); pass --vocab-tree PATH (a "
                             "COLMAP vocabulary tree .bin) or use --matching sequential or exhaustive") from None
    return Path(out)


def _retrieval_pairs(db_path: Path, tree: Path, *, num_images: int, query_ids=None, num_threads: int = -1) -> list:
    """(query, found) image id pairs from a vocabulary tree: each query image with the `num_images` most like it."""
    pycolmap = import_pycolmap()
    opts = pycolmap.VocabTreePairingOptions()
    opts.vocab_tree_path = str(tree)       # always a local file: an empty path would make COLMAP download one
    opts.num_images = int(num_images)
    opts.num_threads = num_threads
    db = pycolmap.Database.open(str(db_path))
    try:
        with quiet_colmap(2):   # a line per image indexed and queried
            try:
                gen = pycolmap.VocabTreePairGenerator(opts, db, list(query_ids or []))
            except Exception as e:
                raise VocabTreeError(f"cannot use the vocabulary tree {tree} ({e}); give a COLMAP vocabulary tree "
                                     ".bin for SIFT features, or leave out --vocab-tree to build one from the "
                                     "photos") from None
            return [(a, b) for a, b in gen.all_pairs() if a != b]
    finally:
        db.close()


def fmt_seconds(s: float) -> str:
    s = max(0.0, float(s))
    return f"{s:.0f} s" if s < 90 else f"{int(s // 60)} min {int(s % 60):02d} s"


def image_ids(db_path: Path) -> dict[str, int]:
    pycolmap = import_pycolmap()
    db = pycolmap.Database.open(str(db_path))
    try:
        return {im.name: im.image_id for im in db.read_all_images()}
    finally:
        db.close()


def plan_pairs(choice: MatchingChoice, db_path: Path, work: Path, *, vocab_tree=None, num_threads: int = -1,
               seed: int = 0, say=lambda m: None) -> tuple[MatchingChoice, list[tuple[int, int]]]:
    """The image id pairs to match under `choice` (after feature extraction). An `auto` choice whose vocabulary
    tree cannot be had falls back to exhaustive (or sequential for numbered names), with a note."""
    pycolmap = import_pycolmap()
    ids = image_ids(db_path)
    n = len(ids)
    strategy = choice.strategy
    work.mkdir(parents=True, exist_ok=True)

    def tree() -> Path:
        if vocab_tree is not None:
            return check_vocab_tree(vocab_tree)
        t0 = time.perf_counter()
        path = build_vocab_tree(db_path, work / "vocab_tree.bin", num_threads=num_threads, seed=seed)
        say(f"      built a vocabulary tree from the photos' features in {time.perf_counter() - t0:.1f} s")
        return path

    if strategy == "vocabtree":
        try:
            found = _retrieval_pairs(db_path, tree(), num_images=min(100, max(20, n // 4)), num_threads=num_threads)
        except VocabTreeError as e:
            if choice.asked != "auto" or vocab_tree is not None:
                raise
            fallback = "sequential" if numbered_sequence(list(ids)) else "exhaustive"
            say(f"note: no vocabulary tree ({e}); matching {fallback} instead")
            choice = MatchingChoice(fallback, f"{choice.reason}; no vocabulary tree", choice.order, choice.asked)
            return plan_pairs(choice, db_path, work, num_threads=num_threads, seed=seed, say=say)
        pairs = {(min(a, b), max(a, b)) for a, b in found}
        return choice, sorted(pairs)
    if strategy == "exhaustive":
        return choice, list(itertools.combinations(sorted(ids.values()), 2))
    if strategy == "sequential":
        order = [ids[name] for name in choice.order if name in ids]
        pairs = {(min(a, b), max(a, b)) for a, b in sequential_pairs(order)}
        if n > SEQUENTIAL_OVERLAP + 1:   # loop closure: frames far apart in time that see the same place
            try:
                queries = order[::LOOP_PERIOD]
                found = _retrieval_pairs(db_path, tree(), num_images=LOOP_IMAGES, query_ids=queries,
                                         num_threads=num_threads)
                rank = {i: k for k, i in enumerate(order)}
                loops = {(min(a, b), max(a, b)) for a, b in found if abs(rank[a] - rank[b]) > SEQUENTIAL_OVERLAP}
                say(f"      loop closure: {len(loops - pairs)} more pairs between frames far apart in the sequence")
                pairs |= loops
            except VocabTreeError as e:
                say(f"note: sequential matching without loop closure ({e})")
        return choice, sorted(pairs)
    if strategy == "spatial":
        db = pycolmap.Database.open(str(db_path))
        try:
            if db.num_pose_priors() == 0:
                raise DataError("--matching spatial needs GPS positions, but COLMAP read none from the photos' EXIF "
                                "(it needs latitude, longitude and altitude); use --matching auto, sequential, "
                                "vocabtree or exhaustive")
            gen = pycolmap.SpatialPairGenerator(pycolmap.SpatialPairingOptions(), db)
            pairs = {(min(a, b), max(a, b)) for a, b in gen.all_pairs() if a != b}
        finally:
            db.close()
        return choice, sorted(pairs)
    raise _unknown_matching(strategy)


def match_pairs(db_path: Path, pairs: list[tuple[int, int]], work: Path, *, num_threads: int = -1,
                say=lambda m: None) -> float:
    """Match and verify the given image id pairs, in chunks that report progress and time left; returns seconds."""
    pycolmap = import_pycolmap()
    db = pycolmap.Database.open(str(db_path))
    try:
        images = db.read_all_images()
        # COLMAP's pair list is "name1 name2" per line: a name with a space (or a leading #) cannot be written
        # there, so such images go by a temporary alias in the database while matching
        aliased = any(re.search(r"\s", im.name) or im.name.startswith("#") for im in images)
        names = {im.image_id: (f"sfm-alias-{im.image_id}" if aliased else im.name) for im in images}
        if aliased:
            for im in images:
                real, im.name = im.name, names[im.image_id]
                db.update_image(im)
                im.name = real
    finally:
        db.close()
    match = pycolmap.FeatureMatchingOptions()
    match.num_threads = num_threads
    match.use_gpu = False
    total = len(pairs)
    chunk = max(100, math.ceil(total / 20))
    t0 = time.perf_counter()
    work.mkdir(parents=True, exist_ok=True)
    pair_file = work / "pairs.txt"
    try:
        for start in range(0, total, chunk):
            part = pairs[start:start + chunk]
            pair_file.write_text("".join(f"{names[a]} {names[b]}\n" for a, b in part))
            opts = pycolmap.ImportedPairingOptions()
            opts.match_list_path = str(pair_file)
            pycolmap.match_image_pairs(db_path, matching_options=match, pairing_options=opts,
                                       device=pycolmap.Device.cpu)
            done = start + len(part)
            if total > chunk:
                spent = time.perf_counter() - t0
                say(f"      matched {done}/{total} pairs, {fmt_seconds(spent)} so far"
                    + (f", about {fmt_seconds(spent / done * (total - done))} left" if done < total else ""))
    finally:
        pair_file.unlink(missing_ok=True)
        if aliased:
            db = pycolmap.Database.open(str(db_path))
            try:
                for im in images:
                    db.update_image(im)
            finally:
                db.close()
    return time.perf_counter() - t0


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


def _map(db: Path, images: Path, work: Path, *, num_threads: int, seed: int, refine_focal: bool, say, total: int):
    """Incremental mapping; the largest model (None when nothing registered) and how many models were made."""
    pycolmap = import_pycolmap()
    opts = pycolmap.IncrementalPipelineOptions()
    opts.num_threads = num_threads
    opts.random_seed = seed
    opts.ba_refine_focal_length = refine_focal
    opts.mapper.abs_pose_refine_focal_length = refine_focal
    count = [0]
    t0 = time.perf_counter()
    step = max(5, total // 10)

    def next_image():  # called as the mapper moves on to each next image
        count[0] += 1
        if count[0] % step == 0:
            spent = time.perf_counter() - t0
            left = f", about {fmt_seconds(spent / count[0] * (total - count[0]))} left" if count[0] < total else ""
            say(f"      mapping: {count[0]}/{total} images tried, {fmt_seconds(spent)} so far{left}")
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


def _extract(db: Path, images: Path, names: list, mode, reader, extract, say) -> None:
    """SIFT features of every image, in chunks that report progress and time left. Chunks share one camera
    (SINGLE: the first chunk's) or make one per image (PER_IMAGE); AUTO groups cameras by size within one call,
    so it runs as one."""
    pycolmap = import_pycolmap()
    names = [str(n).replace("\\", "/") for n in names]
    chunk = len(names) if mode == pycolmap.CameraMode.AUTO else max(8, math.ceil(len(names) / 10))
    t0 = time.perf_counter()
    for start in range(0, len(names), chunk):
        part = names[start:start + chunk]
        pycolmap.extract_features(db, images, image_names=part, camera_mode=mode, reader_options=reader,
                                  extraction_options=extract, device=pycolmap.Device.cpu)
        if start == 0 and mode == pycolmap.CameraMode.SINGLE:
            database = pycolmap.Database.open(str(db))
            try:
                reader.existing_camera_id = database.read_all_cameras()[0].camera_id
            finally:
                database.close()
        done = start + len(part)
        if len(names) > chunk:
            spent = time.perf_counter() - t0
            say(f"      {done}/{len(names)} images, {fmt_seconds(spent)} so far"
                + (f", about {fmt_seconds(spent / done * (len(names) - done))} left" if done < len(names) else ""))


def _check_focal(focal, sizes: set, images: Path) -> float | None:
    """The given focal length in pixels as a float (None when none is given); a DataError when it is not a positive
    number or the photos are of several sizes."""
    if focal is None:
        return None
    if isinstance(focal, bool) or not isinstance(focal, (int, float)) or not np.isfinite(focal) or focal <= 0:
        raise DataError(f"focal={focal!r}: give the focal length in pixels of the photos, a positive number "
                        "(for a 36 mm-equivalent lens of F mm: F / 36 x the photo's width)")
    if len(sizes) > 1:
        listing = ", ".join(f"{w}x{h}" for w, h in sorted(sizes))
        raise DataError(f"a focal length in pixels fits photos of one size, but {images} holds several "
                        f"({listing}); resize the photos to one size or leave out --focal")
    return float(focal)


def _extraction_options(camera_model: str, num_threads: int):
    """pycolmap's image reader options (the camera model) and feature extraction options (threads, on the CPU)."""
    pycolmap = import_pycolmap()
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = camera_model
    extract = pycolmap.FeatureExtractionOptions()
    extract.num_threads = num_threads
    extract.use_gpu = False
    return reader, extract


def _map_and_check(db: Path, images: Path, work: Path, *, focal, priors, num_threads: int, seed: int, say,
                   total: int):
    """Incremental mapping, then the check of the model it keeps (said): (model, number of models, check), the
    model and its check None when nothing was registered."""
    # a given focal is held in every pass (refined, it drifts away: 230 px asked, 117-127 px found)
    rec, n_models = _map(db, images, work, num_threads=num_threads, seed=seed, refine_focal=focal is None, say=say,
                         total=total)
    check = check_reconstruction(rec, priors, total) if rec is not None else None
    if check is not None:
        _say_check(say, check)
    return rec, n_models, check


def _retry_simpler(db: Path, images: Path, work: Path, rec, n_models: int, check, *, camera_model: str, focal,
                   priors, num_threads: int, seed: int, say, total: int):
    """Map again with SIMPLE_PINHOLE cameras after an implausible fit and keep the better of the two fits:
    (model, number of models, check); the database is left describing the model that is kept."""
    why = "; ".join(f.message for f in check.implausible) if check else "nothing was registered"
    hold = f", focal length held at the given {focal:g} px" if focal is not None else ""
    say(f"the {camera_model} fit looks implausible ({why}); mapping again with {SIMPLE_MODEL} (one focal "
        f"length, no distortion, principal point at the image centre{hold}) ...")
    old = _set_cameras(db, _simple_cameras(_read_cameras(db), priors))
    rec2, n2, check2 = _map_and_check(db, images, work, focal=focal, priors=priors, num_threads=num_threads,
                                      seed=seed, say=say, total=total)
    # On a tie the simpler camera wins (it cannot fold, and has fewer ways to be wrong) unless it explains
    # the photos much worse, as it does for a lens with real distortion.
    if check2 is not None and (check is None or (
            check2.rank() <= check.rank()
            and check2.reprojection_error <= max(1.5 * check.reprojection_error,
                                                 check.reprojection_error + 0.5))):
        say(f"kept the {SIMPLE_MODEL} fit")
        return rec2, n2, check2
    say(f"kept the {camera_model} fit (the {SIMPLE_MODEL} one is worse)")
    _set_cameras(db, old)   # the database describes the model that is kept
    return rec, n_models, check


def _check_result(rec, check, images: Path, retry: bool) -> None:
    """A DataError when SfM registered nothing, triangulated no point, or kept cameras that fold."""
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


def _say_findings(say, check) -> None:
    """Say the check's findings as warnings, and what to do when the fit is implausible."""
    for f in check.findings:
        say(("warning: the fit may be wrong: " if f.implausible else "warning: ") + f.message)
    if check.implausible:
        say("warning: check the cameras in the report before training; if you know the lens, run again with "
            f"--camera-model {SIMPLE_MODEL} --focal PIXELS. Fine repeated patterns and symmetric subjects mislead SfM: "
            "photos that also show some irregular texture help")


def _write_sparse(rec, dataset: Path) -> None:
    """Write the model to dataset/sparse/0/ (binary), replacing whatever sparse/ held."""
    out = dataset / "sparse" / "0"
    if out.parent.exists():
        shutil.rmtree(out.parent)
    out.mkdir(parents=True)
    rec.write_binary(str(out))


def _write_report(dataset: Path, rec, check, *, camera_model: str, kept: str, retried: bool, focal, choice,
                  num_pairs: int) -> None:
    """dataset/sfm_report.json (what was asked, what was kept, the check) and dataset/sfm_report.png."""
    info = {"camera_model_asked": camera_model, "camera_model": kept, "retried": retried,
            "focal_given": focal, "matching": choice.strategy, "matching_asked": choice.asked,
            "matching_reason": choice.reason, "num_pairs": num_pairs, **check.to_json()}
    write_json(dataset / REPORT_JSON, info)
    if not retried:
        title = f"SfM with {kept} cameras"
    elif kept == camera_model:
        title = f"SfM with {kept} cameras (implausible, and a {SIMPLE_MODEL} retry was worse)"
    else:
        title = f"SfM with {kept} cameras (after an implausible {camera_model} fit)"
    write_report_png(rec, check, dataset / REPORT_PNG, title=title)


def sfm_in_place(dataset: Path, *, camera_model: str = "SIMPLE_RADIAL", single_camera: bool = True,
                 num_threads: int = -1, seed: int = 0, progress=None, focal: float | None = None,
                 retry: bool = True, report: bool = True, matching: str = "exhaustive", vocab_tree=None,
                 video: bool = False) -> SfMResult:
    """Run SfM on dataset/images, writing dataset/database.db, dataset/sparse/0 (the largest model) and, with
    `report`, dataset/sfm_report.png and .json. See run_sfm for the options (matching defaults to exhaustive
    here, as before; run_sfm and the command line choose by input)."""
    pycolmap = import_pycolmap()

    say = _say(progress)
    t0 = time.perf_counter()
    dataset = Path(dataset)
    images = dataset / "images"
    camera_model = _camera_model(camera_model)
    names = _check_images(images)
    choice = choose_matching(names, matching, video=video)
    if vocab_tree is not None:
        vocab_tree = check_vocab_tree(vocab_tree)
    if choice.strategy == "spatial":
        check_spatial(images, names)
    sizes = {image_size(images / n) for n in names}
    focal = _check_focal(focal, sizes, images)
    db = dataset / "database.db"
    db.unlink(missing_ok=True)
    if not single_camera:
        mode = pycolmap.CameraMode.PER_IMAGE
    else:  # one camera for all photos; AUTO groups them by size when sizes differ
        mode = pycolmap.CameraMode.SINGLE if len(sizes) == 1 else pycolmap.CameraMode.AUTO
    mapping = {"num_threads": num_threads, "seed": seed, "say": say, "total": len(names)}
    try:
        pycolmap.set_random_seed(seed)
        reader, extract = _extraction_options(camera_model, num_threads)
        with quiet_colmap(2):  # its warnings are about GPU/threads/RAM, not about the result
            say(f"[1/3] extracting SIFT features from {len(names)} images ...")
            _extract(db, images, names, mode, reader, extract, say)
            priors = _priors(db, focal)
            extract_seconds = time.perf_counter() - t0
            t_match = time.perf_counter()
            choice, pairs = plan_pairs(choice, db, dataset / ".sfm-work", vocab_tree=vocab_tree,
                                       num_threads=num_threads, seed=seed, say=say)
            say(f"[2/3] matching {len(pairs)} image pairs: {choice.strategy} ({choice.reason}) ...")
            match_pairs(db, pairs, dataset / ".sfm-work", num_threads=num_threads, say=say)
            match_seconds = time.perf_counter() - t_match
            say(f"[3/3] incremental mapping ({camera_model} camera) ...")
            rec, n_models, check = _map_and_check(db, images, dataset / ".sfm-models", focal=focal, priors=priors,
                                                  **mapping)
            retried = False
            simpler = camera_model != SIMPLE_MODEL or focal is not None
            if retry and simpler and (check is None or check.implausible):
                retried = True
                rec, n_models, check = _retry_simpler(db, images, dataset / ".sfm-models-retry", rec, n_models, check,
                                                      camera_model=camera_model, focal=focal, priors=priors,
                                                      **mapping)
    except DataError:
        raise
    except Exception as e:
        raise DataError(f"SfM failed on {images}: {e}") from None
    finally:
        for junk in (".sfm-models", ".sfm-models-retry", ".sfm-work"):
            shutil.rmtree(dataset / junk, ignore_errors=True)
    _check_result(rec, check, images, retry)
    kept = ", ".join(sorted({model_name(c) for c in rec.cameras.values()}))
    _say_findings(say, check)
    _write_sparse(rec, dataset)
    res = SfMResult(dataset, len(names), rec.num_reg_images(), rec.num_points3D(),
                    float(rec.compute_mean_reprojection_error()), time.perf_counter() - t0, rec, check, kept, retried,
                    choice.strategy, len(pairs), {"extract": extract_seconds, "match": match_seconds,
                                                  "map": time.perf_counter() - t0 - extract_seconds - match_seconds})
    if report:
        _write_report(dataset, rec, check, camera_model=camera_model, kept=kept, retried=retried, focal=focal,
                      choice=choice, num_pairs=len(pairs))
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
            retry: bool = True, report: bool = True, matching: str = "auto", vocab_tree=None,
            video: bool = False) -> SfMResult:
    """Recover cameras and a sparse point cloud from a folder of photos; write a COLMAP dataset to out_dir.

    matching: which image pairs to match: auto (the default: exhaustive up to 40 photos, sequential for video frames
    or numbered file names, vocabtree beyond), exhaustive, sequential, vocabtree or spatial (see the module doc).
    vocab_tree: a COLMAP vocabulary tree file for vocabtree matching and loop closure; without one a small tree is
    built from the photos' own features. video: the photos are frames of one video (auto then matches
    sequentially, in name order).

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
    choice = choose_matching(names, matching, video=video)     # bad choices stop before anything is copied
    if vocab_tree is not None:
        vocab_tree = check_vocab_tree(vocab_tree)
    if choice.strategy == "spatial":
        check_spatial(images_dir, names)
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
                               report=report, matching=matching, vocab_tree=vocab_tree, video=video)
        except DataError as e:  # name the user's folder, not our temporary copy
            raise type(e)(str(e).replace(str(tmp / "images"), str(images_dir))) from None
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
