"""Config loading: frozen dataclasses from YAML/dicts, unknown keys rejected, ``a.b=c`` overrides.

Every package defines its own frozen dataclass config and validates it in ``__post_init__``
(raising :class:`~torm.errors.ConfigError`). This module turns nested mappings into those
dataclasses, and applies two rules to every config without the config having to ask:

- numbers: YAML is read with :class:`ConfigLoader`, which resolves every YAML 1.2 / JSON number
  spelling (``1e-7``, ``1E5``, ``.5``) as a number; PyYAML's YAML 1.1 resolver reads ``1e-7`` as a
  string;
- finiteness: every ``float`` field (also inside tuples and optionals) refuses NaN and +-inf. A field
  that may be infinite says so with the annotated type :data:`InfFloat` (``Annotated[float,
  ALLOW_INF]``); it still refuses NaN. :func:`check_finite` applies the same rule to an instance built
  directly in Python (call it from ``__post_init__``);
- ranges: a number field annotated ``Annotated[int, Range(1, 1 << 18, "why")]`` refuses values outside
  ``[lo, hi]`` with the reason, in both paths. Every size and iteration count carries an upper bound this way,
  so an absurd value (``grasp.n_samples=1e12``) is a named error before any work starts, not an
  out-of-memory kill or a hang; :func:`bounded_fields` lists them (docs and the bad-input tests read it).

>>> from dataclasses import dataclass
>>> @dataclass(frozen=True)
... class Inner:
...     res: int = 32
>>> @dataclass(frozen=True)
... class Outer:
...     inner: Inner = Inner()
>>> from_dict(Outer, {"inner": {"res": 48}}, overrides=["inner.res=64"]).inner.res
64
"""

from __future__ import annotations

import dataclasses
import math
import re
import types
import typing
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Annotated, Any, TypeVar

import yaml

from torm.errors import ConfigError

T = TypeVar("T")


class _AllowInf:
    """Marker in ``Annotated[float, ALLOW_INF]``: the field may be +-inf (never NaN)."""

    def __repr__(self) -> str:
        return "ALLOW_INF"


ALLOW_INF = _AllowInf()
#: A float config field that may be infinite (e.g. "no limit"); NaN is still refused.
InfFloat = Annotated[float, ALLOW_INF]


@dataclasses.dataclass(frozen=True)
class Range:
    """Marker in ``Annotated[int | float, Range(lo, hi, why)]``: the field must lie in ``[lo, hi]``.

    Attributes:
        lo: smallest valid value (None: no lower bound).
        hi: largest valid value (None: no upper bound).
        why: what the bound protects, for the error message (e.g. ``"~48 B per point per object"``).
    """

    lo: float | None = None
    hi: float | None = None
    why: str = ""

    def check(self, value: float, where: str) -> None:
        """Raise ConfigError naming ``where`` when ``value`` is outside ``[lo, hi]`` (None and bools pass)."""
        if value is None or isinstance(value, bool) or not isinstance(value, (int, float)):
            return
        if (self.lo is not None and value < self.lo) or (self.hi is not None and value > self.hi):
            lo = "-inf" if self.lo is None else f"{self.lo:g}"
            hi = "inf" if self.hi is None else f"{self.hi:g}"
            why = f" ({self.why})" if self.why else ""
            raise ConfigError(f"{where}={value:g} is outside its valid range [{lo}, {hi}]{why}; give a value in range")


def _range_of(tp: Any) -> Range | None:
    """The :class:`Range` inside ``Annotated[...]`` (also within ``X | None``), else None."""
    if typing.get_origin(tp) in (typing.Union, types.UnionType):
        return next((r for r in map(_range_of, typing.get_args(tp)) if r is not None), None)
    if typing.get_origin(tp) is Annotated:
        return next((m for m in typing.get_args(tp)[1:] if isinstance(m, Range)), None)
    return None


def bounded_fields(cls: type, prefix: str = "") -> dict[str, Range]:
    """Every field of the config dataclass ``cls`` (nested configs too) that carries a :class:`Range`, by dotted
    path (``{"reconstruction.points_per_object": Range(1, 262144, ...)}`` for the trial config)."""
    out: dict[str, Range] = {}
    hints = typing.get_type_hints(cls, include_extras=True)
    for f in dataclasses.fields(cls):
        tp = hints.get(f.name, Any)
        base = _annotated(tp)[0]
        if dataclasses.is_dataclass(base) and isinstance(base, type):
            out.update(bounded_fields(base, f"{prefix}{f.name}."))
        elif (r := _range_of(tp)) is not None:
            out[f"{prefix}{f.name}"] = r
    return out


class ConfigLoader(yaml.SafeLoader):
    """PyYAML's SafeLoader with the YAML 1.2 core-schema float resolver added to YAML 1.1's.

    YAML 1.1 (PyYAML) needs a dot and a signed exponent (``1.0e-7``); YAML 1.2 and JSON also write
    ``1e-7``, ``1E+5``, ``2e3`` and ``.5``. Everything PyYAML read as a float before still is one.
    """


# the float resolver is per first character: drop the 1.1 one, add the union of 1.1 and 1.2 spellings
ConfigLoader.yaml_implicit_resolvers = {
    ch: [(tag, rx) for tag, rx in resolvers if tag != "tag:yaml.org,2002:float"]
    for ch, resolvers in yaml.SafeLoader.yaml_implicit_resolvers.items()
}
ConfigLoader.add_implicit_resolver(
    "tag:yaml.org,2002:float",
    re.compile(r"""^(?:[-+]?(?:[0-9][0-9_]*)\.[0-9_]*(?:[eE][-+]?[0-9]+)?
                  |[-+]?(?:[0-9][0-9_]*)[eE][-+]?[0-9]+
                  |[-+]?\.[0-9][0-9_]*(?:[eE][-+]?[0-9]+)?
                  |[-+]?[0-9][0-9_]*(?::[0-5]?[0-9])+\.[0-9_]*
                  |[-+]?\.(?:inf|Inf|INF)
                  |\.(?:nan|NaN|NAN))$""", re.X),
    list("-+0123456789."),
)
# YAML 1.2 octal (0o17); YAML 1.1's 017 and 0x1F are already ints
ConfigLoader.add_implicit_resolver("tag:torm,2026:octal", re.compile(r"^0o[0-7]+$"), ["0"])
ConfigLoader.add_constructor("tag:torm,2026:octal", lambda loader, node: int(node.value[2:], 8))


def parse_yaml(text: str) -> Any:
    """Parse YAML (or JSON) text with :class:`ConfigLoader`; yaml.YAMLError on bad syntax."""
    return yaml.load(text, Loader=ConfigLoader)  # noqa: S506 - ConfigLoader is a SafeLoader


def parse_override(text: str) -> tuple[list[str], Any]:
    """Parse ``a.b.c=value`` into (["a", "b", "c"], value); the value is read as YAML (``64``, ``[1, 2]``, ``true``)."""
    if "=" not in text:
        raise ConfigError(f"override {text!r} must look like section.key=value (e.g. reconstruction.grid_res=64)")
    key, _, raw = text.partition("=")
    path = [p for p in key.strip().split(".") if p]
    if not path:
        raise ConfigError(f"override {text!r} has an empty key")
    try:
        value = parse_yaml(raw) if raw.strip() else ""
    except yaml.YAMLError as exc:
        raise ConfigError(f"override {text!r}: cannot parse the value as YAML ({exc})") from exc
    return path, value


def apply_overrides(data: Mapping[str, Any], overrides: Iterable[str]) -> dict[str, Any]:
    """Return a deep copy of ``data`` with ``a.b=c`` overrides applied (creating nested dicts as needed)."""
    out: dict[str, Any] = _deepcopy(data)
    for text in overrides:
        path, value = parse_override(text)
        node = out
        for part in path[:-1]:
            nxt = node.get(part)
            if nxt is None:
                nxt = node[part] = {}
            elif not isinstance(nxt, dict):
                raise ConfigError(f"override {text!r}: {part!r} is a value, not a section")
            node = nxt
        node[path[-1]] = value
    return out


def _deepcopy(data: Any) -> Any:
    if isinstance(data, Mapping):
        return {k: _deepcopy(v) for k, v in data.items()}
    if isinstance(data, list):
        return [_deepcopy(v) for v in data]
    return data


def load_yaml(path: str | Path) -> dict[str, Any]:
    """Read a YAML mapping from ``path``; errors name the file."""
    p = Path(path)
    if not p.is_file():
        raise ConfigError(f"config file {p} does not exist; check the path")
    try:
        data = parse_yaml(p.read_text()) or {}
    except yaml.YAMLError as exc:
        raise ConfigError(f"{p}: invalid YAML ({exc})") from exc
    if not isinstance(data, dict):
        raise ConfigError(f"{p}: the top level must be a mapping of keys to values")
    return data


def from_dict(cls: type[T], data: Mapping[str, Any] | None = None, overrides: Iterable[str] = (), where: str = "") -> T:
    """Build the frozen dataclass ``cls`` from a nested mapping; unknown keys raise ConfigError naming them."""
    data = apply_overrides(data or {}, overrides)
    return _build(cls, data, where or cls.__name__)


def load(cls: type[T], path: str | Path | None = None, overrides: Iterable[str] = ()) -> T:
    """Load ``cls`` from a YAML file (or defaults when ``path`` is None) plus ``a.b=c`` overrides."""
    data = load_yaml(path) if path is not None else {}
    where = str(path) if path is not None else cls.__name__
    return from_dict(cls, data, overrides, where=where)


def with_options(cls: type[T], config: T | Mapping[str, Any] | None, options: Mapping[str, Any],
                 where: str = "") -> T:
    """``config`` (an instance of ``cls``, a mapping or None for the defaults) with keyword ``options`` on top.

    Used by constructors that take a config plus keyword overrides (e.g. ``gymnasium.make(id, cameras=())``);
    unknown keys raise ConfigError listing the valid ones.
    """
    base = to_dict(config) if isinstance(config, cls) else dict(config or {})
    return from_dict(cls, {**base, **options}, where=where or cls.__name__)


def to_dict(obj: Any) -> Any:
    """A dataclass config as plain JSON/YAML-friendly data (tuples become lists)."""
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return {f.name: to_dict(getattr(obj, f.name)) for f in dataclasses.fields(obj)}
    if isinstance(obj, (list, tuple)):
        return [to_dict(v) for v in obj]
    if isinstance(obj, dict):
        return {k: to_dict(v) for k, v in obj.items()}
    if isinstance(obj, Path):
        return str(obj)
    return obj


def _build(cls: type, data: Any, where: str) -> Any:
    if not isinstance(data, Mapping):
        raise ConfigError(f"{where}: expected a mapping for {cls.__name__}, got {type(data).__name__}")
    hints = typing.get_type_hints(cls, include_extras=True)
    fields = {f.name: f for f in dataclasses.fields(cls) if f.init}
    unknown = sorted(set(data) - set(fields))
    if unknown:
        raise ConfigError(f"{where}: unknown key(s) {unknown} for {cls.__name__}; valid keys: {sorted(fields)}")
    kwargs = {name: _coerce(hints[name], value, f"{where}.{name}") for name, value in data.items()}
    try:
        return cls(**kwargs)
    except ConfigError:
        raise
    except (TypeError, ValueError) as exc:
        raise ConfigError(f"{where}: {exc}") from exc


def _check_float(value: float, where: str, allow_inf: bool) -> float:
    """``value`` when finite (or infinite with ``allow_inf``); ConfigError naming the field otherwise."""
    if math.isnan(value):
        raise ConfigError(f"{where}: NaN is not a valid value; give a number")
    if math.isinf(value) and not allow_inf:
        raise ConfigError(f"{where}: {value} is not allowed; give a finite number")
    return value


def _annotated(tp: Any) -> tuple[Any, bool]:
    """(the type inside ``Annotated[...]``, whether it carries :data:`ALLOW_INF`); (tp, False) otherwise."""
    if typing.get_origin(tp) is Annotated:
        base, *meta = typing.get_args(tp)
        return base, any(m is ALLOW_INF for m in meta)
    return tp, False


def check_finite(obj: Any, where: str = "") -> None:
    """Refuse NaN / inf in every float field of the dataclass instance ``obj`` (nested configs too), and values
    outside a field's :class:`Range`.

    The rule of :func:`from_dict` for instances built directly in Python: call it from a top-level
    config's ``__post_init__``. Fields typed :data:`InfFloat` may be infinite; ``Any``/``dict`` fields
    are not inspected.
    """
    if not (dataclasses.is_dataclass(obj) and not isinstance(obj, type)):
        return
    hints = typing.get_type_hints(type(obj), include_extras=True)
    for f in dataclasses.fields(obj):
        _check_value(hints.get(f.name, Any), getattr(obj, f.name), f"{where or type(obj).__name__}.{f.name}")


def _check_value(tp: Any, value: Any, where: str) -> None:
    if (rng := _range_of(tp)) is not None:
        rng.check(value, where)
    tp, allow_inf = _annotated(tp)
    origin, args = typing.get_origin(tp), typing.get_args(tp)
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        check_finite(value, where)
    elif origin in (typing.Union, types.UnionType):
        if any(_annotated(a)[0] is float for a in args) and isinstance(value, float):
            _check_float(value, where, any(_annotated(a) == (float, True) for a in args))
    elif origin in (tuple, list) and isinstance(value, (tuple, list)):
        if origin is tuple and args and not (len(args) == 2 and args[1] is Ellipsis):
            for i, (a, v) in enumerate(zip(args, value, strict=False)):
                _check_value(a, v, f"{where}[{i}]")
        elif args:
            for i, v in enumerate(value):
                _check_value(args[0], v, f"{where}[{i}]")
    elif tp is float and isinstance(value, (int, float)) and not isinstance(value, bool):
        _check_float(float(value), where, allow_inf)


def _coerce(tp: Any, value: Any, where: str) -> Any:
    rng = _range_of(tp)
    out = _coerce_type(tp, value, where)
    if rng is not None:
        rng.check(out, where)
    return out


def _coerce_type(tp: Any, value: Any, where: str) -> Any:
    tp, allow_inf = _annotated(tp)
    origin = typing.get_origin(tp)
    args = typing.get_args(tp)
    if dataclasses.is_dataclass(tp):
        return _build(tp, value, where)
    if origin in (typing.Union, types.UnionType):
        if value is None and type(None) in args:
            return None
        errors = []
        for arg in args:
            if arg is type(None):
                continue
            try:
                return _coerce(arg, value, where)
            except ConfigError as exc:
                errors.append(str(exc))
        raise ConfigError(f"{where}: {value!r} does not match {tp}: {'; '.join(errors)}")
    if origin is typing.Literal:
        if value not in args:
            raise ConfigError(f"{where}: {value!r} is not one of {list(args)}")
        return value
    if origin in (tuple, list):
        if not isinstance(value, (list, tuple)):
            raise ConfigError(f"{where}: expected a list, got {value!r}")
        if origin is tuple and len(args) == 2 and args[1] is Ellipsis:
            return tuple(_coerce(args[0], v, f"{where}[{i}]") for i, v in enumerate(value))
        if origin is tuple and args:
            if len(args) != len(value):
                raise ConfigError(f"{where}: expected {len(args)} values, got {len(value)}")
            return tuple(_coerce(a, v, f"{where}[{i}]") for i, (a, v) in enumerate(zip(args, value, strict=True)))
        inner = args[0] if args else Any
        seq = [_coerce(inner, v, f"{where}[{i}]") for i, v in enumerate(value)]
        return tuple(seq) if origin is tuple else seq
    if origin in (dict, Mapping):
        if not isinstance(value, Mapping):
            raise ConfigError(f"{where}: expected a mapping, got {value!r}")
        return dict(value)
    if tp is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ConfigError(f"{where}: expected a number, got {value!r}")
        return _check_float(float(value), where, allow_inf)
    if tp is int:
        if isinstance(value, bool) or not (isinstance(value, int) or (isinstance(value, float) and value.is_integer())):
            raise ConfigError(f"{where}: expected an integer, got {value!r}")
        return int(value)
    if tp is bool:
        if not isinstance(value, bool):
            raise ConfigError(f"{where}: expected true or false, got {value!r}")
        return value
    if tp is str:
        if not isinstance(value, str):
            raise ConfigError(f"{where}: expected a string, got {value!r}")
        return value
    if tp is Path:
        return Path(value)
    return value
