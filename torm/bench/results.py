"""A run folder's files, written so that nothing is lost: ``results.jsonl`` and ``manifest.json``.

``results.jsonl``: one JSON object per finished trial and line. Each line is appended with one
``os.write`` on an ``O_APPEND`` descriptor followed by ``fsync``, so a crash or SIGKILL leaves at
most a truncated *last* line. Reading drops (and logs) such a line; before new rows are appended the
runner cuts it off and saves the fragment next to the file (:func:`repair_tail`), never silently.
A corrupted line in the middle (a disk or editing accident) is reported with its 1-based line number
and the valid lines are kept (``strict=True`` raises :class:`BenchmarkError` instead).

``manifest.json`` (replaced atomically through a temp file + ``os.replace``): the resolved config, its
identity hash (:func:`torm.bench.spec.config_hash`), versions, git revision and one entry per
invocation ("session") with start/end timestamps, which the report turns into throughput.

Retries (``torm bench --retry failed``) append a new row for the same key with ``attempt`` one higher
(rows without one are attempt 1): reading keeps the highest attempt of each key in ``rows`` and the
rows it replaced in ``history``, so nothing that happened is lost.

Non-finite floats (NaN, inf) are written as ``null`` so every line is strict JSON.
"""

from __future__ import annotations

import datetime as dt
import json
import logging
import math
import os
import platform
import subprocess
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from torm.errors import BenchmarkError

log = logging.getLogger(__name__)

RESULTS_NAME = "results.jsonl"
MANIFEST_NAME = "manifest.json"
# Row keys that describe how/when a trial ran rather than what it produced (ignored by comparisons).
VOLATILE_KEYS: frozenset[str] = frozenset({"run", "timings", "versions"})


def utc_now() -> str:
    """Current UTC time, ISO 8601 with milliseconds (``2026-11-22T04:16:11.123+00:00``)."""
    return dt.datetime.now(dt.timezone.utc).isoformat(timespec="milliseconds")


def parse_time(text: str) -> dt.datetime:
    return dt.datetime.fromisoformat(text)


def _clean(obj: Any) -> Any:
    """JSON-ready copy: numpy scalars/arrays to Python, non-finite floats to None, tuples to lists."""
    if isinstance(obj, dict):
        return {str(k): _clean(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_clean(v) for v in obj]
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, (str, int, bool)) or obj is None:
        return obj
    if hasattr(obj, "tolist"):  # numpy array or scalar
        return _clean(obj.tolist())
    if isinstance(obj, Path):
        return str(obj)
    return str(obj)


def encode_row(row: dict[str, Any]) -> bytes:
    """One results line: compact strict JSON + ``\\n`` (the row must not contain raw newlines; json escapes them)."""
    return (json.dumps(_clean(row), separators=(",", ":"), allow_nan=False) + "\n").encode()


def append_row(path: str | Path, row: dict[str, Any]) -> None:
    """Append ``row`` as one line with a single ``O_APPEND`` write, then flush it to disk (fsync)."""
    data = encode_row(row)
    fd = os.open(str(path), os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o644)
    try:
        written = os.write(fd, data)
        while written < len(data):  # regular files do not short-write in practice; be safe anyway
            written += os.write(fd, data[written:])
        os.fsync(fd)
    finally:
        os.close(fd)


@dataclass
class ResultsFile:
    """What :func:`read_results` found.

    Attributes:
        rows: the valid rows in file order (one per key; see ``duplicates``).
        bad_lines: 1-based numbers of corrupted lines that were skipped (not counting a truncated last line).
        truncated: the last line had no newline (an interrupted write) and was dropped.
        duplicates: keys seen more than once with the same attempt; the first row is kept.
        history: rows replaced by a later attempt of the same trial (``--retry``), in file order.
        problems: human-readable descriptions of the corrupted, truncated and duplicated lines.
    """

    rows: list[dict[str, Any]] = field(default_factory=list)
    bad_lines: list[int] = field(default_factory=list)
    truncated: bool = False
    duplicates: list[str] = field(default_factory=list)
    history: list[dict[str, Any]] = field(default_factory=list)
    problems: list[str] = field(default_factory=list)

    @property
    def keys(self) -> set[str]:
        return {r["key"] for r in self.rows}


def read_results(path: str | Path, strict: bool = False) -> ResultsFile:
    """Read a ``results.jsonl`` file (missing file: no rows).

    A last line without a newline is an interrupted append: dropped with a warning. Any other line
    that is not a JSON object with a ``key`` is corrupted: with ``strict`` a BenchmarkError names the
    file and line number, otherwise the line is skipped, reported in ``problems`` and logged.
    """
    p = Path(path)
    out = ResultsFile()
    if not p.exists():
        return out
    data = p.read_bytes()
    lines = data.split(b"\n")
    tail = lines.pop()  # b"" when the file ends with a newline
    if tail.strip() and _complete_row(tail):
        lines.append(tail)  # a complete row that only lacks its newline: kept (repair_tail adds the newline)
    elif tail.strip():
        out.truncated = True
        msg = (f"{p}: line {len(lines) + 1} is incomplete (no newline; an interrupted write) "
               f"and was dropped: {tail[:80]!r}")
        out.problems.append(msg)
        log.warning("%s", msg)
    where: dict[str, int] = {}  # key -> index in out.rows
    for i, raw in enumerate(lines, start=1):
        if not raw.strip():
            continue
        try:
            row = json.loads(raw)
            if not isinstance(row, dict) or not isinstance(row.get("key"), str):
                raise ValueError("not a JSON object with a 'key'")
        except ValueError as exc:
            msg = f"{p}: line {i} is corrupted ({exc}); it was skipped, the valid lines are kept: {raw[:80]!r}"
            if strict:
                raise BenchmarkError(msg) from exc
            out.bad_lines.append(i)
            out.problems.append(msg)
            log.warning("%s", msg)
            continue
        k = row["key"]
        if k in where:
            old = out.rows[where[k]]
            if attempt(row) > attempt(old):
                out.history.append(old)
                out.rows[where[k]] = row
                continue
            out.duplicates.append(k)
            out.problems.append(f"{p}: line {i} repeats trial {k!r}; the first row is kept")
            continue
        where[k] = len(out.rows)
        out.rows.append(row)
    return out


def attempt(row: dict[str, Any]) -> int:
    """Which attempt at its trial a row is (1 unless a ``--retry`` wrote it)."""
    try:
        return int(row.get("attempt") or 1)
    except (TypeError, ValueError):
        return 1


def _complete_row(raw: bytes) -> bool:
    """True when ``raw`` is a whole result row (a JSON object with a ``key``)."""
    try:
        row = json.loads(raw)
    except ValueError:
        return False
    return isinstance(row, dict) and isinstance(row.get("key"), str)


def repair_tail(path: str | Path) -> Path | None:
    """Cut an incomplete last line off ``path`` before appending; the fragment is saved, not deleted.

    A last line that is a complete row and lacks only its newline (the write stopped between the row and
    its ``\n``) is kept and the newline added. Returns the file the fragment was saved to
    (``results.jsonl.truncated-<UTC time>``), or None when nothing was cut.
    """
    p = Path(path)
    if not p.exists() or p.stat().st_size == 0:
        return None
    data = p.read_bytes()
    if data.endswith(b"\n"):
        return None
    if _complete_row(data[data.rfind(b"\n") + 1:]):
        with open(p, "ab") as f:
            f.write(b"\n")
            f.flush()
            os.fsync(f.fileno())
        log.warning("%s: the last row lacked its newline (interrupted write); the newline was added", p)
        return None
    cut = data.rfind(b"\n") + 1
    stamp = dt.datetime.now(dt.timezone.utc).strftime("%Y%m%dT%H%M%S")
    saved = p.with_name(f"{p.name}.truncated-{stamp}")
    saved.write_bytes(data[cut:])
    with open(p, "r+b") as f:
        f.truncate(cut)
        f.flush()
        os.fsync(f.fileno())
    log.warning("%s: removed an incomplete last line (interrupted write); its bytes are saved in %s", p, saved)
    return saved


def remove_corrupt_lines(path: str | Path, line_numbers: list[int]) -> Path | None:
    """Move the corrupted lines ``line_numbers`` (1-based, from :func:`read_results`) out of ``path`` into
    ``<name>.corrupt-<UTC time>`` and rewrite ``path`` without them (temp file + fsync + rename), so a damaged
    line is reported once, not on every run. Returns the file holding the removed lines (None: nothing to do).
    The caller holds the run folder's lock."""
    p = Path(path)
    if not line_numbers or not p.exists():
        return None
    bad = set(line_numbers)
    lines = p.read_bytes().split(b"\n")
    keep = [ln for i, ln in enumerate(lines, start=1) if i not in bad]
    stamp = dt.datetime.now(dt.timezone.utc).strftime("%Y%m%dT%H%M%S")
    saved = p.with_name(f"{p.name}.corrupt-{stamp}")
    saved.write_bytes(b"".join(f"line {i}: ".encode() + lines[i - 1] + b"\n" for i in sorted(bad)
                               if i <= len(lines)))
    tmp = p.with_name(p.name + ".tmp")
    with open(tmp, "wb") as f:
        f.write(b"\n".join(keep))
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, p)
    log.warning("%s: %d corrupted line(s) moved to %s", p, len(bad), saved)
    return saved


def write_json_atomic(path: str | Path, data: Any) -> None:
    """Write JSON through ``<path>.tmp`` + fsync + ``os.replace`` (readers see the old or the new file)."""
    p = Path(path)
    tmp = p.with_name(p.name + ".tmp")
    with open(tmp, "w") as f:
        json.dump(_clean(data), f, indent=2, allow_nan=False)
        f.write("\n")
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, p)


def read_manifest(run_dir: str | Path) -> dict[str, Any] | None:
    """The run folder's manifest, or None when there is none; BenchmarkError when it is unreadable."""
    p = Path(run_dir) / MANIFEST_NAME
    if not p.exists():
        return None
    try:
        data = json.loads(p.read_text())
    except ValueError as exc:
        raise BenchmarkError(f"{p} is not valid JSON ({exc}); fix it or start over with --fresh") from exc
    if not isinstance(data, dict) or "config" not in data:
        raise BenchmarkError(f"{p} has no 'config'; it is not a torm bench manifest (use --fresh to start over)")
    return data


def git_revision(cwd: str | Path | None = None) -> dict[str, Any]:
    """``{"commit": sha or None, "dirty": bool or None}`` of the repository holding torm (None without git)."""
    where = Path(cwd) if cwd is not None else Path(__file__).resolve().parent
    try:
        sha = subprocess.run(["git", "rev-parse", "HEAD"], cwd=where, capture_output=True, text=True, timeout=10)
        if sha.returncode != 0:
            return {"commit": None, "dirty": None}
        st = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], cwd=where,
                            capture_output=True, text=True, timeout=10)
        return {"commit": sha.stdout.strip(), "dirty": bool(st.stdout.strip()) if st.returncode == 0 else None}
    except (OSError, subprocess.SubprocessError):
        return {"commit": None, "dirty": None}


def cpu_model() -> str:
    """The CPU's model name (Linux /proc/cpuinfo), for the machine context of result files."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown"


def package_versions() -> dict[str, str | None]:
    """Versions of the packages that shape a result, read from metadata (nothing heavy is imported)."""
    from importlib import metadata

    import torm

    out: dict[str, str | None] = {"torm": torm.__version__, "python": platform.python_version()}
    for name in ("torch", "mujoco", "numpy", "trimesh", "ray"):
        try:
            out[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            out[name] = None
    return out


def diff_dicts(old: dict[str, Any], new: dict[str, Any], prefix: str = "") -> list[str]:
    """Lines ``key: old -> new`` for every differing (nested) key."""
    lines = []
    for k in sorted(set(old) | set(new)):
        a, b = old.get(k, "<unset>"), new.get(k, "<unset>")
        if isinstance(a, dict) and isinstance(b, dict):
            lines += diff_dicts(a, b, f"{prefix}{k}.")
        elif a != b:
            lines.append(f"{prefix}{k}: {a!r} -> {b!r}")
    return lines


def move_aside(run_dir: str | Path) -> Path | None:
    """Move a run folder's results, manifest, logs and recordings into ``run_dir/old-<UTC time>/``.

    Nothing is deleted; returns the folder they went to (None when there was nothing to move).
    """
    d = Path(run_dir)
    names = [n for n in (RESULTS_NAME, MANIFEST_NAME, "logs", "recordings") if (d / n).exists()]
    names += [p.name for p in d.glob(f"{RESULTS_NAME}.truncated-*")]
    if not names:
        return None
    stamp = dt.datetime.now(dt.timezone.utc).strftime("%Y%m%dT%H%M%S")
    dest = d / f"old-{stamp}"
    n = 1
    while dest.exists():
        n += 1
        dest = d / f"old-{stamp}-{n}"
    dest.mkdir()
    for name in names:
        os.replace(d / name, dest / name)
    log.warning("--fresh: moved the previous results of %s to %s", d, dest)
    return dest


def comparable(row: dict[str, Any]) -> dict[str, Any]:
    """``row`` without what legitimately differs between two runs of the same trial.

    Drops :data:`VOLATILE_KEYS` (``run``, ``timings``, ``versions``) at the top level and, at any
    depth, durations: keys ending in ``_s`` (wall-clock seconds, by the project's naming).
    """

    def strip(obj: Any) -> Any:
        if isinstance(obj, dict):
            return {k: strip(v) for k, v in obj.items() if not k.endswith("_s")}
        if isinstance(obj, list):
            return [strip(v) for v in obj]
        return obj

    return strip({k: v for k, v in row.items() if k not in VOLATILE_KEYS})


__all__ = ["MANIFEST_NAME", "RESULTS_NAME", "ResultsFile", "VOLATILE_KEYS", "append_row", "attempt", "comparable",
           "diff_dicts",
           "encode_row", "git_revision", "move_aside", "package_versions", "read_manifest", "read_results",
           "remove_corrupt_lines", "repair_tail", "utc_now", "write_json_atomic"]
