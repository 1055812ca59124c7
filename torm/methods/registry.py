"""Where perception methods come from: the built-ins, installed plug-ins (entry points), ``module:callable``.

Names a trial's ``method`` may take:

- a built-in: ``torm``, ``depth``, ``depth_fusion``, ``oracle`` (:data:`torm.perception.METHODS`), implemented
  through the same interface in :mod:`torm.methods.builtin_methods` (the loop calls their ``run``, which keeps their
  diagnostics; ``perceive`` is the interface);
- a plug-in installed with an entry point in the group ``torm.methods`` (``[project.entry-points."torm.methods"]
  plane_fill = "torm_plane_fill:PlaneFill"`` in the plug-in's ``pyproject.toml``): its entry-point name;
- ``package.module:callable``: any importable factory, no installation needed.

A factory is called with the trial's ``method_options`` as keyword arguments and must return an object with the
:class:`~torm.methods.interface.PerceptionMethod` fields; anything else is a :class:`~torm.errors.PluginError`
naming it. ``torm methods list`` prints every method with its version and source.
"""

from __future__ import annotations

import hashlib
import importlib
import json
from dataclasses import dataclass
from importlib import metadata
from typing import Any

from torm.errors import PluginError

#: the entry-point group plug-in perception methods register in
ENTRY_POINT_GROUP = "torm.methods"
#: built-in methods (classes in torm.methods.builtin_methods; their steps in torm.perception)
BUILTINS: dict[str, str] = {
    "torm": "TORM: silhouettes -> DMTet-Multi -> split objects (the paper's method)",
    "depth": "single-view sensor depth inside the capture's masks, symmetric completion",
    "depth_fusion": "TSDF fusion of every view's sensor depth (Open3D), cut by the masks",
    "oracle": "samples of the true meshes (simulation only; the upper bound)",
}


@dataclass(frozen=True)
class MethodInfo:
    """A method as listed: name, version, where it comes from (``builtin``, ``entry point <dist>``,
    ``module:callable``) and a one-line description."""

    name: str
    version: str
    source: str
    description: str = ""


def is_builtin(name: str) -> bool:
    return name in BUILTINS


def _entry_points() -> dict[str, metadata.EntryPoint]:
    return {ep.name: ep for ep in metadata.entry_points(group=ENTRY_POINT_GROUP)}


def method_names() -> tuple[str, ...]:
    """The names a method goes by without importing it: the built-ins, then the installed entry points."""
    return tuple(BUILTINS) + tuple(sorted(n for n in _entry_points() if n not in BUILTINS))


def resolve_factory(name: str, group: str = ENTRY_POINT_GROUP, kind: str = "method",
                    builtins: tuple[str, ...] = tuple(BUILTINS)) -> tuple[Any, str]:
    """(factory, source) of a plug-in name: ``package.module:callable`` imported, or the entry point ``name`` of
    ``group`` loaded. ``kind`` and ``builtins`` only shape the error messages (UnknownNameError lists the valid
    names; PluginError says what failed to import or load)."""
    if ":" in name:
        mod, _, attr = name.partition(":")
        try:
            obj: Any = importlib.import_module(mod)
            for part in attr.split("."):
                obj = getattr(obj, part)
        except (ImportError, AttributeError) as exc:
            raise PluginError(f"{kind} {name!r}: cannot import {attr!r} from module {mod!r} ({exc}); give "
                              "package.module:callable of an importable factory") from exc
        return obj, "module:callable"
    eps = {ep.name: ep for ep in metadata.entry_points(group=group)}
    if name not in eps:
        from torm.errors import UnknownNameError

        raise UnknownNameError(kind, name, [*builtins, *sorted(eps), "package.module:callable"])
    ep = eps[name]
    try:
        obj = ep.load()
    except Exception as exc:  # a broken plug-in must not look like a missing one
        raise PluginError(f"{kind} {name!r}: its entry point {ep.value!r} fails to load: {exc}") from exc
    dist = getattr(ep, "dist", None)
    return obj, f"entry point ({dist.name if dist else ep.value})"


def _factory(name: str) -> tuple[Any, str]:
    return resolve_factory(name)


def load_method(name: str, options: dict[str, Any] | None = None) -> Any:
    """The method object for ``name``, built with ``options`` and checked against the interface (``name``,
    ``version``, ``needs``, ``perceive``). A built-in name gives its :mod:`torm.methods.builtin_methods` class
    (``options`` are its constructor's arguments, e.g. ``load_method("depth", {"view": 3})``)."""
    from torm.methods.interface import Needs

    if is_builtin(name):
        from torm.methods.builtin_methods import BUILTIN_CLASSES

        factory, source = BUILTIN_CLASSES[name], "builtin"
    else:
        factory, source = _factory(name)
    try:
        method = factory(**(options or {})) if callable(factory) else factory
    except TypeError as exc:
        raise PluginError(f"method {name!r} ({source}): its factory does not accept the options "
                          f"{sorted(options or {})}: {exc}") from exc
    missing = [a for a in ("name", "version", "needs", "perceive") if not hasattr(method, a)]
    if missing or not callable(getattr(method, "perceive", None)):
        raise PluginError(f"method {name!r} ({source}) lacks {', '.join(missing) or 'a callable perceive'}: a "
                          "perception method needs name, version, needs (torm.methods.Needs) and "
                          "perceive(capture, context)")
    if not isinstance(method.needs, Needs):
        raise PluginError(f"method {name!r}: needs must be a torm.methods.Needs, got {type(method.needs).__name__}")
    return method


def method_info(name: str, options: dict[str, Any] | None = None) -> MethodInfo:
    """Name, version and source of any method name (built-in or plug-in)."""
    if is_builtin(name):
        import torm

        return MethodInfo(name, torm.__version__, "builtin", BUILTINS[name])
    m = load_method(name, options)
    _, source = _factory(name)
    doc = (type(m).__doc__ or "").strip().splitlines()
    return MethodInfo(str(m.name), str(m.version), source, doc[0] if doc else "")


def check_method_name(name: str) -> None:
    """Raise (UnknownNameError / PluginError) unless ``name`` is a built-in or a plug-in that can be found.
    Loads nothing but the entry-point table and, for ``module:callable``, the module."""
    if is_builtin(name):
        return
    _factory(name)


def list_methods() -> list[MethodInfo]:
    """Every built-in and installed plug-in method (a plug-in that fails to load is listed with its error)."""
    out = [method_info(n) for n in BUILTINS]
    for name in sorted(_entry_points()):
        try:
            out.append(method_info(name))
        except Exception as exc:  # listed, not fatal
            out.append(MethodInfo(name, "?", "entry point", f"fails to load: {exc}"))
    return out


def options_hash(options: dict[str, Any]) -> str:
    """First 12 hex digits of the sha256 of the options as sorted JSON (what a result row records)."""
    return hashlib.sha256(json.dumps(options, sort_keys=True, default=str).encode()).hexdigest()[:12]
