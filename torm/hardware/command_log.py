"""Append-only JSONL log of every command sent to (or withheld from) the real hardware.

One JSON object per line: ``{"t": unix time (s), "iso": UTC time, "kind": str, ...payload}``. Numpy
arrays are written as lists. Thread-safe; a ``None`` path keeps the records in memory only
(``records``), which the tests read.
"""

from __future__ import annotations

import datetime as _dt
import json
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np


def _default(o: Any) -> Any:
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, np.generic):
        return o.item()
    return str(o)


class CommandLog:
    """Timestamped command records, appended to ``path`` (JSONL) when given, and kept in ``records``."""

    def __init__(self, path: str | Path | None = None, keep: int = 10000) -> None:
        self.path = Path(path) if path else None
        if self.path is not None:
            self.path.parent.mkdir(parents=True, exist_ok=True)
        self.records: list[dict[str, Any]] = []
        self._keep = keep
        self._lock = threading.Lock()

    def __call__(self, kind: str, payload: dict[str, Any] | None = None) -> None:
        self.write(kind, **(payload or {}))

    def write(self, kind: str, **payload: Any) -> None:
        """Record one command of type ``kind`` with its payload."""
        t = time.time()
        rec = {"t": t, "iso": _dt.datetime.fromtimestamp(t, _dt.timezone.utc).isoformat(), "kind": kind, **payload}
        line = json.dumps(rec, default=_default)
        with self._lock:
            self.records.append(rec)
            if len(self.records) > self._keep:
                del self.records[: len(self.records) - self._keep]
            if self.path is not None:
                with self.path.open("a") as f:
                    f.write(line + "\n")
