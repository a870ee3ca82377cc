"""The nerfstudio methods `splatzoo-<member>`: one MethodSpecification per member, each with a model config class
whose fields are the member's options and splatzoo's training options (`ns-train splatzoo-gabor --help` lists them
as --pipeline.model.n-waves, --pipeline.model.strategy, ...). The classes are made here, at import, from the members'
config dataclasses and TrainConfig, and live in this module so that config.yml names them. Imports nerfstudio.
"""
from __future__ import annotations

import dataclasses
import typing

import torch
import tyro
from nerfstudio.configs.base_config import MachineConfig, ViewerConfig
from nerfstudio.pipelines.base_pipeline import VanillaPipelineConfig
from nerfstudio.plugins.types import MethodSpecification

from ...training import TrainConfig
from .datamanager import SplatzooDatamanagerConfig
from .model import SplatzooModelConfig, train_option_names
from .trainer import SplatzooTrainerConfig

MEMBERS = {  # member -> what ns-train --help says of it
    "2dgs": "splatzoo's 2D Gaussian surfels (2DGS), one colour each",
    "gabor": "splatzoo's 3D Gabor surfels: N waves of learnable frequency, weight and phase in each",
    "gabor-adaptive": "splatzoo's gabor with waves only where the training views show they pay",
    "beta": "splatzoo's 2D surfels with a learned Beta-kernel falloff",
    "beta-gabor": "splatzoo's gabor-adaptive waves, a colour and direction each, on surfels with beta's learned falloff",
    "textured": "splatzoo's surfels with a small RGBA texture each",
    "neural-gabor": "splatzoo's surfels with a tiny sine network each",
}


def _option(f: dataclasses.Field, hint) -> tuple:
    """A config field for dataclasses.make_dataclass: the type (with its help for tyro) and the default."""
    help_text = f.metadata.get("help")
    typ = typing.Annotated[hint, tyro.conf.arg(help=help_text)] if help_text else hint
    if f.default_factory is not dataclasses.MISSING:
        return f.name, typ, dataclasses.field(default_factory=f.default_factory)
    return f.name, typ, dataclasses.field(default=f.default)


def model_config_class(member: str) -> type:
    """SplatzooModelConfig with `member`'s options and splatzoo's training options as fields."""
    from ...zoo import get_model_spec

    config_cls = get_model_spec(member).config_cls
    hints = typing.get_type_hints(config_cls)
    fields = [_option(f, hints[f.name]) for f in dataclasses.fields(config_cls)]
    train_hints = typing.get_type_hints(TrainConfig)
    train = {f.name: f for f in dataclasses.fields(TrainConfig)}
    fields += [_option(train[name], train_hints[name]) for name in train_option_names() if name not in hints]
    fields.append(("member", str, dataclasses.field(default=member)))
    name = "Splatzoo" + "".join(part.capitalize() for part in member.split("-")) + "ModelConfig"
    cls = dataclasses.make_dataclass(name, fields, bases=(SplatzooModelConfig,),
                                     namespace={"__module__": __name__,
                                                "__doc__": f"{MEMBERS.get(member, member)}; splatzoo's training."})
    globals()[name] = cls  # config.yml names the class by module and name
    return cls


def method(member: str) -> MethodSpecification:
    """The method splatzoo-<member>: splatzoo's schedule and defaults (30000 iterations), splatzoo-data, on the GPU
    when there is one (splatzoo's C++ rasterizer on the CPU otherwise)."""
    config = SplatzooTrainerConfig(
        method_name=f"splatzoo-{member}",
        machine=MachineConfig(device_type="cuda" if torch.cuda.is_available() else "cpu"),
        steps_per_eval_image=500,
        steps_per_eval_batch=0,
        steps_per_save=2000,
        steps_per_eval_all_images=0,
        max_num_iterations=30000,
        mixed_precision=False,
        pipeline=VanillaPipelineConfig(datamanager=SplatzooDatamanagerConfig(), model=model_config_class(member)()),
        optimizers={},
        viewer=ViewerConfig(num_rays_per_chunk=1 << 15),
        vis="viewer",
    )
    return MethodSpecification(config=config, description=MEMBERS.get(member, f"splatzoo's {member}"))


splatzoo_2dgs = method("2dgs")
splatzoo_gabor = method("gabor")
splatzoo_gabor_adaptive = method("gabor-adaptive")
splatzoo_beta = method("beta")
splatzoo_beta_gabor = method("beta-gabor")
splatzoo_textured = method("textured")
splatzoo_neural_gabor = method("neural-gabor")
