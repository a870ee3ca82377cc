"""Name -> spec registries, with third-party entries discovered lazily from entry points."""
from __future__ import annotations

import difflib
import importlib
import importlib.metadata
from dataclasses import dataclass, field
from typing import Any, Callable, Generic, Iterable, TypeVar

from .errors import DuplicateNameError, PluginError, UnknownNameError

API_VERSION = 1  # bump when the model contract changes incompatibly

S = TypeVar("S")


def closest(name: str, known: Iterable[str]) -> str:
    """A ' Did you mean X?' suffix, or ''."""
    match = difflib.get_close_matches(str(name), list(known), n=1, cutoff=0.5)
    return f". Did you mean {match[0]!r}?" if match else ""


@dataclass
class Entry(Generic[S]):
    name: str
    origin: str            # "built-in" or "plugin (<distribution>)"
    spec: S | None = None  # None until a plugin is loaded
    error: str = ""        # why a plugin failed to load
    loader: Callable[[], S] | None = None

    @property
    def broken(self) -> bool:
        return bool(self.error)


class Registry(Generic[S]):
    """Specs by name. Built-ins register explicitly; plugins come from an entry-point group, imported only
    when first asked for, so a broken plugin breaks nothing but itself."""

    def __init__(self, kind: str, entry_point_group: str | None = None,
                 builtins_module: str | None = None, validate: Callable[[Any, str], S] | None = None):
        self.kind = kind
        self.group = entry_point_group
        self.builtins_module = builtins_module
        self.validate = validate
        self._entries: dict[str, Entry[S]] = {}
        self._discovered = False

    def register(self, name: str, spec: S, origin: str = "built-in") -> S:
        if name in self._entries:
            raise DuplicateNameError(f"{self.kind} {name!r} is registered twice "
                                     f"({self._entries[name].origin} and {origin}); rename one of them")
        self._entries[name] = Entry(name, origin, spec)
        return spec

    def _discover(self) -> None:
        if self._discovered:
            return
        self._discovered = True
        if self.builtins_module:
            importlib.import_module(self.builtins_module)
        if not self.group:
            return
        for ep in importlib.metadata.entry_points(group=self.group):
            dist = getattr(ep, "dist", None)
            origin = f"plugin ({dist.name})" if dist is not None else "plugin"
            if ep.name in self._entries:
                existing = self._entries[ep.name]
                # the same distribution seen twice on sys.path is not a conflict
                if existing.origin == origin:
                    continue
                self._entries[ep.name] = Entry(ep.name, origin, error=(
                    f"name clashes with the {existing.origin} {self.kind} {ep.name!r}; "
                    f"the plugin must use another name"))
                if existing.origin == "built-in":  # the built-in keeps its name
                    self._entries[ep.name] = existing
                continue
            self._entries[ep.name] = Entry(ep.name, origin, loader=ep.load)

    def _load(self, entry: Entry[S]) -> Entry[S]:
        if entry.spec is None and not entry.error and entry.loader is not None:
            try:
                obj = entry.loader()
                entry.spec = self.validate(obj, entry.name) if self.validate else obj
            except Exception as e:  # a plugin can fail in any way; keep the reason to show the user
                entry.error = f"{type(e).__name__}: {e}"
        return entry

    def names(self) -> list[str]:
        """Every known name, plugins included, without importing plugins."""
        self._discover()
        return sorted(self._entries)

    def entries(self) -> list[Entry[S]]:
        """Every entry with plugins loaded (broken ones carry their error)."""
        self._discover()
        return [self._load(self._entries[n]) for n in sorted(self._entries)]

    def get(self, name: str) -> S:
        self._discover()
        if name not in self._entries:
            raise UnknownNameError(f"unknown {self.kind} {name!r}; known: {', '.join(sorted(self._entries))}"
                                   + closest(name, self._entries))
        entry = self._load(self._entries[name])
        if entry.broken:
            raise PluginError(f"{self.kind} {name!r} from {entry.origin} is broken: {entry.error}. "
                              f"Reinstall or fix that plugin; other {self.kind}s still work.")
        return entry.spec  # type: ignore[return-value]

    def __contains__(self, name: str) -> bool:
        self._discover()
        return name in self._entries


@dataclass
class ModelSpec:
    """What a model type declares: the plugin contract (api_version guards against stale plugins).

    cls: a splatzoo.models.base.SplatModel subclass; config_cls: a dataclass of options with defaults.
    """

    name: str
    cls: type
    config_cls: type
    description: str = ""
    api_version: int = API_VERSION
    extra: dict = field(default_factory=dict)


def _entry_spec(obj: Any, name: str, spec_type: type, type_name: str):
    """The spec an entry point names (or a factory of it returns), checked for its type, API version and name."""
    if callable(obj) and not isinstance(obj, (spec_type, type)):
        obj = obj()
    if not isinstance(obj, spec_type):
        raise PluginError(f"entry point must name a {type_name}, got {type(obj).__name__}")
    if obj.api_version != API_VERSION:
        raise PluginError(f"plugin targets splatzoo model API {obj.api_version}, this splatzoo has {API_VERSION}")
    if obj.name != name:
        raise PluginError(f"entry point name {name!r} differs from the spec's name {obj.name!r}")
    return obj


def _validate_model_spec(obj: Any, name: str) -> ModelSpec:
    return _entry_spec(obj, name, ModelSpec, "splatzoo.ModelSpec")


MODELS: Registry[ModelSpec] = Registry("model", entry_point_group="splatzoo.models",
                                       builtins_module="splatzoo.models", validate=_validate_model_spec)


def register_model(spec: ModelSpec) -> ModelSpec:
    """Register a built-in (or programmatic) model spec."""
    return MODELS.register(spec.name, spec)


@dataclass(frozen=True)
class AppearanceKindSpec:
    """A research appearance kind written in Python: the plugin contract of the `splatzoo.appearance_kinds` entry
    points (or register_appearance_kind), rendered and differentiated (by autograd) by the reference backend only.

    fn(u, v, view_dirs, params) -> (rgb, gain), per (pixel, surfel) pair of one shading pass:
      u, v       [P,n]    the point of the surfel where the pair's colour is taken, in sigmas (the ray's hit; (0, 0)
                          where the screen filter wins; anti-aliased, the pixel footprint's centre);
      view_dirs  [P,n,3]  unit world direction of the pixel's ray (from the camera through the pixel: towards the hit);
      params     [n,*params]  the surfels' rows of Surfels.appearance_params;
      rgb        [P,n,3]  added to the colour of the table's kinds (the sum is clamped at 0);
      gain       [P,n] in [0, 1], or None (1): multiplies the opacity (clamped into [0, 1]: a gain never grows a
                          surfel past the screen box of its support).
    Plain differentiable torch code; it must not mix pairs (each output entry depends on its own pair only).
    params: the per-surfel parameter shape. A built-in kind's name (splatzoo.types.BUILTIN_KINDS) is refused.
    """

    name: str
    fn: Callable
    params: tuple
    description: str = ""
    api_version: int = API_VERSION


# the names of the built-in kinds (splatzoo.types.BUILTIN_KINDS, sections of csrc/surfel_math.h), which no Python kind
# may take: filled in by splatzoo.types, which derives them from its field table (this module sits below it)
BUILTIN_KIND_NAMES: set[str] = set()


def _validate_appearance_kind(obj: Any, name: str) -> AppearanceKindSpec:
    obj = _entry_spec(obj, name, AppearanceKindSpec, "splatzoo.registry.AppearanceKindSpec")
    if name in BUILTIN_KIND_NAMES:
        raise PluginError(f"{name!r} is a built-in appearance kind (a section of csrc/surfel_math.h); the plugin must "
                          "use another name")
    if not callable(obj.fn):
        raise PluginError(f"appearance kind {name!r}: fn must be callable, got {type(obj.fn).__name__}")
    params = tuple(obj.params) if isinstance(obj.params, (tuple, list)) else (obj.params,)
    if not all(isinstance(d, int) and not isinstance(d, bool) and d >= 1 for d in params):
        raise PluginError(f"appearance kind {name!r}: params must be the per-surfel parameter shape, positive "
                          f"integers, got {obj.params!r}")
    return obj if params == obj.params else AppearanceKindSpec(obj.name, obj.fn, params, obj.description,
                                                               obj.api_version)


APPEARANCE_KINDS: Registry[AppearanceKindSpec] = Registry("appearance kind",
                                                          entry_point_group="splatzoo.appearance_kinds",
                                                          validate=_validate_appearance_kind)


def register_appearance_kind(spec: AppearanceKindSpec) -> AppearanceKindSpec:
    """Register a Python appearance kind from code (a notebook, a test); plugins use the entry-point group."""
    return APPEARANCE_KINDS.register(spec.name, _validate_appearance_kind(spec, spec.name))
