"""The `splatzoo-data` dataparser: any folder splatzoo reads (COLMAP, Blender / nerfstudio transforms, instant-ngp,
synthetic scenes) as nerfstudio data, through `splatzoo.data.load_scene`, with splatzoo's train/test split, image
sizes, masks and background. Its world frame is the dataset's own (identity dataparser transform, scale 1), so the
initial points, the scene extent and every image are exactly those `splatzoo train` uses; the Scene itself rides
along in the metadata, for the model and for datamanager.SplatzooDataset. Imports nerfstudio (but not its
dataparser_configs, which loads this module as a plugin).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import torch
from nerfstudio.cameras.cameras import Cameras, CameraType
from nerfstudio.data.dataparsers.base_dataparser import DataParser, DataParserConfig, DataparserOutputs
from nerfstudio.data.scene_box import SceneBox
from nerfstudio.plugins.registry_dataparser import DataParserSpecification

from .convert import opengl_camera_to_world

SCENE_KEY = "splatzoo_scene"   # dataparser metadata: a SceneHandle
_SCENES: dict = {}             # (folder, options) -> Scene: the train and test splits (and eval's) load it once


class SceneHandle:
    """A splatzoo Scene in nerfstudio's metadata, with the views of one split. nerfstudio deep-copies metadata;
    the handle copies as itself, so every holder shares one Scene (and its decoded images)."""

    def __init__(self, scene, split: str):
        self.scene, self.split = scene, split

    @property
    def views(self) -> list:
        """The split's views: test, or train (a scene without test views is evaluated on its training views, as
        `splatzoo eval` does)."""
        return self.scene.test if self.split == "test" and self.scene.test else self.scene.train

    def __deepcopy__(self, memo):
        return self


def scene_handle(metadata) -> SceneHandle | None:
    handle = (metadata or {}).get(SCENE_KEY)
    return handle if isinstance(handle, SceneHandle) else None


def _masks(value: str):
    words = {"auto": "auto", "true": True, "yes": True, "on": True, "false": False, "no": False, "off": False}
    if value.lower() not in words:
        from ...errors import DataError

        raise DataError(f"masks must be auto, true or false, got {value!r}")
    return words[value.lower()]


@dataclass
class SplatzooDataParserConfig(DataParserConfig):
    """Any dataset folder splatzoo reads, as `splatzoo train` reads it (options as `splatzoo train`'s)."""

    _target: type = field(default_factory=lambda: SplatzooDataParser)
    data: Path = Path()
    """The dataset folder (COLMAP, Blender / nerfstudio transforms, instant-ngp, a splatzoo synthetic scene)."""
    resolution: int | None = None
    """Downscale factor 1, 2, 4 or 8 (uses images_<n>/ when present)."""
    max_width: int | None = None
    """Cap on the image width in pixels (default: photos wider than 1600 px are downscaled to it)."""
    test_every: int = 8
    """Images sorted by name, every test_every-th is a test view (0: no test split)."""
    background: str = "auto"
    """auto (found in the images), random, black, white or R,G,B: the colour behind the surfels."""
    masks: str = "auto"
    """auto (when the folder has masks/), true or false."""
    skip_missing: bool = False
    """Leave out the frames of a transforms file whose image is missing."""


class SplatzooDataParser(DataParser):
    config: SplatzooDataParserConfig
    includes_time: bool = False

    def scene(self):
        """The splatzoo Scene of the config's folder and options (loaded once per process)."""
        from ...data import load_scene

        c = self.config
        key = (str(Path(c.data).expanduser().resolve()), c.resolution, c.max_width, c.test_every, c.background,
               c.masks, c.skip_missing)
        if key not in _SCENES:
            _SCENES[key] = load_scene(c.data, resolution=c.resolution, max_width=c.max_width, test_every=c.test_every,
                                      background=c.background, masks=_masks(c.masks), skip_missing=c.skip_missing)
        return _SCENES[key]

    def _generate_dataparser_outputs(self, split: str = "train", **kwargs) -> DataparserOutputs:
        scene = self.scene()
        handle = SceneHandle(scene, "train" if split == "train" else "test")
        views = handle.views
        cams = [v.camera for v in views]
        K = torch.stack([c.K.double() for c in cams])
        cameras = Cameras(
            camera_to_worlds=torch.stack([opengl_camera_to_world(c) for c in cams]),
            fx=K[:, 0, 0:1].float(), fy=K[:, 1, 1:2].float(), cx=K[:, 0, 2:3].float(), cy=K[:, 1, 2:3].float(),
            width=torch.tensor([[c.width] for c in cams]), height=torch.tensor([[c.height] for c in cams]),
            camera_type=CameraType.PERSPECTIVE)
        return DataparserOutputs(
            image_filenames=[Path(v.path) if v.path is not None else Path(v.name) for v in views],
            cameras=cameras, scene_box=SceneBox(aabb=_scene_box(scene)),
            metadata={SCENE_KEY: handle},
            dataparser_transform=torch.eye(4)[:3, :], dataparser_scale=1.0)


def _scene_box(scene) -> torch.Tensor:
    """[2,3]: the box around the initial points and the camera centres, a little larger."""
    centres = torch.stack([v.camera.center.float() for v in scene.train + scene.test])
    pts = torch.cat([scene.points.float(), centres]) if scene.points.shape[0] else centres
    lo, hi = pts.min(0).values, pts.max(0).values
    pad = 0.05 * (hi - lo).clamp_min(1e-3)
    return torch.stack([lo - pad, hi + pad])


splatzoo_data = DataParserSpecification(
    config=SplatzooDataParserConfig(),
    description="any dataset folder splatzoo reads (COLMAP, transforms.json, synthetic scenes), as splatzoo reads it")
