"""Video in: sharp, evenly spaced frames of a clip, in order; bad clips and options are named errors; a tiny clip of
a synthetic orbit goes through `splatzoo sfm clip --frames N` with sequential matching."""
from __future__ import annotations

import json

import numpy as np
import pytest

cv2 = pytest.importorskip("cv2")

from splatzoo.data.video import (VideoError, extract_frames, orbit_cameras, orbit_frames,  # noqa: E402
                                 select_frames, sharpness)
from splatzoo.errors import DataError  # noqa: E402


def _write_video(path, frames, fps=12.0):
    """frames: uint8 RGB [H,W,3]; MJPG in .avi, which every OpenCV build writes."""
    h, w = frames[0].shape[:2]
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), fps, (w, h))
    assert writer.isOpened()
    for f in frames:
        writer.write(np.ascontiguousarray(f[..., ::-1]))
    writer.release()
    return path


def _blur(f):
    return cv2.GaussianBlur(f, (0, 0), 3.0)


@pytest.fixture(scope="module")
def views():
    """8 distinct views along an orbit (small renders, in order)."""
    return [rgb for _, rgb in orbit_frames("boots", 8, 128, 96)]


# which of the 3 copies of each view is the sharp one (the other two are blurred)
SHARP_AT = [0, 2, 1, 1, 0, 2, 2, 0]


@pytest.fixture(scope="module")
def clip(tmp_path_factory, views):
    """24 frames: each view three times, two of the copies blurred."""
    frames = []
    for v, pos in zip(views, SHARP_AT):
        frames += [v if k == pos else _blur(v) for k in range(3)]
    return _write_video(tmp_path_factory.mktemp("clip") / "clip.avi", frames, fps=12.0)


def test_select_frames_takes_the_sharpest_of_each_window():
    scores = [1, 5, 2, 9, 1, 1, 3, 3, 7, 0]
    assert select_frames(scores, 5) == [1, 3, 4, 6, 8]
    assert select_frames(scores, 20) == list(range(10))       # more than there are: every frame, once


def test_blur_lowers_the_sharpness(views):
    assert sharpness(_blur(views[0])) < 0.3 * sharpness(views[0])


def test_extraction_keeps_the_count_skips_blurred_frames_and_keeps_order(clip, views, tmp_path):
    messages = []
    got = extract_frames(clip, tmp_path / "f", frames=8, progress=messages.append)
    expected = [3 * k + pos for k, pos in enumerate(SHARP_AT)]
    assert got.indices == expected
    assert [p.name for p in got.paths] == [f"frame_{k:05d}.jpg" for k in range(1, 9)]
    assert sorted(p.name for p in (tmp_path / "f").iterdir()) == [p.name for p in got.paths]
    assert got.video_frames == 24 and got.video_fps == pytest.approx(12.0)
    assert any("passed over 16 blurred frames" in m for m in messages), messages
    # the written frames are the sharp views, in order
    for k, path in enumerate(got.paths):
        img = cv2.imread(str(path))[..., ::-1].astype(np.float32)
        errs = [np.abs(img - v.astype(np.float32)).mean() for v in views]
        assert int(np.argmin(errs)) == k


def test_fps_spreads_frames_over_time(clip, tmp_path):
    got = extract_frames(clip, tmp_path / "f", fps=4, progress=False)     # 2 s of video at 4 per second
    assert got.indices == [3 * k + pos for k, pos in enumerate(SHARP_AT)]
    got = extract_frames(clip, tmp_path / "g", fps=1.5, progress=False)
    assert len(got.indices) == 3 and got.indices == sorted(got.indices)
    got = extract_frames(clip, tmp_path / "h", frames=100, progress=False)  # more than the clip has: all of it
    assert got.indices == list(range(24))


def test_bad_videos_and_options_are_named_errors(tmp_path, clip, views):
    text = tmp_path / "notes.mp4"
    text.write_text("not a video at all\n" * 50)
    with pytest.raises(VideoError, match="not a video, or it uses a codec"):
        extract_frames(text, tmp_path / "o")
    with pytest.raises(VideoError, match="does not exist"):
        extract_frames(tmp_path / "missing.mp4", tmp_path / "o")
    png = tmp_path / "photo.png"
    cv2.imwrite(str(png), views[0])
    with pytest.raises(VideoError, match="is an image, not a video"):
        extract_frames(png, tmp_path / "o")
    empty = tmp_path / "empty.avi"
    cv2.VideoWriter(str(empty), cv2.VideoWriter_fourcc(*"MJPG"), 10.0, (64, 48)).release()
    with pytest.raises(VideoError, match="no frame|not a video"):
        extract_frames(empty, tmp_path / "o")
    two = _write_video(tmp_path / "two.avi", views[:2])
    with pytest.raises(VideoError, match="only 2 frames"):
        extract_frames(two, tmp_path / "o")
    for bad in (0, -1, float("nan")):
        with pytest.raises(VideoError, match="--fps"):
            extract_frames(clip, tmp_path / "o", fps=bad)
    for bad in (2, 0, -5):
        with pytest.raises(VideoError, match="at least 3"):
            extract_frames(clip, tmp_path / "o", frames=bad)
    with pytest.raises(VideoError, match="not both"):
        extract_frames(clip, tmp_path / "o", fps=2, frames=10)
    with pytest.raises(VideoError, match="keeps only 1 frame"):
        extract_frames(clip, tmp_path / "o", fps=0.5)
    assert issubclass(VideoError, DataError)
    assert not (tmp_path / "o").exists() or not any((tmp_path / "o").iterdir())


def test_frame_rates_no_clip_has_are_named_errors(clip, tmp_path):
    from splatzoo.data.video import MAX_FPS

    for bad in (1e308, 10 ** 400, float("inf"), -float("inf"), float("nan"), 0, -2, MAX_FPS * 1.01, "2", True):
        with pytest.raises(VideoError, match="--fps") as e:
            extract_frames(clip, tmp_path / "o", fps=bad)
        assert "give a" in str(e.value)
    # up to the clip's own rate and beyond it (to MAX_FPS): every frame, once
    assert extract_frames(clip, tmp_path / "a", fps=12, progress=False).indices == list(range(24))
    assert extract_frames(clip, tmp_path / "b", fps=MAX_FPS, progress=False).indices == list(range(24))
    assert not (tmp_path / "o").exists()


@pytest.mark.parametrize("value", ["1e308", "inf", "nan", "0", "-1", "1e400"])
def test_cli_sfm_fps_out_of_range_is_a_named_error(clip, tmp_path, value):
    from typer.testing import CliRunner

    from splatzoo.cli import app

    res = CliRunner().invoke(app, ["sfm", str(clip), "--out", str(tmp_path / "o"), f"--fps={value}"])
    assert isinstance(res.exception, VideoError), (res.output, res.exception)
    assert "--fps" in str(res.exception)
    assert not (tmp_path / "o").exists()


def test_cli_refuses_frame_options_for_a_folder_and_bad_videos(tmp_path):
    from typer.testing import CliRunner

    from splatzoo.cli import app

    (tmp_path / "photos").mkdir()
    res = CliRunner().invoke(app, ["sfm", str(tmp_path / "photos"), "--out", str(tmp_path / "o"), "--frames", "10"])
    assert res.exit_code != 0 and "not a video file" in str(res.exception)
    bad = tmp_path / "clip.mov"
    bad.write_bytes(b"\x00" * 4096)
    res = CliRunner().invoke(app, ["sfm", str(bad), "--out", str(tmp_path / "o")])
    assert isinstance(res.exception, VideoError), res.output
    res = CliRunner().invoke(app, ["sfm", str(bad), "--out", str(tmp_path / "o"), "--fps", "0"])
    assert isinstance(res.exception, VideoError) and "--fps" in str(res.exception)
    assert not (tmp_path / "o").exists()


def test_orbit_cameras_walk_in_small_even_steps():
    cams = orbit_cameras("boots", 40, 64, 48)
    c = np.array([cam.center.double().numpy() for cam in cams])
    steps = np.linalg.norm(np.diff(np.vstack([c, c[:1]]), axis=0), axis=1)
    assert steps.max() < 1.5 * steps.min() and steps.max() < 0.25 * np.linalg.norm(c[0] - c[20])


def test_cli_sfm_on_a_video_uses_sequential_matching(tmp_path):
    """End to end on a tiny clip: 16 views along an orbit, each twice, one copy blurred."""
    from typer.testing import CliRunner

    from splatzoo.cli import app

    frames = []
    for k, (_, rgb) in enumerate(orbit_frames("boots", 16, 256, 192)):
        frames += [_blur(rgb), rgb] if k % 2 else [rgb, _blur(rgb)]
    clip = _write_video(tmp_path / "walk.avi", frames, fps=8.0)
    out = tmp_path / "data"
    res = CliRunner().invoke(app, ["sfm", str(clip), "--out", str(out), "--frames", "16"])
    assert res.exit_code == 0, res.output + repr(res.exception)
    assert "sequential (frames of a video)" in res.output and "passed over 16 blurred frames" in res.output
    info = json.loads((out / "video.json").read_text())
    assert [f["index"] for f in info["frames"]] == [2 * k + (k % 2) for k in range(16)]
    report = json.loads((out / "sfm_report.json").read_text())
    assert report["matching"] == "sequential" and report["num_pairs"] > 0
    assert report["num_registered"] >= 14, res.output
    assert sorted(p.name for p in (out / "images").iterdir()) == [f"frame_{k:05d}.jpg" for k in range(1, 17)]
