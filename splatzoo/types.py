"""The data contract shared by every layer: Camera, Surfels and RenderOutput.

Conventions (see README "Conventions"):
- cameras use OpenCV axes: +x right, +y down, +z forward; pixel (i, j) has its centre at (i + 0.5, j + 0.5);
- a surfel is a 2D Gaussian disc: P(u, v) = mean + scale_u * t_u * u + scale_v * t_v * v, with t_u, t_v the first
  two columns of the rotation of the (w, x, y, z) quaternion, so (u, v) are measured in sigmas;
- its colour at (u, v) is max(0, base_color + sum_k amplitude_k * cos(wave_vector_k . (u, v) + phase_k)
  + texture_rgb(u, v)), its opacity o * falloff * texture_alpha(u, v) (the texture, when the batch has one: a T x T
  RGBA texel grid over (u, v) in [-TEXTURE_RADIUS, TEXTURE_RADIUS]^2 sigmas, sampled bilinearly, clamped to its edge).
"""
from __future__ import annotations

import copy
from dataclasses import dataclass, field, fields, replace

import torch

from .errors import ShapeError
from .registry import APPEARANCE_KINDS, BUILTIN_KIND_NAMES


@dataclass
class Camera:
    """A pinhole camera. world_to_camera [4,4] (OpenCV axes), K [3,3] in pixels."""

    world_to_camera: torch.Tensor
    K: torch.Tensor
    width: int
    height: int
    name: str = ""

    def __post_init__(self) -> None:
        self.world_to_camera = torch.as_tensor(self.world_to_camera)
        self.K = torch.as_tensor(self.K)
        if not self.world_to_camera.is_floating_point():
            self.world_to_camera = self.world_to_camera.double()
        self.K = self.K.to(self.world_to_camera.dtype)
        if tuple(self.world_to_camera.shape) != (4, 4):
            raise ShapeError(f"Camera {self.name!r}: world_to_camera must be [4,4], got {list(self.world_to_camera.shape)}")
        if tuple(self.K.shape) != (3, 3):
            raise ShapeError(f"Camera {self.name!r}: K must be [3,3], got {list(self.K.shape)}")
        self.width, self.height = int(self.width), int(self.height)
        if self.width < 1 or self.height < 1:
            raise ShapeError(f"Camera {self.name!r}: image size must be at least 1x1, got {self.width}x{self.height}")
        if not (torch.isfinite(self.world_to_camera).all() and torch.isfinite(self.K).all()):
            raise ShapeError(f"Camera {self.name!r}: world_to_camera and K must be finite")

    @property
    def R(self) -> torch.Tensor:
        """World-to-camera rotation [3,3]."""
        return self.world_to_camera[:3, :3]

    @property
    def t(self) -> torch.Tensor:
        """World-to-camera translation [3]."""
        return self.world_to_camera[:3, 3]

    @property
    def center(self) -> torch.Tensor:
        """Camera centre in world coordinates [3]."""
        return -self.R.T @ self.t

    @property
    def camera_to_world(self) -> torch.Tensor:
        return torch.linalg.inv(self.world_to_camera)

    def to(self, device=None, dtype=None) -> "Camera":
        # cast where the tensors are (the host, for cameras read from files) and check the cast there; then move
        # the checked values, so that a camera sent to a GPU every step never makes the GPU wait for a check
        w2c, K = self.world_to_camera.to(dtype=dtype), self.K.to(dtype=dtype)
        cast = self if w2c is self.world_to_camera and K is self.K else replace(self, world_to_camera=w2c, K=K)
        w2c, K = cast.world_to_camera.to(device=device), cast.K.to(device=device)
        if w2c is cast.world_to_camera and K is cast.K:
            return cast  # nothing moved: skip the copy (a render calls this per frame)
        moved = copy.copy(cast)
        moved.world_to_camera, moved.K = w2c, K
        return moved

    def detach(self) -> "Camera":
        """The same camera with its tensors cut from any autograd graph (rasterizers take cameras as constants)."""
        if not (self.world_to_camera.requires_grad or self.K.requires_grad):
            return self
        return replace(self, world_to_camera=self.world_to_camera.detach(), K=self.K.detach())

    def scaled(self, factor: float) -> "Camera":
        """The same camera for an image resized by `factor` (e.g. 0.5 halves width and height)."""
        w, h = max(1, round(self.width * factor)), max(1, round(self.height * factor))
        K = self.K.clone()
        K[0] *= w / self.width
        K[1] *= h / self.height
        return replace(self, K=K, width=w, height=h)

    @staticmethod
    def look_at(eye, target, up=(0.0, -1.0, 0.0), *, fov_deg: float = 60.0, width: int = 64, height: int = 64,
                name: str = "", dtype=torch.float64) -> "Camera":
        """A camera at `eye` looking at `target`; `up` is the world direction that appears up in the image."""
        eye = torch.as_tensor(eye, dtype=dtype)
        target = torch.as_tensor(target, dtype=dtype)
        up = torch.as_tensor(up, dtype=dtype)
        z = target - eye
        z = z / z.norm()
        x = torch.linalg.cross(z, -up)
        if x.norm() < 1e-9:  # looking along `up`: any perpendicular will do
            x = torch.linalg.cross(z, torch.tensor([1.0, 0.0, 0.0], dtype=dtype))
            if x.norm() < 1e-9:
                x = torch.linalg.cross(z, torch.tensor([0.0, 0.0, 1.0], dtype=dtype))
        x = x / x.norm()
        y = torch.linalg.cross(z, x)
        R = torch.stack([x, y, z])  # rows: camera axes in world coordinates
        w2c = torch.eye(4, dtype=dtype)
        w2c[:3, :3] = R
        w2c[:3, 3] = -R @ eye
        f = 0.5 * width / torch.tan(torch.deg2rad(torch.tensor(fov_deg, dtype=dtype)) / 2)
        K = torch.tensor([[f, 0, width / 2], [0, f, height / 2], [0, 0, 1]], dtype=dtype)
        return Camera(w2c, K, width, height, name)


# Roles of the per-surfel fields: "geometry" is read by the projection (its gradients come back through it); the
# other roles are read by the tile loops for every (surfel, pixel) pair, each with its own gradient buffer.
SURFEL_ROLES = ("geometry", "opacity", "appearance")


# The valid ranges of the fields. Inside them every backend gives the same render and gradients (to float
# rounding; tests/test_native.py holds them to it at the bounds); Surfels.validate refuses values outside, naming
# the field. Models keep their surfels inside by their parametrisation (models/base.py clamps the scales; gabor its
# frequencies). The reasons:
# - MAX_SCALE: the reference's anti-aliasing footprint overflows float beyond scale x focal ~ 1e19, and the camera
#   checks allow focal lengths up to ~3e9 px;
# - MAX_WAVE_NUMBER: float phases k . (u, v) lose their precision beyond it (gradients 5e-4 apart between backends
#   at 1e4, 0.24 at 1e6; 1e3 radians per sigma is 160 periods per sigma, far finer than a pixel of most surfels);
# - MAX_PHASE keeps phase + k . (u, v) where float's cosine is accurate to 1e-3;
# - MAX_COORDINATE, MAX_VALUE: far from float's overflow in the products of the projection and the blend.
MAX_SCALE = 1e8
MAX_WAVE_NUMBER = 1e3
MAX_PHASE = 1e4
MAX_COORDINATE = 1e12
MAX_VALUE = 1e6
# - MAX_FALLOFF: the Beta kernel (1 - s rho/2)^(1/s) keeps a bounded slope at the edge of its support for s <= 1.
MAX_FALLOFF = 1.0
# The texture's half-width in sigmas: its T x T texels tile (u, v) in [-R, R]^2, which covers the support an opacity
# of 1 gives a Gaussian (3.33 sigmas) but for a faint rim, where the edge texels are extended (clamp to edge). The
# same number is csrc/surfel_math.h's TEXTURE_RADIUS.
TEXTURE_RADIUS = 3.0
# Texture alpha multiplies the opacity: kept in [0, 1] so the surfel's support (its screen box) never grows.
TEXTURE_VALID = ((-MAX_VALUE, MAX_VALUE),) * 3 + ((0.0, 1.0),)


def surfel_field(*dims, role: str, doc: str, valid, optional: bool = False, kind: str | None = None):
    """A Surfels field's declaration: its trailing shape per surfel (ints, "K" for the batch's wave count or "T" for
    its texture size), its role (SURFEL_ROLES), what it holds and the closed range `valid` of its values: one
    (lo, hi), or one per entry of the last dimension. An appearance field names its appearance `kind` (snake_case: the
    kind's struct in csrc/surfel_math.h is its CamelCase, its reference twin rasterizers/reference.KIND_TWINS[kind]).
    Everything else is derived from these: Surfels.validate, the native rasterizer's arguments, checks, gradient
    buffers and each kind's field pointers (csrc/surfel_fields.h, generated by splatzoo/rasterizers/fields.py)."""
    if role not in SURFEL_ROLES:
        raise ValueError(f"surfel field role {role!r} is not one of {SURFEL_ROLES}")
    if (role == "appearance") != (kind is not None):
        raise ValueError("an appearance field names its kind (kind='...'), and only an appearance field does")
    if isinstance(valid[0], (tuple, list)):
        valid = tuple(tuple(map(float, r)) for r in valid)
        if not dims or dims[-1] != len(valid):
            raise ValueError("per-channel valid ranges need one (lo, hi) per entry of the field's last dimension")
    else:
        valid = tuple(map(float, valid))
    meta = {"dims": tuple(dims), "role": role, "doc": doc, "valid": valid, "kind": kind}
    # optional: None (the default) stands for zeros, what a model that does not use the field means
    return field(default=None, metadata=meta) if optional else field(metadata=meta)


@dataclass
class Surfels:
    """A batch of N surfels with K waves each, ready to rasterize for one camera. One line per field below: the
    table every layer derives from (SURFEL_FIELDS).

    falloff [N] may be left out (None): zeros, the Gaussian surfel of 2DGS.
    texture [N,T,T,4] may be left out (None): T = 0, no texture (and no cost). texture[i, r, c] is the RGBA texel of
    row r (along v) and column c (along u); its centre lies at (u, v) = -R + (c + 1/2, r + 1/2) 2R/T, R =
    TEXTURE_RADIUS. Its rgb is added to the colour (a residual, as the waves), its alpha in [0, 1] multiplies the
    opacity.
    wave_counts [N] integer or None: surfel i uses only its first wave_counts[i] waves; the others give no colour
    and no gradient, and the native rasterizers skip them (None: all K waves are used). Models with a per-surfel
    number of waves pack the active ones to the front.
    appearance_kind, appearance_params [N,...]: a research appearance kind written in Python, by its registered name
    (splatzoo.registry.APPEARANCE_KINDS: a plugin's `splatzoo.appearance_kinds` entry point), and each surfel's
    parameters for it (the shape its spec declares). Its rgb adds to the colour of the table's kinds and its opacity
    gain multiplies theirs. Only the reference backend renders it (autograd gives its gradients); the native backends
    refuse it by name until it has its own section in csrc/surfel_math.h. None: the table's kinds only.
    """

    means: torch.Tensor = surfel_field(3, role="geometry", doc="centre in world space",
                                       valid=(-MAX_COORDINATE, MAX_COORDINATE))
    quats: torch.Tensor = surfel_field(4, role="geometry", doc="rotation (w, x, y, z), need not be normalised",
                                       valid=(-MAX_VALUE, MAX_VALUE))
    scales: torch.Tensor = surfel_field(2, role="geometry", doc="linear sigma along u, v", valid=(0, MAX_SCALE))
    opacities: torch.Tensor = surfel_field(role="opacity", doc="peak opacity", valid=(0, 1))
    base_color: torch.Tensor = surfel_field(3, role="appearance", kind="wave_bank", doc="view-evaluated colour c0",
                                            valid=(-MAX_VALUE, MAX_VALUE))
    wave_vectors: torch.Tensor = surfel_field("K", 2, role="appearance", kind="wave_bank",
                                              doc="k_k, radians per sigma", valid=(-MAX_WAVE_NUMBER, MAX_WAVE_NUMBER))
    wave_phases: torch.Tensor = surfel_field("K", role="appearance", kind="wave_bank", doc="phi_k, radians",
                                             valid=(-MAX_PHASE, MAX_PHASE))
    wave_amplitudes: torch.Tensor = surfel_field("K", 3, role="appearance", kind="wave_bank",
                                                 doc="a_k, colour per wave", valid=(-MAX_VALUE, MAX_VALUE))
    falloff: torch.Tensor | None = surfel_field(role="opacity", doc="falloff exponent s: 0 the Gaussian exp(-rho/2), "
                                                "else the Beta kernel (1 - s rho/2)^(1/s)", valid=(0, MAX_FALLOFF),
                                                optional=True)
    texture: torch.Tensor | None = surfel_field("T", "T", 4, role="appearance", kind="texture",
                                                doc="RGBA texels over (u, v) in "
                                                "[-TEXTURE_RADIUS, TEXTURE_RADIUS]^2 sigmas: rgb added to the colour, "
                                                "alpha times the opacity", valid=TEXTURE_VALID, optional=True)
    wave_counts: torch.Tensor | None = None
    appearance_kind: str | None = None
    appearance_params: torch.Tensor | None = None

    def __post_init__(self) -> None:
        if isinstance(self.opacities, torch.Tensor):
            # an optional field left out is zeros: no texture (T = 0), the Gaussian falloff
            for f in SURFEL_FIELDS:
                if f.optional and getattr(self, f.name) is None:
                    k = self.wave_vectors.shape[1] if isinstance(self.wave_vectors, torch.Tensor) else 0
                    setattr(self, f.name, self.opacities.new_zeros(f.shape(self.opacities.shape[0], k, 0)))

    @property
    def num(self) -> int:
        return self.means.shape[0]

    @property
    def num_waves(self) -> int:
        return self.wave_vectors.shape[1]

    @property
    def texture_size(self) -> int:
        """T, the texels per side of the batch's textures (0: none)."""
        return self.texture.shape[1]

    @staticmethod
    def empty(num_waves: int = 0, *, device=None, dtype=torch.float32) -> "Surfels":
        return Surfels(**{f.name: torch.zeros(f.shape(0, num_waves, 0), device=device, dtype=dtype)
                          for f in SURFEL_FIELDS})

    @staticmethod
    def constant_color(means, quats, scales, opacities, colors) -> "Surfels":
        """2DGS surfels: K = 0, colour constant over each disc."""
        n = means.shape[0]
        e = means.new_zeros
        return Surfels(means, quats, scales, opacities, colors, e(n, 0, 2), e(n, 0), e(n, 0, 3))

    def tensors(self) -> dict[str, torch.Tensor]:
        """The floating-point (differentiable) fields, in table order; wave_counts is not among them."""
        return {f.name: getattr(self, f.name) for f in SURFEL_FIELDS}

    def map(self, fn, counts_fn=None) -> "Surfels":
        """Apply `fn` to the floating-point fields (and a Python kind's appearance_params); wave_counts goes through
        `counts_fn` (kept as is if None)."""
        counts = self.wave_counts
        if counts is not None and counts_fn is not None:
            counts = counts_fn(counts)
        params = self.appearance_params
        return Surfels(**{k: fn(v) for k, v in self.tensors().items()}, wave_counts=counts,
                       appearance_kind=self.appearance_kind, appearance_params=None if params is None else fn(params))

    def to(self, device=None, dtype=None) -> "Surfels":
        # counts move with the surfels but stay integers
        return self.map(lambda t: t.to(device=device, dtype=dtype), lambda c: c.to(device=device))

    def index(self, idx) -> "Surfels":
        return self.map(lambda t: t[idx], lambda c: c[idx])

    def validate(self) -> "Surfels":
        """Check shapes, dtypes and finiteness against the field table; raise ShapeError naming the field."""
        t = self.tensors()
        for f in SURFEL_FIELDS:
            if not isinstance(t[f.name], torch.Tensor):
                raise ShapeError(f"Surfels.{f.name} must be a torch.Tensor, got {type(t[f.name]).__name__}")
        n = self.means.shape[0] if self.means.dim() == 2 else -1
        k = self.wave_vectors.shape[1] if self.wave_vectors.dim() == 3 else -1
        ts = self.texture.shape[1] if self.texture.dim() == 4 else -1
        dtype, device = self.means.dtype, self.means.device
        for f in SURFEL_FIELDS:
            v = t[f.name]
            if n < 0 or k < 0 or ts < 0 or tuple(v.shape) != f.shape(n, k, ts):
                raise ShapeError(f"Surfels.{f.name} must have shape {f.symbolic_shape()} (N={n}, K={k}, T={ts}), got "
                                 f"{list(v.shape)}")
            if not v.is_floating_point() or v.dtype != dtype or v.device != device:
                raise ShapeError(f"Surfels.{f.name} is {v.dtype} on {v.device}; every field must be {dtype} on {device}")
        # one device-to-host sync for every field (on a GPU each check would otherwise stall the queue); a NaN fails
        # the range test too
        inside = torch.stack([f.inside(v).all() for f, v in zip(SURFEL_FIELDS, t.values())]).tolist()
        for f, ok in zip(SURFEL_FIELDS, inside):
            if not ok:
                v = t[f.name]
                if not torch.isfinite(v).all():
                    raise ShapeError(f"Surfels.{f.name} contains NaN or Inf values; check the model parameters that "
                                     "produced it")
                for ch, (lo, hi) in f.channel_ranges():
                    vc = v if ch is None else v[..., ch]
                    outside = (vc < lo) | (vc > hi)
                    if bool(outside.any()):
                        v = vc
                        break
                what = f.doc if ch is None else f"{f.doc}; channel {ch}"
                raise ShapeError(f"Surfels.{f.name} ({what}) must lie in [{lo:g}, {hi:g}], the range where every "
                                 f"rasterizer gives the same answer; {int(outside.sum())} value(s) lie outside, from "
                                 f"{v.min().item():.4g} to {v.max().item():.4g}. Check the model parameters that "
                                 "produced it")
        c = self.wave_counts
        if c is not None:
            if not isinstance(c, torch.Tensor) or c.is_floating_point() or c.is_complex() or c.dtype == torch.bool:
                raise ShapeError("Surfels.wave_counts must be an integer tensor [N] (or None for all K waves), got "
                                 f"{c.dtype if isinstance(c, torch.Tensor) else type(c).__name__}")
            if tuple(c.shape) != (n,) or c.device != device:
                raise ShapeError(f"Surfels.wave_counts must have shape [N] (N={n}) on {device}, got {list(c.shape)} "
                                 f"on {c.device}")
            lo, hi = torch.stack([c.min(), c.max()]).tolist() if n else (0, 0)
            if lo < 0 or hi > k:
                raise ShapeError(f"Surfels.wave_counts must lie in [0, K={k}], got values in [{lo}, {hi}]")
        self._validate_python_kind(n, dtype, device)
        return self

    def _validate_python_kind(self, n: int, dtype, device) -> None:
        kind, params = self.appearance_kind, self.appearance_params
        if kind is None:
            if params is not None:
                raise ShapeError("Surfels.appearance_params is set but appearance_kind is None; name the appearance "
                                 "kind the parameters are for")
            return
        spec = APPEARANCE_KINDS.get(kind)  # an unknown name lists the known ones
        shape = (n, *spec.params)
        if not isinstance(params, torch.Tensor) or tuple(params.shape) != shape:
            got = list(params.shape) if isinstance(params, torch.Tensor) else type(params).__name__
            raise ShapeError(f"Surfels.appearance_params of the appearance kind {kind!r} must have shape "
                             f"[N,{','.join(map(str, spec.params))}] (N={n}), got {got}")
        if params.dtype != dtype or params.device != device:
            raise ShapeError(f"Surfels.appearance_params is {params.dtype} on {params.device}; every field must be "
                             f"{dtype} on {device}")
        if not bool(torch.isfinite(params).all()):
            raise ShapeError(f"Surfels.appearance_params (appearance kind {kind!r}) contains NaN or Inf values; check "
                             "the model parameters that produced it")


@dataclass(frozen=True)
class SurfelField:
    """One row of the field table, read from the Surfels declaration."""

    name: str
    dims: tuple  # trailing shape per surfel; "K": the batch's wave count, "T": its texture size
    role: str
    doc: str
    valid: tuple  # closed range of the values (lo, hi), or one per entry of the last dimension
    kind: str | None = None  # an appearance field's kind
    optional: bool = False  # may be left out (None): zeros

    def shape(self, n: int, k: int, t: int = 0) -> tuple[int, ...]:
        return (n, *({"K": k, "T": t}.get(d, d) for d in self.dims))

    def channel_ranges(self) -> list:
        """[(None, (lo, hi))] for one range, else [(channel, (lo, hi)), ...] along the last dimension."""
        if isinstance(self.valid[0], tuple):
            return list(enumerate(self.valid))
        return [(None, self.valid)]

    def inside(self, v: torch.Tensor) -> torch.Tensor:
        """Where v lies in its valid range (False for NaN)."""
        ok = None
        for ch, (lo, hi) in self.channel_ranges():
            vc = v if ch is None else v[..., ch]
            o = (vc >= lo) & (vc <= hi)
            ok = o if ok is None else ok & o
        return ok

    def symbolic_shape(self) -> str:
        return "[" + ",".join(["N", *map(str, self.dims)]) + "]"


SURFEL_FIELDS: tuple[SurfelField, ...] = tuple(
    SurfelField(f.name, f.metadata["dims"], f.metadata["role"], f.metadata["doc"], f.metadata["valid"],
                f.metadata["kind"], f.default is None)
    for f in fields(Surfels) if "dims" in f.metadata)
# The appearance kinds of the table, in table order: each has its section in csrc/surfel_math.h and its twin in
# rasterizers/reference.py, and every backend renders it. (A Python kind, Surfels.appearance_kind, is not among them.)
BUILTIN_KINDS: tuple[str, ...] = tuple(dict.fromkeys(f.kind for f in SURFEL_FIELDS if f.kind))
BUILTIN_KIND_NAMES.update(BUILTIN_KINDS)  # a Python appearance kind may not take a built-in kind's name


@dataclass
class RenderOutput:
    """What a rasterizer returns for one camera.

    rgb [H,W,3]; alpha [H,W] = 1 - final transmittance; depth [H,W] expected camera depth of the surface
    (sum w z / sum w; 0 where nothing is hit); median_depth [H,W] (depth where transmittance crosses 0.5);
    normal [H,W,3] world-space, weighted sum of surfel normals that face the camera; distortion [H,W] the
    2DGS depth-distortion term sum_{j<i} w_i w_j (m_i - m_j)^2 on NDC depth m.
    An image-only render (rasterize(..., image_only=True)) has rgb and alpha only; the others are None.
    """

    rgb: torch.Tensor
    alpha: torch.Tensor
    depth: torch.Tensor | None = None
    median_depth: torch.Tensor | None = None
    normal: torch.Tensor | None = None
    distortion: torch.Tensor | None = None

    def tensors(self) -> dict[str, torch.Tensor]:
        """The outputs this render has (all six, or rgb and alpha for an image-only render)."""
        return {f.name: getattr(self, f.name) for f in fields(self) if getattr(self, f.name) is not None}

    def image(self) -> torch.Tensor:
        """rgb as a picture: float [H,W,3] clamped to [0,1], cut from autograd, on the CPU."""
        return self.rgb.detach().clamp(0, 1).cpu()
