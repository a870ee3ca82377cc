"""The data manager of the splatzoo methods: nerfstudio's full-image data manager over a dataset that hands out
splatzoo's own images when the dataparser is splatzoo-data (dataparser.py). Imports nerfstudio."""
from __future__ import annotations

from dataclasses import dataclass, field

import torch
from nerfstudio.configs.dataparser_configs import AnnotatedDataParserUnion
from nerfstudio.data.datamanagers.full_images_datamanager import FullImageDatamanager, FullImageDatamanagerConfig
from nerfstudio.data.datasets.base_dataset import InputDataset

from .dataparser import SplatzooDataParserConfig, scene_handle


class SplatzooDataset(InputDataset):
    """nerfstudio's dataset, handing out splatzoo's images (at camera size, RGBA composited over the scene's
    background) when its dataparser is splatzoo-data; with any other dataparser, nerfstudio's own."""

    def _view(self, image_idx: int):
        handle = scene_handle(self._dataparser_outputs.metadata)
        return None if handle is None else handle.views[image_idx]

    def get_numpy_image(self, image_idx: int):
        view = self._view(image_idx)
        return super().get_numpy_image(image_idx) if view is None else view.image().numpy()

    def get_image_float32(self, image_idx: int) -> torch.Tensor:
        view = self._view(image_idx)
        return super().get_image_float32(image_idx) if view is None else view.image_float()

    def get_image_uint8(self, image_idx: int) -> torch.Tensor:
        view = self._view(image_idx)
        return super().get_image_uint8(image_idx) if view is None else view.image()


class SplatzooDatamanager(FullImageDatamanager[SplatzooDataset]):
    """nerfstudio's full-image data manager over SplatzooDataset."""


@dataclass
class SplatzooDatamanagerConfig(FullImageDatamanagerConfig):
    _target: type = field(default_factory=lambda: SplatzooDatamanager)
    dataparser: AnnotatedDataParserUnion = field(default_factory=SplatzooDataParserConfig)
