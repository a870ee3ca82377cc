"""Video in: sharp, evenly spaced frames of a clip, written as images, then SfM on them with sequential matching.

`extract_frames(video, folder, fps=2 | frames=150)` splits the clip into equal windows (one per frame wanted) and
keeps the sharpest frame of each: sharpness is the variance of the Laplacian of the frame in grey, at most 640 px
wide, so a frame smeared by motion blur loses to its sharp neighbours. The video is read twice (once to score every
frame, once to write the chosen ones), so memory stays small for long clips. `sfm_video` writes the frames into a
dataset's images/ (frame_00001.jpg, ... in time order), a video.json saying which frame of the clip each one is, and
runs `sfm_in_place` on them (sequential matching unless asked otherwise).

`orbit_frames` renders a synthetic scene along a smooth orbit, frame after frame as a video would show it: a
stand-in for a real clip in tests and benchmarks.
"""
from __future__ import annotations

import json
import math
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import DataError

VIDEO_SUFFIXES = {".mp4", ".mov", ".m4v", ".avi", ".mkv", ".webm", ".mpg", ".mpeg", ".wmv", ".flv", ".3gp", ".mts",
                  ".m2ts", ".ts", ".ogv"}
IMAGE_SUFFIXES = {".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".webp", ".gif"}
SHARPNESS_WIDTH = 640          # frames are scored at most this wide, so the score does not depend on resolution
DEFAULT_FPS = 2.0
MAX_FPS = 1000.0               # no clip has more frames per second than this (a frame rate above it is not believed)
VIDEO_JSON = "video.json"


class VideoError(DataError):
    """A video that cannot be turned into frames: not a video, a codec this OpenCV cannot decode, no frames, or
    options that ask for too few frames."""


@dataclass
class VideoFrames:
    """What extract_frames wrote."""

    paths: list[Path]              # the frames written, in time order
    indices: list[int]             # their frame numbers in the clip (0-based)
    sharpness: list[float]         # their variance of the Laplacian
    video_frames: int              # frames decoded from the clip
    video_fps: float               # the clip's frame rate (0 when it does not say)
    median_sharpness: float        # over every frame of the clip
    seconds: float


def _import_cv2():
    try:
        import cv2
    except ImportError:
        raise DataError("reading a video needs OpenCV: pip install opencv-python-headless") from None
    return cv2


def is_video_path(path) -> bool:
    """A file (not a folder) whose name says video; other files are tried as videos too by extract_frames."""
    p = Path(path)
    return p.is_file() and p.suffix.lower() in VIDEO_SUFFIXES


def sharpness(frame: np.ndarray) -> float:
    """Variance of the Laplacian of the frame (BGR or grey uint8) in grey, scaled to at most 640 px wide."""
    cv2 = _import_cv2()
    grey = frame if frame.ndim == 2 else cv2.cvtColor(frame, cv2.COLOR_BGR2GRAY)
    if grey.shape[1] > SHARPNESS_WIDTH:
        scale = SHARPNESS_WIDTH / grey.shape[1]
        grey = cv2.resize(grey, (SHARPNESS_WIDTH, max(1, round(grey.shape[0] * scale))), interpolation=cv2.INTER_AREA)
    return float(cv2.Laplacian(grey, cv2.CV_64F).var())


def select_frames(scores, count: int) -> list[int]:
    """Split the frames into `count` equal windows and take the sharpest of each (the earliest on a tie)."""
    scores = np.asarray(scores, dtype=np.float64)
    count = min(int(count), len(scores))
    edges = np.linspace(0, len(scores), count + 1).round().astype(int)
    return [int(a + np.argmax(scores[a:b])) for a, b in zip(edges[:-1], edges[1:]) if b > a]


def check_frame_options(fps=None, frames=None) -> tuple[float | None, int | None]:
    """Validated (fps, frames); neither given means DEFAULT_FPS."""
    if fps is not None and frames is not None:
        raise VideoError("give --fps or --frames, not both: --fps takes frames per second of video, --frames a "
                         "total count spread evenly over the clip")
    if fps is not None:
        number = not isinstance(fps, bool) and isinstance(fps, (int, float, np.integer, np.floating))
        try:
            fps = float(fps) if number else fps
        except OverflowError:   # an integer too large for a float
            fps = math.inf
        if not number or not math.isfinite(fps) or fps <= 0:
            raise VideoError(f"--fps {fps!r:.40}: give a positive number of frames to keep per second of video "
                             f"(e.g. {DEFAULT_FPS:g}; 1-5 suits a slow walk around the subject)")
        if fps > MAX_FPS:
            raise VideoError(f"--fps {fps:g}: more frames per second than any video has (at most {MAX_FPS:g}); give "
                             f"a rate such as {DEFAULT_FPS:g} (1-5 suits a slow walk around the subject), the clip's "
                             "own frame rate to keep every frame, or --frames N for a total count")
        return fps, None
    if frames is not None:
        if isinstance(frames, bool) or not isinstance(frames, (int, np.integer)) or frames < 3:
            raise VideoError(f"--frames {frames!r}: give a whole number of frames to keep, at least 3 (SfM needs "
                             "several overlapping views; 50-200 suits a walk around the subject)")
        return None, int(frames)
    return DEFAULT_FPS, None


def _open(cv2, path: Path):
    from .sfm import quiet_stdio

    with quiet_stdio():   # ffmpeg prints its own complaints about files it cannot parse; ours says what to do
        cap = cv2.VideoCapture(str(path), cv2.CAP_FFMPEG)
    if not cap.isOpened():
        raise VideoError(f"cannot read {path} as a video: it is not a video, or it uses a codec this OpenCV cannot "
                         "decode. Convert it to H.264 MP4 (e.g. ffmpeg -i IN -c:v libx264 clip.mp4), or export its "
                         "frames as images and pass their folder")
    return cap


def _check_video_path(video) -> Path:
    path = Path(video).expanduser()
    if not path.exists():
        raise VideoError(f"video {path} does not exist")
    if path.is_dir():
        raise VideoError(f"{path} is a folder; pass a video file (or use the folder of photos as it is)")
    if path.suffix.lower() in IMAGE_SUFFIXES:
        raise VideoError(f"{path} is an image, not a video; pass the folder that holds your photos, or a video file")
    return path


def _score_frames(cv2, path: Path, say, t0: float):
    """Pass 1: the sharpness of every frame of the clip, the frame size (None when no frame decodes) and the
    clip's frame rate (0 when it does not say one)."""
    from .sfm import fmt_seconds

    cap = _open(cv2, path)
    try:
        video_fps = float(cap.get(cv2.CAP_PROP_FPS) or 0.0)
        video_fps = video_fps if math.isfinite(video_fps) and 0 < video_fps < MAX_FPS else 0.0
        expected = int(cap.get(cv2.CAP_PROP_FRAME_COUNT) or 0)
        expected = expected if 0 < expected < 10 ** 8 else 0
        say(f"reading {path.name}: {expected or 'an unknown number of'} frames"
            + (f" at {video_fps:.3g} fps" if video_fps else "") + ", scoring sharpness ...")
        scores, size = [], None
        step = max(100, expected // 10) if expected else 500
        while True:
            ok, frame = cap.read()
            if not ok or frame is None:
                break
            size = size or (frame.shape[1], frame.shape[0])
            scores.append(sharpness(frame))
            if len(scores) % step == 0 and expected and len(scores) < expected:
                spent = time.perf_counter() - t0
                say(f"      {len(scores)}/{expected} frames scored, about "
                    f"{fmt_seconds(spent / len(scores) * (expected - len(scores)) * 1.3)} left")
    finally:
        cap.release()
    return scores, size, video_fps


def _frames_to_keep(path: Path, n: int, video_fps: float, fps: float | None, frames: int | None, say) -> int:
    """How many of the clip's n frames to keep (at most n); a VideoError when the clip or the rate asked gives
    fewer than 3."""
    if n == 0:
        raise VideoError(f"no frame of {path} could be decoded: it holds no video frames, or its codec is one this "
                         "OpenCV cannot decode. Convert it to H.264 MP4 (e.g. ffmpeg -i IN -c:v libx264 clip.mp4)")
    if n < 3:
        raise VideoError(f"{path} has only {n} frame{'s' if n > 1 else ''}; SfM needs at least 3 views (a clip of a "
                         "slow walk around the subject, 10 s or more, works well)")
    if fps is not None:
        if not video_fps:
            raise VideoError(f"{path} does not say its frame rate, so --fps cannot be applied; use --frames N")
        # every frame once the rate asked reaches the clip's (below it the ratio is under 1: no overflow)
        count = n if fps >= video_fps else int(round(n * (fps / video_fps)))
        if count < 3:
            raise VideoError(f"--fps {fps:g} keeps only {count} frame{'s' if count != 1 else ''} of this "
                             f"{n / video_fps:.1f} s clip; SfM needs at least 3: raise --fps or use --frames N")
    else:
        count = frames
    if count >= n:
        if count > n:
            say(f"note: the clip has only {n} frames; keeping all of them")
        count = n
    return count


def _write_frames(cv2, path: Path, chosen: list[int], out_dir: Path, suffix: str) -> list[Path]:
    """Pass 2: write the chosen frames as out_dir/frame_00001.jpg, ... (in the order chosen); a VideoError when
    the clip does not give them again."""
    out_dir.mkdir(parents=True, exist_ok=True)
    width = max(5, len(str(len(chosen))))
    wanted = {idx: k for k, idx in enumerate(chosen)}
    paths: list[Path | None] = [None] * len(chosen)
    params = [cv2.IMWRITE_JPEG_QUALITY, 95] if suffix.lower() in (".jpg", ".jpeg") else []
    cap = _open(cv2, path)
    try:
        for idx in range(chosen[-1] + 1):
            if idx not in wanted:
                if not cap.grab():
                    break
                continue
            ok, frame = cap.read()
            if not ok or frame is None:
                break
            k = wanted[idx]
            dst = out_dir / f"frame_{k + 1:0{width}d}{suffix}"
            if not cv2.imwrite(str(dst), frame, params):
                raise DataError(f"cannot write {dst}; check that the output folder is writable and has space")
            paths[k] = dst
    finally:
        cap.release()
    if any(p is None for p in paths):
        raise VideoError(f"{path} gave different frames on a second reading (a damaged file?); convert it, e.g. "
                         "ffmpeg -i IN -c:v libx264 clip.mp4, and try again")
    return paths


def _say_kept(say, scores: list, chosen: list[int], count: int, size, t0: float) -> float:
    """Say how many frames were kept and how many blurred ones were passed over, and note kept frames that are
    still blurred; the seconds spent since t0."""
    n = len(scores)
    kept = [scores[i] for i in chosen]
    # blurred: under half the sharpness of the frame kept in its window; a kept frame under half the kept frames'
    # median: its whole window was blurred
    edges = np.linspace(0, n, count + 1).round().astype(int)
    skipped = sum(int((np.asarray(scores[a:b]) < 0.5 * max(scores[a:b])).sum()) for a, b in zip(edges[:-1], edges[1:])
                  if b > a)
    blurry = sum(s < 0.5 * float(np.median(kept)) for s in kept)
    spent = time.perf_counter() - t0
    say(f"kept {len(chosen)} of {n} frames ({size[0]}x{size[1]}), the sharpest of each window"
        + (f"; passed over {skipped} blurred frame{'s' if skipped != 1 else ''}" if skipped > 0 else "")
        + f" ({spent:.1f} s)")
    if blurry:
        say(f"note: {blurry} of the kept frames are still blurred (sharpness under half the clip's median): their "
            "whole window was; a slower camera move, or more light, gives sharper frames")
    return spent


def extract_frames(video, out_dir, *, fps: float | None = None, frames: int | None = None, progress=None,
                   suffix: str = ".jpg") -> VideoFrames:
    """Write sharp, evenly spaced frames of `video` into `out_dir` as frame_00001.jpg, ... (time order).

    fps: frames to keep per second of video; frames: how many to keep over the whole clip (give one; neither means
    DEFAULT_FPS). The clip is cut into that many equal windows and the sharpest frame of each is kept. A clip with
    fewer frames than asked gives all of them. Raises VideoError for what is not a readable video."""
    from ..io import say_progress as _say

    cv2 = _import_cv2()
    say = _say(progress)
    fps, frames = check_frame_options(fps, frames)
    path = _check_video_path(video)
    t0 = time.perf_counter()

    scores, size, video_fps = _score_frames(cv2, path, say, t0)
    n = len(scores)
    count = _frames_to_keep(path, n, video_fps, fps, frames, say)
    chosen = select_frames(scores, count)
    paths = _write_frames(cv2, path, chosen, Path(out_dir), suffix)
    median = float(np.median(scores))
    kept = [scores[i] for i in chosen]
    spent = _say_kept(say, scores, chosen, count, size, t0)
    return VideoFrames(paths, chosen, kept, n, video_fps, median, spent)


def sfm_video(video, out_dir, *, fps: float | None = None, frames: int | None = None, overwrite: bool = False,
              progress=True, matching: str = "auto", **sfm_options):
    """Frames of a video into a COLMAP dataset at out_dir: extract_frames into out_dir/images, then SfM on them
    (`matching` auto means sequential for frames of a video). sfm_options go to sfm_in_place (camera_model, focal,
    num_threads, seed, retry, report, vocab_tree, single_camera). Nothing is written at out_dir until SfM has
    finished. Returns the SfMResult."""
    from ..io import say_progress as _say
    from .sfm import choose_matching, sfm_in_place
    from .staging import finish_output, prepare_output

    say = _say(progress)
    check_frame_options(fps, frames)
    path = _check_video_path(video)
    choose_matching(["a", "b"], matching, video=True)          # an unknown strategy stops before the video is read
    out_dir = Path(out_dir).expanduser()
    tmp = prepare_output(out_dir, overwrite)
    try:
        got = extract_frames(path, tmp / "images", fps=fps, frames=frames, progress=say)
        info = {"video": str(path.resolve()), "video_frames": got.video_frames, "video_fps": got.video_fps,
                "median_sharpness": got.median_sharpness,
                "frames": [{"name": p.name, "index": i, "time": (i / got.video_fps if got.video_fps else None),
                            "sharpness": s} for p, i, s in zip(got.paths, got.indices, got.sharpness)]}
        (tmp / VIDEO_JSON).write_text(json.dumps(info, indent=1) + "\n")
        try:
            res = sfm_in_place(tmp, progress=say, matching=matching, video=True, **sfm_options)
        except DataError as e:  # name the user's output, not our temporary folder
            raise type(e)(str(e).replace(str(tmp), str(out_dir))) from None
        finish_output(tmp, out_dir)
    finally:
        if tmp.exists():
            import shutil

            shutil.rmtree(tmp, ignore_errors=True)
    res.path = out_dir
    say(res.summary())
    return res


# --- a synthetic clip -------------------------------------------------------------------------------------------

def orbit_cameras(name: str, frames: int, width: int, height: int, *, turns: float = 1.0,
                  elevation=(22.0, 42.0)):
    """Cameras of a synthetic scene along a smooth closed orbit, in order (as frames of a video walking around
    it): azimuth steps evenly through `turns` turns, elevation swings once between the two values (degrees)."""
    from .synthetic import get_spec, scene_camera

    spec = get_spec(name)
    if frames < 2:
        raise DataError(f"frames={frames}: an orbit needs at least 2")
    target = np.asarray(spec.target, dtype=np.float64)
    lo, hi = elevation
    cams = []
    for i in range(frames):
        t = i / frames
        az = 2 * math.pi * turns * t
        el = math.radians((lo + hi) / 2 + (hi - lo) / 2 * math.sin(2 * math.pi * t))
        eye = target + spec.distance * np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az),
                                                 math.sin(el)])
        cams.append(scene_camera(spec, eye, width, height, f"frame_{i + 1:05d}.png"))
    return cams


def orbit_frames(name: str, frames: int, width: int, height: int, *, turns: float = 1.0, supersample: int = 2):
    """Render `orbit_cameras`: yields (camera, uint8 RGB [H,W,3]) in order."""
    from .synthetic import MeshScene, get_spec, render_mesh

    spec = get_spec(name)
    mesh = MeshScene(spec.build())
    for cam in orbit_cameras(name, frames, width, height, turns=turns):
        rgb, _ = render_mesh(mesh, cam, supersample, specular=spec.specular)
        yield cam, (np.clip(rgb, 0, 1) * 255 + 0.5).astype(np.uint8)
