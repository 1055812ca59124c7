"""On-disk render cache: one entry per rendered view, keyed by everything that changes its pixels.

The key is the sha256 of a canonical JSON document of the *inputs* (see :func:`cache_inputs`): the scene
description digest (scenario, layout seed, every rendered geom's pose/shape/material, scene-builder version),
the camera (K, T_world_cam, size), the renderer settings (every :class:`~torm.capture.render_settings.PbrSettings`
field except ``threads`` and ``cache``, which change no pixel), the resolved Mitsuba variant and version, and any
extra emitters / light scales. Each entry is ``<key>.npz`` (``rgb`` uint8, optional ``instance`` int32) beside
``<key>.json`` holding those inputs in full; :meth:`RenderCache.get` compares the stored inputs with the
requested ones and refuses (with a warning) an entry that does not match, so an entry rendered with other
settings is never reused silently. Writes are atomic (temporary file + rename).

Location: ``$TORM_CACHE_DIR/renders`` (default ``~/.cache/torm/renders``).
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
from pathlib import Path
from typing import Any

import numpy as np

log = logging.getLogger(__name__)

#: Settings fields that do not change a pixel and so are not part of the key.
NON_KEY_SETTINGS = ("threads", "cache")


def cache_root() -> Path:
    """``$TORM_CACHE_DIR`` or ``~/.cache/torm`` (created on first write)."""
    env = os.environ.get("TORM_CACHE_DIR")
    return Path(env).expanduser() if env else Path.home() / ".cache" / "torm"


def canonical(obj: Any) -> Any:
    """JSON-ready canonical form of ``obj``: numbers rounded to 9 significant digits, arrays as shape + sha1.

    Mitsuba objects that convert to arrays (bitmaps, transforms) are hashed as arrays. Raises TypeError for
    anything else (the caller then renders without the cache).
    """
    if isinstance(obj, dict):
        return {str(k): canonical(v) for k, v in sorted(obj.items(), key=lambda kv: str(kv[0]))}
    if isinstance(obj, (list, tuple)):
        return [canonical(v) for v in obj]
    if isinstance(obj, (bool, np.bool_)) or obj is None or isinstance(obj, str):
        return obj if not isinstance(obj, np.bool_) else bool(obj)
    if isinstance(obj, (int, np.integer)):
        return int(obj)
    if isinstance(obj, (float, np.floating)):
        return float(f"{float(obj):.9g}")
    if hasattr(obj, "matrix"):  # mi.ScalarTransform4f
        obj = np.asarray(obj.matrix)
    if not isinstance(obj, np.ndarray):
        try:
            obj = np.asarray(obj)
        except Exception as exc:
            raise TypeError(f"cannot key a {type(obj).__name__}") from exc
        if obj.dtype == object:
            raise TypeError(f"cannot key a {type(obj).__name__}")
    if obj.size <= 16:
        return {"array": np.round(obj.astype(np.float64), 9).tolist()}
    return {"shape": list(obj.shape), "dtype": str(obj.dtype), "sha1": hashlib.sha1(np.ascontiguousarray(obj)
                                                                                   .tobytes()).hexdigest()}


def cache_key(inputs: dict[str, Any]) -> str:
    """sha256 hex digest of the canonical JSON of ``inputs``."""
    return hashlib.sha256(json.dumps(canonical(inputs), sort_keys=True).encode()).hexdigest()


def settings_for_key(settings: Any) -> dict[str, Any]:
    """The settings fields that shape pixels (all but :data:`NON_KEY_SETTINGS`) as a dict."""
    from torm.config import to_dict

    return {k: v for k, v in to_dict(settings).items() if k not in NON_KEY_SETTINGS}


class RenderCache:
    """Render entries under ``root`` (default :func:`cache_root` / ``renders``)."""

    def __init__(self, root: str | Path | None = None) -> None:
        self.root = Path(root) if root is not None else cache_root() / "renders"

    def _paths(self, key: str) -> tuple[Path, Path]:
        d = self.root / key[:2]
        return d / f"{key}.npz", d / f"{key}.json"

    def get(self, key: str, inputs: dict[str, Any]) -> dict[str, np.ndarray] | None:
        """The arrays stored under ``key`` when its stored inputs equal ``inputs``; None otherwise (a mismatch or
        an unreadable entry is logged as a warning and ignored)."""
        npz, meta = self._paths(key)
        if not (npz.exists() and meta.exists()):
            return None
        try:
            stored = json.loads(meta.read_text())
            if stored.get("inputs") != json.loads(json.dumps(canonical(inputs), sort_keys=True)):
                log.warning("render cache entry %s was made from other inputs (settings %s); ignoring it and "
                            "rendering again", npz, stored.get("inputs", {}).get("settings"))
                return None
            with np.load(npz) as z:
                return {k: z[k] for k in z.files}
        except (OSError, ValueError, KeyError) as exc:
            log.warning("render cache entry %s is unreadable (%s); rendering again", npz, exc)
            return None

    def put(self, key: str, inputs: dict[str, Any], arrays: dict[str, np.ndarray]) -> Path:
        """Store ``arrays`` (e.g. ``rgb``, ``instance``) with their ``inputs`` under ``key``; returns the npz path."""
        npz, meta = self._paths(key)
        npz.parent.mkdir(parents=True, exist_ok=True)
        tmp = npz.with_name(f".{npz.stem}.{os.getpid()}.tmp.npz")
        np.savez_compressed(tmp, **arrays)
        tmp.replace(npz)
        tmpj = meta.with_name(f".{meta.stem}.{os.getpid()}.tmp.json")
        tmpj.write_text(json.dumps({"inputs": canonical(inputs)}, sort_keys=True, indent=1))
        tmpj.replace(meta)
        return npz
