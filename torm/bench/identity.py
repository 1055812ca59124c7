"""What a benchmark run *is*: the resolved trial config plus the code that runs it.

Rows of one run folder must come from one definition of a trial. :func:`run_identity` collects it:

- ``bench``: the grid-independent benchmark fields (suite, trial function, base seed, per-trial time
  limit; the ``--set`` strings only when the trial module cannot resolve them into a config);
- ``trial_config``: the fully resolved base trial config (every default included), as returned by the
  trial module's ``check_overrides`` (``torm.bench.trial``: ``to_dict(TrialConfig)``), so a changed
  default (grip force 130 -> 40 N) changes the identity although no override changed;
- ``files``: SHA-256 of every existing file the resolved config names (a robot YAML, a hardware config,
  ONNX weights), so editing such a file changes the identity too;
- ``code``: the git commit of the checkout torm runs from, whether it has uncommitted changes and a
  SHA-256 of those changes (``git diff HEAD``), a SHA-256 of every installed file of the ``torm`` and ``sim``
  packages (so an installed copy without git, edited between two runs, is told apart too), and the versions
  of torm's runtime dependencies.

:func:`identity_hash` is its SHA-256; the runner refuses to resume a folder whose stored identity
differs and lists the differences (:func:`torm.bench.results.diff_dicts`).
"""

from __future__ import annotations

import hashlib
import json
import platform
import re
import subprocess
from collections.abc import Iterable
from importlib import metadata
from pathlib import Path
from typing import Any

#: Extras whose packages shape a result (``dev`` tools such as pytest or ruff do not).
RESULT_EXTRAS = ("hardware", "distributed")
#: Largest file hashed for ``files`` (bigger ones are identified by size and modification time).
MAX_HASH_BYTES = 1 << 30


def git_state(cwd: str | Path | None = None) -> dict[str, Any]:
    """``{"commit", "dirty", "diff_sha256"}`` of the repository holding torm (all None without git).

    ``diff_sha256`` hashes ``git diff HEAD`` (tracked files only), so two different uncommitted states of
    the same commit are told apart; None when the tree is clean.
    """
    package = Path(__file__).resolve().parents[1]  # .../torm
    where = Path(cwd) if cwd is not None else package
    none = {"commit": None, "dirty": None, "diff_sha256": None}
    try:
        top = subprocess.run(["git", "rev-parse", "--show-toplevel"], cwd=where, capture_output=True, text=True,
                             timeout=10)
        if top.returncode != 0 or (cwd is None and Path(top.stdout.strip()).resolve() != package.parent):
            return none  # not a checkout of torm (e.g. installed into another project's repository)
        sha = subprocess.run(["git", "rev-parse", "HEAD"], cwd=where, capture_output=True, text=True, timeout=10)
        if sha.returncode != 0:
            return none
        diff = subprocess.run(["git", "diff", "HEAD", "--no-ext-diff", "--binary"], cwd=where, capture_output=True,
                              timeout=30)
    except (OSError, subprocess.SubprocessError):
        return none
    if diff.returncode != 0:
        return {**none, "commit": sha.stdout.strip()}
    dirty = bool(diff.stdout.strip())
    return {"commit": sha.stdout.strip(), "dirty": dirty,
            "diff_sha256": hashlib.sha256(diff.stdout).hexdigest() if dirty else None}


#: the name torm is installed under (``pyproject.toml``'s ``project.name``; the registry's ``torm`` is another package)
DISTRIBUTION = "torm-glass"


def dependency_versions() -> dict[str, str | None]:
    """Python, torm and every runtime dependency of torm (plus the result-shaping extras) with its version."""
    import torm

    out: dict[str, str | None] = {"python": platform.python_version(), "torm": torm.__version__}
    try:
        requires = metadata.requires(DISTRIBUTION) or []
    except metadata.PackageNotFoundError:
        requires = []
    for req in requires:
        name, _, marker = req.partition(";")
        extra = re.search(r"extra\s*==\s*['\"]([^'\"]+)['\"]", marker)
        if extra and extra.group(1) not in RESULT_EXTRAS:
            continue
        m = re.match(r"\s*([A-Za-z0-9][A-Za-z0-9._-]*)", name)
        if not m:
            continue
        dist = m.group(1).lower()
        try:
            out[dist] = metadata.version(dist)
        except metadata.PackageNotFoundError:
            out[dist] = None
    return dict(sorted(out.items()))


#: Packages whose installed files make up the code of a trial (their hash is part of the run identity).
CODE_PACKAGES = ("torm", "sim")


def package_files_hash(packages: tuple[str, ...] = CODE_PACKAGES) -> str:
    """SHA-256 (hex) of every file of the installed ``packages`` (relative path and content; ``__pycache__``
    and ``.pyc`` skipped): the code that runs, with or without git (an installed copy edited in place, a wheel,
    untracked files in a checkout). 228 files, 8.6 MB, 0.1 s for torm and sim (2026-12-05)."""
    import importlib

    h = hashlib.sha256()
    for name in packages:
        root = Path(importlib.import_module(name).__file__).resolve().parent
        files = sorted(p for p in root.rglob("*") if p.is_file() and "__pycache__" not in p.parts
                       and p.suffix != ".pyc")
        for p in files:
            h.update(f"{name}/{p.relative_to(root).as_posix()}\0".encode())
            h.update(hashlib.sha256(p.read_bytes()).digest())
    return h.hexdigest()


def code_version() -> dict[str, Any]:
    """``{"git": git_state(), "files_sha256": package_files_hash(), "packages": dependency_versions()}``: two runs
    of different code differ even without git (:func:`package_files_hash`)."""
    return {"git": git_state(), "files_sha256": package_files_hash(), "packages": dependency_versions()}


def _file_id(p: Path) -> str:
    st = p.stat()
    if st.st_size > MAX_HASH_BYTES:
        return f"size {st.st_size}, mtime {st.st_mtime_ns}"
    h = hashlib.sha256()
    with open(p, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def referenced_files(data: Any, prefix: str = "") -> dict[str, str]:
    """``{dotted key: sha256}`` for every string value in ``data`` that names an existing file."""
    out: dict[str, str] = {}
    if isinstance(data, dict):
        for k, v in data.items():
            out.update(referenced_files(v, f"{prefix}{k}."))
    elif isinstance(data, (list, tuple)):
        for i, v in enumerate(data):
            out.update(referenced_files(v, f"{prefix}{i}."))
    elif isinstance(data, str) and data and len(data) < 4096 and ("/" in data or "." in data):
        try:
            p = Path(data).expanduser()
            if p.is_file():
                out[prefix.rstrip(".")] = _file_id(p)
        except (OSError, ValueError):
            pass
    return out


def run_identity(bench: dict[str, Any], trial_config: dict[str, Any] | None,
                 code: dict[str, Any] | None = None) -> dict[str, Any]:
    """The identity of a run (module docstring). ``bench``: the benchmark identity fields; ``trial_config``:
    the resolved base trial config (None when the trial module cannot resolve one); ``code``: defaults to
    :func:`code_version`."""
    return {"bench": bench, "trial_config": trial_config,
            "files": referenced_files(trial_config) if trial_config is not None else {},
            "code": code if code is not None else code_version()}


def grid_hash(keys: Iterable[str]) -> str:
    """SHA-256 of a grid's trial keys (``suite/scenario/trial/method``), order-free: two runs of one config with
    different grids (more trials, other scenarios) differ here though their :func:`identity_hash` is equal."""
    return hashlib.sha256(json.dumps(sorted(set(keys))).encode()).hexdigest()


def identity_hash(identity: dict[str, Any]) -> str:
    """SHA-256 (hex) of the identity's canonical JSON (non-finite floats as null)."""
    from torm.bench.results import _clean

    text = json.dumps(_clean(identity), sort_keys=True, separators=(",", ":"), allow_nan=False)
    return hashlib.sha256(text.encode()).hexdigest()


__all__ = ["CODE_PACKAGES", "code_version", "dependency_versions", "git_state", "grid_hash", "identity_hash",
           "package_files_hash", "referenced_files", "run_identity"]
