"""Base classes for primitive types. A model owns per-primitive parameters and maps them, for one camera,
to the Surfels contract. Plugins subclass SurfelModel and register a ModelSpec."""
from __future__ import annotations

import dataclasses
import math
from typing import Any

import torch
from torch import nn

from ..errors import ShapeError, SplatzooError
from ..geometry import normals_to_quats
from ..types import MAX_SCALE, Camera, RenderOutput, Surfels

# geometry(): the scales' upper limit, as a log-scale (a hair below MAX_SCALE: float's exp may round up)
LOG_MAX_SCALE = math.log(MAX_SCALE) - 1e-5


def inverse_sigmoid(x: torch.Tensor) -> torch.Tensor:
    x = x.clamp(1e-6, 1 - 1e-6)
    return torch.log(x / (1 - x))


def nearest_neighbour_distance(points: torch.Tensor, k: int = 3) -> torch.Tensor:
    """Mean distance from each point to its k nearest other points [N] (a KD-tree: O(N log N), seconds at 1M)."""
    from scipy.spatial import cKDTree

    n = points.shape[0]
    if n < 2:
        return points.new_ones(n)
    k = min(k, n - 1)
    pts = points.detach().double().cpu().numpy()
    # k + 1 neighbours, the first being the point itself (or a duplicate of it: distance 0 either way)
    dist, _ = cKDTree(pts).query(pts, k=k + 1)
    return torch.from_numpy(dist[:, 1:].mean(1)).to(points)


@dataclasses.dataclass
class Shedding:
    """One way to make a model smaller: `what` it removes, `preview(camera)` the Surfels it would leave (to render
    and measure before choosing) and `apply()` that does it (keeping the optimizer pointing at the parameters)."""

    what: str
    preview: Any
    apply: Any


@dataclasses.dataclass(frozen=True)
class RenderSettings:
    """How a model is rendered, whoever renders it: the model owns them (`SplatModel.render_settings`, changed only
    through `set_render_settings`) and its checkpoint keeps them.

    antialias: rendered with the pixel-footprint filter (RasterSettings.pixel_filter): trained so, and so every render
      of it (evaluation, viewer, mesh) must be.
    background: the colour [3] behind the surfels that the model was trained over (the photos' own backdrop), the
      default of render(); None: black (a model trained over random colours, or made outside training).
    """

    antialias: bool = False
    background: tuple[float, float, float] | None = None


class SplatModel(nn.Module):
    """A primitive type. Subclasses define parameters in `__init__(config, num_primitives)` with first
    dimension num_primitives, initialise them in `init_from_points`, and implement `surfels(camera)`."""

    name: str = ""  # set from the registry spec when created through create_model
    # how the model is rendered (RenderSettings); kept in the checkpoint
    render_settings: RenderSettings = RenderSettings()
    # the precision the model is stored at (packing.PRECISIONS): a run trained with --store 8bit holds the values its
    # packed file loads back as, and its stored size is that file's. Kept in the checkpoint
    precision: str = "float32"
    # the densification strategy a run uses when its config says "auto" (TrainConfig.strategy): "adc", "mcmc" or
    # "frequency"
    densify_strategy: str = "adc"
    # names of buffers with one row per primitive (e.g. per-surfel wave counts): densification and loading edit
    # them with the parameters; they are not trained
    primitive_buffers: tuple[str, ...] = ()
    # the PLY property prefix of a per-primitive parameter where it is not `<name>_` (splatzoo.model_ply: the
    # parameter [N, k] is written as <prefix>0 .. <prefix>{k-1}); the 3DGS layout's own names (x y z, opacity, scale_,
    # rot_, f_dc_, f_rest_) belong to the file format and need no entry here
    ply_prefixes: dict[str, str] = {}
    # the mean absolute colour error of the recent training steps over the pixels the surfels cover (alpha > 1/2;
    # an exponential average over about 100 steps, colour units for images in [0,1]), set by the trainer before each
    # on_step; None outside training
    recent_error: float | None = None
    # probe_error(surfels_of): the mean squared colour error over a fixed few training views, each rendered from
    # surfels_of(camera) (no gradient); set by the trainer that trains the model, so on_step can measure what an
    # edit would cost before making it. None outside training
    probe_error: Any = None

    @classmethod
    def budget_start(cls, fit: int) -> float:
        """Under a byte budget the model starts with this many times the `fit` primitives that the budget holds plain,
        and sheds down to it (training/budget.py): `compare --budgets` starts each run with that many, `train
        --max-bytes` densifies to no more. The survivors of a larger start beat a count fixed from the start (2dgs on
        the quick sweater: +0.8 dB at 5%, +0.9 at 25%, +1.3 at 100%; BENCHMARKS.md, "Budgeted runs start with twice
        what fits"); how much larger pays depends on the member (Surfel2DModel's, BetaGaborModel's)."""
        return 2.0

    def __init__(self, config: Any, num_primitives: int = 0):
        super().__init__()
        if not dataclasses.is_dataclass(config):
            raise TypeError(f"{type(self).__name__} expects a config dataclass, got {type(config).__name__}")
        self.config = config

    # --- the contract -------------------------------------------------------------------------------
    def surfels(self, camera: Camera) -> Surfels:
        raise NotImplementedError

    def init_from_points(self, points: torch.Tensor, colors: torch.Tensor, generator: torch.Generator) -> None:
        raise NotImplementedError

    def optim_groups(self, scene_extent: float) -> list[dict]:
        """Adam parameter groups: dicts with "name", "params" and "lr". The group named "means" gets the
        exponential position schedule."""
        raise NotImplementedError

    def draws_nothing(self) -> str | None:
        """Why this model, as its parameters stand, renders nothing from anywhere (and so can learn nothing: no pair
        contributes, no gradient flows), naming the parameter; None when it can draw. Loading refuses such a model.
        SplatModel knows no opacity: models that do override it."""
        return None

    # --- rendering ----------------------------------------------------------------------------------
    def render(self, camera: Camera, *, background=None, backend="auto", surfels: Surfels | None = None,
               image_only: bool = False) -> RenderOutput:
        """The model seen from `camera`, rendered as it was trained: with its own render settings (the pixel-footprint
        filter, see RenderSettings) over `background` (a colour [3] or a grey scalar; default: the model's own
        `background`, black if it has none). Differentiable with respect to the parameters (not the camera).

        The camera is moved to the model's device and dtype. backend: "auto" or a name (splatzoo.rasterizers).
        surfels: other surfels of this model for this camera to render with its settings instead of
        `surfels(camera)`, e.g. a recolouring for display or the model with some waves removed.
        image_only: a picture to look at or score, fast: rgb and alpha only, not differentiable (see rasterize).
        """
        from ..rasterizers import rasterize

        p = next(self.parameters(), None)
        cam = camera.to(p.device, p.dtype) if p is not None else camera
        if background is None:
            background = self.background
        if surfels is None:
            with torch.set_grad_enabled(torch.is_grad_enabled() and not image_only):
                surfels = self.surfels(cam)
        return rasterize(surfels, cam, backend=backend, background=background, settings=self.raster_settings,
                         image_only=image_only)

    def set_render_settings(self, settings: RenderSettings | None = None, **changes) -> "SplatModel":
        """The one place the model's render settings change: to `settings` (say another model's, to render alike),
        then `changes` (antialias=..., background=...) on top. Returns the model."""
        new = dataclasses.replace(settings if settings is not None else self.render_settings, **changes)
        if not isinstance(new.antialias, bool):
            raise SplatzooError(f"render setting antialias must be true or false, got {new.antialias!r:.60}")
        background = new.background
        if background is not None:
            try:
                background = tuple(float(c) for c in background)
            except (TypeError, ValueError):
                background = None
            if background is None or len(background) != 3 or not all(math.isfinite(c) for c in background):
                raise SplatzooError(f"render setting background must be a colour of 3 finite numbers or None, got "
                                    f"{new.background!r:.60}")
        self.render_settings = RenderSettings(new.antialias, background)
        return self

    @property
    def antialias(self) -> bool:
        """Rendered with the pixel-footprint filter (RenderSettings.antialias); assigning it sets the render setting."""
        return self.render_settings.antialias

    @antialias.setter
    def antialias(self, value: bool) -> None:
        self.set_render_settings(antialias=value)

    @property
    def background(self) -> tuple[float, float, float] | None:
        """The colour render() draws behind the surfels (RenderSettings.background); assigning it sets the render
        setting."""
        return self.render_settings.background

    @background.setter
    def background(self, value) -> None:
        self.set_render_settings(background=value)

    # --- generic helpers ----------------------------------------------------------------------------
    @property
    def raster_settings(self):
        """The rasterizer settings this model is rendered with (see `antialias`)."""
        from ..rasterizers.common import ANTIALIASED, SETTINGS

        return ANTIALIASED if self.antialias else SETTINGS

    @property
    def num_primitives(self) -> int:
        return next(iter(self.per_primitive().values())).shape[0]

    def per_primitive(self) -> dict[str, torch.Tensor]:
        """Tensors whose first dimension indexes primitives (what densification edits): the trainable parameters,
        then the buffers named in `primitive_buffers`."""
        out: dict[str, torch.Tensor] = dict(self.named_parameters())
        for name in self.primitive_buffers:
            buf = getattr(self, name, None)
            if isinstance(buf, torch.Tensor):
                out[name] = buf
        return out

    def replace_parameters(self, new: dict[str, torch.Tensor]) -> None:
        """Swap per-primitive parameters (and primitive buffers) for tensors with a new primitive count
        (densify, load)."""
        for name, value in new.items():
            if name in self.primitive_buffers:
                old = getattr(self, name)
                value = value.detach()
                if value.is_floating_point() and not old.is_floating_point():
                    value = value.round()  # e.g. read back from a float PLY column
                persistent = name not in self._non_persistent_buffers_set
                self.register_buffer(name, value.to(old.dtype).clone(), persistent=persistent)
            else:
                setattr(self, name, nn.Parameter(value.detach().clone().requires_grad_(True)))

    def edit_primitives(self, optimizer: torch.optim.Optimizer | None, keep: torch.Tensor,
                        new: dict[str, torch.Tensor] | None = None) -> None:
        """Keep rows `keep` (bool [N]) of every per-primitive parameter and buffer and append rows `new[name]` (none:
        only remove); Adam moments of kept rows survive, appended rows start at zero. What densification, relocation
        and a byte budget edit the count with."""
        params = self.per_primitive()
        new = new or {name: p.detach()[:0] for name, p in params.items()}
        by_id = {id(p): name for name, p in params.items()}
        replacements = {name: torch.cat([p.detach()[keep], new[name].to(p)]) for name, p in params.items()}
        old_states = {}
        for group in (optimizer.param_groups if optimizer is not None else ()):
            for i, p in enumerate(group["params"]):
                name = by_id.get(id(p))
                if name is not None:
                    old_states[name] = (group, i, optimizer.state.pop(p, None))
        self.replace_parameters(replacements)
        fresh = self.per_primitive()
        for name, (group, i, state) in old_states.items():
            p = fresh[name]
            group["params"][i] = p
            if state:
                n_new = new[name].shape[0]
                for key in ("exp_avg", "exp_avg_sq"):
                    if key in state:
                        state[key] = torch.cat([state[key][keep], state[key].new_zeros(n_new, *state[key].shape[1:])])
                optimizer.state[p] = state

    def swap_parameter(self, name: str, fn, optimizer: torch.optim.Optimizer | None = None) -> None:
        """Replace parameter `name` by fn(parameter) (any shape), applying fn to its Adam moments too, and point
        the optimizer at the new tensor. For edits along dimensions other than the primitive one."""
        old = getattr(self, name)
        new = nn.Parameter(fn(old.detach()).clone().requires_grad_(True))
        setattr(self, name, new)
        if optimizer is None:
            return
        for group in optimizer.param_groups:
            for i, p in enumerate(group["params"]):
                if p is old:
                    group["params"][i] = new
                    state = optimizer.state.pop(old, None)
                    if state:
                        for key in ("exp_avg", "exp_avg_sq"):
                            if key in state and state[key].shape == old.shape:
                                state[key] = fn(state[key])
                        optimizer.state[new] = state

    @torch.no_grad()
    def set_rows(self, name: str, rows: torch.Tensor, value, optimizer: torch.optim.Optimizer | None = None) -> None:
        """Overwrite rows of parameter (or primitive buffer) `name` in place and restart their Adam moments (a
        re-parametrisation: the old moments describe another quantity)."""
        p = getattr(self, name)
        p[rows] = value
        restart_moments(optimizer, p, rows)

    def split_children(self, rows: dict[str, torch.Tensor], offsets: torch.Tensor,
                       shrink: float) -> dict[str, torch.Tensor]:
        """Split children's per-primitive rows (densification): `rows` are copies of each child's parent with the
        child's centre and scales already set; offsets [M,2] is each child's centre in its parent's (u, v), in the
        parent's sigmas, and the child's sigmas are the parent's / shrink. A model whose appearance varies over
        (u, v) re-expresses it in the child's frame here, so that the child shows what its parent showed where it
        sits: at the child's (u', v') the parent's (u, v) = offsets + (u', v') / shrink. The default returns the
        rows unchanged (right for appearance that is constant over the surfel)."""
        return rows

    def size_bytes(self) -> int:
        """Bytes of stored parameters (float32)."""
        return sum(p.numel() for p in self.parameters()) * 4

    # --- a byte budget ----------------------------------------------------------------------------------------
    def stored_row_bytes(self, precision: str) -> torch.Tensor:
        """[N] the bytes each primitive's rows take in the packed file at `precision` (splatzoo.packing). A model
        whose stored layout is not one row per primitive (packed waves) overrides it."""
        from ..packing import value_bytes

        n = self.num_primitives
        per_row = sum(t[:1].numel() * value_bytes(name, t, precision) for name, t in self.per_primitive().items()
                      if name not in self._non_persistent_buffers_set)
        return torch.full((n,), float(per_row))

    def shed_richness(self) -> "SplatModel":
        """Drop, in place, whatever the model can shed without losing primitives under a byte budget (adaptive
        waves: all of them), and return it: the smallest a model of this count can be. Nothing by default."""
        return self

    def shed_free(self, optimizer=None) -> dict | None:
        """Under a byte budget, before anything is chosen: drop what the model itself judges worth nothing (adaptive
        waves: its own measured pruning, which then runs here instead of on its schedule). Nothing by default."""
        return None

    def shedding_options(self, nbytes: int, precision: str, optimizer=None) -> list[Shedding]:
        """Ways to free at least `nbytes` of the model's stored size at `precision` (or as much as one way can),
        each with a preview of what it would leave for the trainer to measure. By default: the weakest primitives
        (SurfelModel); a model with optional richness adds its own."""
        return []

    def summary(self) -> dict:
        """Model-specific numbers worth reporting next to the metrics (e.g. active waves); {} by default."""
        return {}

    def regulariser(self) -> torch.Tensor | None:
        """A penalty the trainer adds to every view's loss (e.g. sparsity on the waves); None by default."""
        return None

    def wave_fit_step(self, iterations: int) -> int | None:
        """The iteration of a run of `iterations` after which the trainer fits the model's waves to the training photos
        (training/wave_fit.py, through wave_slots and start_waves); None, by default: never."""
        return None

    def on_step(self, step: int, train_config: Any, optimizer: torch.optim.Optimizer) -> dict | None:
        """Called by the trainer after every optimiser step (and after densification), with the run's TrainConfig.
        A model may edit itself here (e.g. drop unused waves); it must then keep `optimizer` pointing at its
        parameters (see swap_parameter). No-op by default."""
        return None

    @classmethod
    def from_points(cls, config, points: torch.Tensor, colors: torch.Tensor, *, seed: int = 0) -> "SplatModel":
        points = torch.as_tensor(points, dtype=torch.float32)
        colors = torch.as_tensor(colors, dtype=torch.float32)
        if points.dim() != 2 or points.shape[1] != 3:
            raise ShapeError(f"points must be [N,3], got {list(points.shape)}")
        if colors.shape != points.shape:
            raise ShapeError(f"colors must be [N,3] like points {list(points.shape)}, got {list(colors.shape)}")
        if not (torch.isfinite(points).all() and torch.isfinite(colors).all()):
            raise ShapeError("points and colors must be finite (no NaN or Inf)")
        if colors.numel() and colors.max() > 1.0 + 1e-6:
            colors = colors / 255.0  # uint8-range colours
        model = cls(config, points.shape[0])
        gen = torch.Generator().manual_seed(seed)
        with torch.no_grad():
            model.init_from_points(points, colors.clamp(0, 1), gen)
        return model

    def checkpoint(self) -> dict:
        ck = {"model": self.name, "config": dataclasses.asdict(self.config),
              "state": {k: v.detach().cpu() for k, v in self.state_dict().items()}}
        if self.antialias:  # absent means False: checkpoints from before the option load unchanged
            ck["antialias"] = True
        if self.background is not None:  # absent means black
            ck["background"] = [float(c) for c in self.background]
        if self.precision != "float32":  # absent means as trained
            ck["precision"] = self.precision
        return ck

    def load_checkpoint_state(self, state: dict) -> None:
        """Inverse of checkpoint()["state"] on a model built with 0 primitives."""
        self.replace_parameters({k: state[k] for k, _ in self.named_parameters()})
        self.load_state_dict(state, strict=False)


class SurfelModel(SplatModel):
    """2D Gaussian surfel geometry shared by every built-in model: position, two scales, rotation, opacity.

    Parameters are stored unconstrained: scales as log sigma, opacity as a logit, rotation as an
    unnormalised quaternion.
    """

    def __init__(self, config, num_primitives: int = 0):
        super().__init__(config, num_primitives)
        n = num_primitives
        self.means = nn.Parameter(torch.zeros(n, 3))
        self.log_scales = nn.Parameter(torch.zeros(n, 2))
        self.quats = nn.Parameter(torch.zeros(n, 4).index_fill_(1, torch.tensor([0]), 1.0))
        self.logit_opacity = nn.Parameter(torch.zeros(n))

    def init_geometry(self, points: torch.Tensor, generator: torch.Generator, *, initial_opacity: float = 0.1,
                      normals: torch.Tensor | None = None) -> None:
        """2DGS initialisation: scale from the nearest-neighbour distance, random rotation, opacity 0.1."""
        dist = nearest_neighbour_distance(points).clamp_min(1e-7)
        self.means.copy_(points)
        self.log_scales.copy_(torch.log(dist)[:, None].expand(-1, 2))
        if normals is not None:
            self.quats.copy_(normals_to_quats(normals))
        else:
            self.quats.copy_(torch.rand(points.shape[0], 4, generator=generator))
        self.logit_opacity.fill_(math.log(initial_opacity / (1 - initial_opacity)))

    def effective_opacity(self) -> torch.Tensor:
        """[N] the most opacity each surfel can show anywhere (what decides whether it is alive): its peak opacity,
        times whatever else scales it inside the surfel (e.g. a texture's alpha)."""
        return torch.sigmoid(self.logit_opacity)

    @torch.no_grad()
    def shedding_options(self, nbytes: int, precision: str, optimizer=None) -> list[Shedding]:
        """The weakest surfels (least opacity x area) whose stored rows add up to `nbytes`; one surfel stays."""
        n = self.num_primitives
        if n <= 1:
            return []
        value = self.effective_opacity().detach() * torch.exp(self.log_scales.detach()).prod(-1)
        order = value.argsort()
        held = self.stored_row_bytes(precision).to(value.device)[order].cumsum(0)
        j = min(int((held < nbytes).sum()) + 1, n - 1)
        keep = torch.ones(n, dtype=torch.bool, device=value.device)
        keep[order[:j]] = False
        kept = keep.nonzero().squeeze(1)
        return [Shedding(f"{j} weakest surfels", lambda camera: self.surfels(camera).index(kept),
                         lambda: self.edit_primitives(optimizer, keep))]

    def draws_nothing(self) -> str | None:
        from ..rasterizers.common import SETTINGS

        n = self.logit_opacity.shape[0]
        if n and float(torch.sigmoid(self.logit_opacity.detach()).max()) < SETTINGS.alpha_min:
            return (f"logit_opacity: every one of its {n} surfels has an opacity below 1/255, which the rasterizer "
                    "skips: the model draws nothing and cannot learn (the run diverged or the file was edited)")
        return None

    def geometry(self) -> dict[str, torch.Tensor]:
        """Surfels geometry fields in activated form. The scales stop at MAX_SCALE (types.py: the range where every
        rasterizer agrees), so a crafted or diverged log-scale (88 would overflow float) renders a huge surfel with
        finite gradients."""
        return {"means": self.means, "quats": self.quats, "scales": torch.exp(self.log_scales.clamp(max=LOG_MAX_SCALE)),
                "opacities": torch.sigmoid(self.logit_opacity)}

    def geometry_groups(self, scene_extent: float) -> list[dict]:
        return [
            {"name": "means", "params": [self.means], "lr": 1.6e-4 * scene_extent},
            {"name": "log_scales", "params": [self.log_scales], "lr": 5e-3},
            {"name": "quats", "params": [self.quats], "lr": 1e-3},
            {"name": "logit_opacity", "params": [self.logit_opacity], "lr": 0.05},
        ]


def restart_moments(optimizer: torch.optim.Optimizer | None, p: torch.Tensor, rows: torch.Tensor) -> None:
    """Zero Adam's moments of parameter `p` at `rows` (edited rows: the old moments describe another quantity)."""
    state = optimizer.state.get(p) if optimizer is not None else None
    for key in ("exp_avg", "exp_avg_sq"):
        if state and key in state and state[key].shape == p.shape:
            state[key][rows] = 0


def view_directions(means: torch.Tensor, camera: Camera) -> torch.Tensor:
    """Unit directions from the camera centre to each mean [N,3]."""
    d = means - camera.center.to(means)
    return d / d.norm(dim=-1, keepdim=True).clamp_min(1e-12)


class ModelOptionError(SplatzooError, TypeError):
    """Model options that do not match the model's config fields."""
