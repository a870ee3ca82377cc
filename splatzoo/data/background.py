"""The colour behind the surfels: given, or found in the images.

A model renders over one background colour, and training compares those renders with the photos, so the colour
must be the photos' own: an object shot on white and trained over black learns a white fog in front of the black.

`--background` takes auto (the default), black, white, R,G,B (three numbers in [0,1], or 0..255) or random:
- auto: images with alpha are composited over black; otherwise the images' borders are sampled and, when most
  border pixels share one colour that the point cloud does not hold (a backdrop, not a wall of the scene), that
  colour is the background (snapped to black or white when within a few levels of them); else black.
- random: every training step draws a new background colour behind both the render and the image (so coverage,
  alpha, is learned honestly and no colour is baked into the surfels). It needs images with alpha (renders and the
  evaluation then use black), or masks (masks/<image name>) and a backdrop of one colour: the masks put the new
  colour in place of the backdrop, and renders and the evaluation use the backdrop.

Over a fixed backdrop a half-transparent surface can pass for the right colour, which another viewer's background
would show; `splatzoo eval` reports the mean alpha inside the masks. On the built-in scenes training over the fixed
backdrop already ends at 0.97-1.0 there, and random colours through the masks change it by at most 0.02 while moving
PSNR by -0.2 to +0.3 dB (BENCHMARKS.md), so `auto` keeps the backdrop fixed and `random` is a choice.
"""
from __future__ import annotations

import numpy as np
import torch

from ..errors import DataError

NAMED = {"black": (0.0, 0.0, 0.0), "white": (1.0, 1.0, 1.0)}
CHOICES = "auto, black, white, random or R,G,B (three numbers in [0,1] or 0..255)"
TOLERANCE = 0.06          # a border pixel within this (per channel) of the median counts as background
MIN_BORDER_SHARE = 0.6    # of the border pixels, at least this share must be background
MAX_POINT_SHARE = 0.25    # a colour this common among the points is part of the scene
SAMPLED_VIEWS = 24


def parse_background(value) -> str | tuple[float, float, float]:
    """"auto", "random" or an RGB tuple in [0,1] from what a user typed (or a stored list)."""
    if value is None:
        return "auto"
    if isinstance(value, str):
        text = value.strip().lower()
        if text in ("auto", "random"):
            return text
        if text in NAMED:
            return NAMED[text]
        parts = [p for p in text.replace(" ", "").split(",") if p]
        try:
            numbers = [float(p) for p in parts]
        except ValueError:
            numbers = []
    else:
        try:
            numbers = [float(c) for c in value]
        except (TypeError, ValueError, OverflowError):  # OverflowError: an integer too large for a float
            numbers = []
    if len(numbers) != 3 or not all(np.isfinite(numbers)):
        raise DataError(f"background {value!r} is not understood; use {CHOICES}")
    if any(c > 1 for c in numbers):  # 0..255
        if not all(0 <= c <= 255 for c in numbers):
            raise DataError(f"background {value!r}: numbers must lie in [0,1] (or 0..255)")
        numbers = [c / 255 for c in numbers]
    if not all(0 <= c <= 1 for c in numbers):
        raise DataError(f"background {value!r}: numbers must lie in [0,1] (or 0..255)")
    return tuple(float(c) for c in numbers)


def _has_alpha(view) -> bool:
    from .scene import image_has_alpha

    if view.pixels is not None:
        return view.pixels.shape[2] == 4
    return view.path is not None and image_has_alpha(view.path)


def border_colour(views, sample: int = SAMPLED_VIEWS) -> tuple[np.ndarray, float]:
    """(median colour in [0,1], share of border pixels within TOLERANCE of it) over the borders of up to `sample`
    views spread over the list. The border is a strip 2% of the shorter side wide (at least 2 pixels)."""
    if not views:
        return np.zeros(3), 0.0
    picks = [views[i] for i in np.linspace(0, len(views) - 1, min(sample, len(views))).round().astype(int)]
    strips = []
    for v in picks:
        img = v.image().numpy().astype(np.float32) / 255
        b = max(2, round(0.02 * min(img.shape[:2])))
        strips += [img[:b].reshape(-1, 3), img[-b:].reshape(-1, 3), img[b:-b, :b].reshape(-1, 3),
                   img[b:-b, -b:].reshape(-1, 3)]
    pixels = np.concatenate(strips)
    colour = np.median(pixels, axis=0)
    share = float((np.abs(pixels - colour).max(1) <= TOLERANCE).mean())
    return colour, share


def _has_masks(views) -> bool:
    """Every (sampled) view has a mask and no alpha: the masks can replace the photos' backdrop."""
    picks = views[:SAMPLED_VIEWS]
    return bool(picks) and all(v.use_mask and not _has_alpha(v) for v in picks)


MASKED = ("; the masks put a new colour in place of the backdrop each training step, so surfaces learn to be opaque "
          "(renders over the backdrop)")


def choose_background(option, train_views, point_colors: torch.Tensor | None) -> tuple[tuple, bool, str]:
    """(background colour, random per step?, a sentence saying what was chosen and why) for the parsed option.
    Random with masks (no alpha) returns the photos' backdrop as the colour: what renders and evaluation use."""
    if option == "random":
        if train_views and all(_has_alpha(v) for v in train_views[:SAMPLED_VIEWS]):
            return NAMED["black"], True, "random per training step (images have alpha); renders over black"
        if not _has_masks(train_views):
            raise DataError("--background random needs images with an alpha channel (RGBA) or masks (masks/<image "
                            "name>), so that a new colour can be put behind the object each step; these images have "
                            "neither. Use auto, black, white or R,G,B")
        colour, _, note = choose_background("auto", train_views, point_colors)
        if "no common colour" in note or "part of the scene" in note:
            raise DataError(f"--background random with masks needs a backdrop of one colour around the object, to "
                            f"replace through the masks; found {note.removeprefix('auto: ')}. Use auto, black, white "
                            "or R,G,B")
        return colour, True, "random per training step" + note.removeprefix("auto") + MASKED
    if option != "auto":
        return tuple(option), False, ""
    if train_views and _has_alpha(train_views[0]):
        return NAMED["black"], False, "auto: the images have alpha, composited over black (--background random " \
                                      "learns transparency instead)"
    colour, share = border_colour(train_views)
    shown = ", ".join(f"{c:.2f}" for c in colour)
    if share < MIN_BORDER_SHARE:
        return NAMED["black"], False, f"auto: black (the image borders have no common colour: {share:.0%} near " \
                                      f"({shown}))"
    if point_colors is not None and len(point_colors):
        near = (np.abs(point_colors.cpu().numpy() - colour).max(1) <= TOLERANCE).mean()
        if near > MAX_POINT_SHARE:
            return NAMED["black"], False, f"auto: black ({share:.0%} of the image borders are ({shown}), but so are " \
                                          f"{near:.0%} of the points: a part of the scene, not a backdrop; pass " \
                                          "--background if it is one)"
    for name, rgb in NAMED.items():
        if np.abs(colour - rgb).max() <= TOLERANCE:
            return rgb, False, f"auto: {name} ({share:.0%} of the image borders are ({shown}))"
    return tuple(float(c) for c in colour), False, f"auto: ({shown}), the colour of {share:.0%} of the image borders"
