"""Install torm in fresh virtual environments across Python versions and at both ends of its dependency ranges.

Proves what ``pyproject.toml`` claims: for each profile a new venv is made with that Python, torm is installed
with ``pip install .[dev]`` (plus a constraints file for the profile), then ``import torm`` and a smoke selection
of the test suite run in it (foundation, config, a closed-loop oracle trial, the gymnasium envs, reconstruction).

Profiles (``--profile`` to run some; default all):

- ``py3.11-lowest``: every direct dependency pinned to the lower end of its range in pyproject.toml;
- ``py3.11-newest``: the newest releases the ranges allow on this machine;
- ``py3.10``, ``py3.12``, ``py3.13``: newest releases on the other supported Pythons (from ``~/.pyenv``).

A profile whose Python is not installed is reported as ``skipped`` (not run), never as passed. Torch wheels
other than the CPU 2.13.0 one on this machine's disk come from PyPI (CUDA builds, several GB each; about a
minute to download here); each venv is deleted after its run (``--keep`` keeps them).

Writes ``benchmarks/results/install_matrix.{json,md}``; each profile's result is appended as it finishes, so an
interrupted run loses nothing (re-run to continue; ``--fresh`` starts over). About 3-6 minutes per profile here.

Usage: ``python benchmarks/install_matrix.py [--profile py3.12 ...] [--fresh] [--keep]``
"""

from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "benchmarks" / "results"
WORK = ROOT / "runs" / "install_matrix"
PYENV = Path.home() / ".pyenv" / "versions"

#: Test files run in every environment (about 1-2 minutes on 2 cores).
SMOKE_TESTS = ("tests/test_foundation.py", "tests/test_pipeline_context.py", "tests/test_pipeline_smoke.py",
               "tests/test_env_pick.py", "tests/test_recon_geometry.py", "tests/test_cli_help.py",
               "tests/test_bench_stats.py")
#: Packages whose installed version each result records.
REPORTED = ("torch", "mujoco", "dm-control", "mink", "numpy", "scipy", "numba", "trimesh", "coacd", "onnxruntime",
            "opencv-python-headless", "gymnasium", "rerun-sdk", "ray", "dm-env")


def lower_bounds(pyproject: Path) -> dict[str, str]:
    """``name -> lowest allowed version`` of every direct dependency (core + dev extra) with a ``>=`` bound."""
    text = pyproject.read_text()
    deps = re.search(r"^dependencies = \[(.*?)^\]", text, re.S | re.M).group(1)
    dev = re.search(r"^dev = \[(.*?)\]$", text, re.S | re.M).group(1)
    out = {}
    for spec in re.findall(r'"([^"]+)"', deps + dev):
        m = re.match(r"([A-Za-z0-9_.\-\[\]]+?)\s*(?:\[[^\]]*\])?\s*>=\s*([0-9][^,\s;]*)", spec)
        if m:
            out[m.group(1)] = m.group(2)
    return out


def python_for(version: str) -> Path | None:
    """The pyenv interpreter for ``3.X`` (newest patch release installed), or None."""
    cands = sorted(PYENV.glob(f"{version}.*"), key=lambda p: [int(x) for x in p.name.split(".") if x.isdigit()])
    exe = cands[-1] / "bin" / "python3" if cands else None
    return exe if exe is not None and exe.exists() else None


def profiles() -> dict[str, dict]:
    low = lower_bounds(ROOT / "pyproject.toml")
    return {
        "py3.11-lowest": {"python": "3.11", "constraints": low, "note": "every direct dependency at its lower bound"},
        "py3.11-newest": {"python": "3.11", "constraints": {}, "note": "newest releases the ranges allow"},
        "py3.10": {"python": "3.10", "constraints": {}, "note": "newest releases"},
        "py3.12": {"python": "3.12", "constraints": {}, "note": "newest releases"},
        "py3.13": {"python": "3.13", "constraints": {}, "note": "newest releases"},
    }


def _run(cmd: list[str], env: dict[str, str], timeout: float, log: Path) -> tuple[int, float]:
    t = time.perf_counter()
    with log.open("a") as f:
        f.write(f"$ {' '.join(cmd)}\n")
        f.flush()
        try:
            rc = subprocess.run(cmd, cwd=ROOT, env=env, stdout=f, stderr=subprocess.STDOUT, timeout=timeout).returncode
        except subprocess.TimeoutExpired:
            rc = 124
    return rc, time.perf_counter() - t


def run_profile(name: str, prof: dict, keep: bool) -> dict:
    py = python_for(prof["python"])
    out = {"profile": name, "python": prof["python"], "note": prof["note"], "constraints": prof["constraints"]}
    if py is None:
        return {**out, "status": "skipped", "reason": f"no Python {prof['python']} under {PYENV}"}
    venv = WORK / name
    shutil.rmtree(venv, ignore_errors=True)
    WORK.mkdir(parents=True, exist_ok=True)
    log = WORK / f"{name}.log"
    log.write_text("")
    env = {k: v for k, v in os.environ.items() if k not in ("VIRTUAL_ENV", "PYTHONPATH", "PYTHONHOME")}
    env.update(MUJOCO_GL="egl", PYOPENGL_PLATFORM="egl", TORM_THREADS="1", OMP_NUM_THREADS="1")
    rc, _ = _run([str(py), "-m", "venv", str(venv)], env, 300, log)
    pip = [str(venv / "bin" / "python"), "-m", "pip"]
    rc = rc or _run([*pip, "install", "-q", "--upgrade", "pip"], env, 600, log)[0]
    cons = WORK / f"{name}.constraints.txt"
    # X.Y bounds take the first release series (==X.Y.*: e.g. opencv's 4.9.0.80); X.Y.Z bounds that release.
    cons.write_text("".join(f"{k}=={v}{'.*' if v.count('.') < 2 else ''}\n" for k, v in prof["constraints"].items()))
    if prof["constraints"]:
        env["PIP_CONSTRAINT"] = str(cons)
    install_rc, install_s = _run([*pip, "install", "-q", ".[dev]"], env, 3600, log) if rc == 0 else (rc, 0.0)
    out.update(python_exe=str(py), install_rc=install_rc, install_s=round(install_s, 1))
    if install_rc != 0:
        if not keep:
            shutil.rmtree(venv, ignore_errors=True)
        return {**out, "status": "install_failed", "log_tail": log.read_text()[-3000:]}
    freeze = subprocess.run([*pip, "list", "--format", "json"], capture_output=True, text=True, env=env).stdout
    # PEP 503 names: pip lists dm-control as "dm_control"
    have = {re.sub(r"[-_.]+", "-", d["name"]).lower(): d["version"] for d in json.loads(freeze or "[]")}
    out["versions"] = {p: have.get(p) for p in REPORTED}
    out["python_version"] = subprocess.run([str(venv / "bin" / "python"), "-c", "import platform; print("
                                            "platform.python_version())"], capture_output=True, text=True
                                           ).stdout.strip()
    imp_rc, _ = _run([str(venv / "bin" / "python"), "-c", "import torm, torm.env, sim.world, torm.reconstruction"],
                     env, 600, log)
    test_rc, test_s = _run([str(venv / "bin" / "python"), "-m", "pytest", "-q", "-x", "-p", "no:cacheprovider",
                            *SMOKE_TESTS], env, 3600, log)
    tail = log.read_text().splitlines()
    summary = next((x for x in reversed(tail) if re.search(r"\d+ (passed|failed)", x)), "")
    out.update(import_rc=imp_rc, tests_rc=test_rc, tests_s=round(test_s, 1), tests_summary=summary.strip("= "))
    out["status"] = "passed" if imp_rc == 0 and test_rc == 0 else "tests_failed"
    if out["status"] != "passed":
        out["log_tail"] = "\n".join(tail[-60:])
    if not keep:
        shutil.rmtree(venv, ignore_errors=True)
    return out


def write(results: list[dict]) -> None:
    from datetime import datetime, timezone

    RESULTS.mkdir(parents=True, exist_ok=True)
    doc = {"date_utc": datetime.now(timezone.utc).isoformat(timespec="seconds"), "smoke_tests": list(SMOKE_TESTS),
           "machine": {"cpu_count": os.cpu_count()}, "results": results}
    (RESULTS / "install_matrix.json").write_text(json.dumps(doc, indent=1))
    lines = ["# Install matrix: Python versions and both ends of the dependency ranges\n",
             "Each profile: a fresh venv, `pip install .[dev]` (with the profile's constraints), `import torm`, "
             f"then the smoke tests ({', '.join(f'`{t}`' for t in SMOKE_TESTS)}).\n",
             "| profile | Python | status | torch | mujoco | dm-control | mink | numpy | gymnasium | rerun-sdk | ray "
             "| install s | tests |", "|" + "---|" * 13]
    for r in results:
        v = r.get("versions") or {}
        lines.append(f"| {r['profile']} | {r.get('python_version') or r['python']} | {r['status']} | "
                     + " | ".join(str(v.get(p) or "–") for p in ("torch", "mujoco", "dm-control", "mink", "numpy",
                                                                  "gymnasium", "rerun-sdk", "ray"))
                     + f" | {r.get('install_s', '–')} | {r.get('tests_summary') or r.get('reason') or '–'} |")
    lines.append(f"\n{doc['date_utc']}; lower bounds read from pyproject.toml: "
                 f"`{json.dumps(lower_bounds(ROOT / 'pyproject.toml'))}`\n")
    (RESULTS / "install_matrix.md").write_text("\n".join(lines))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--profile", action="append", default=[], help="profile(s) to run (default: all)")
    ap.add_argument("--fresh", action="store_true", help="forget earlier results")
    ap.add_argument("--keep", action="store_true", help="keep the venvs")
    args = ap.parse_args(argv)
    profs = profiles()
    unknown = set(args.profile) - set(profs)
    if unknown:
        ap.error(f"unknown profile(s) {sorted(unknown)}; valid: {sorted(profs)}")
    path = RESULTS / "install_matrix.json"
    done = [] if args.fresh or not path.exists() else json.loads(path.read_text())["results"]
    for name in args.profile or list(profs):
        done = [r for r in done if r["profile"] != name]
        res = run_profile(name, profs[name], args.keep)
        done.append(res)
        write(done)
        sys.stderr.write(f"{name}: {res['status']} {res.get('tests_summary', '')}\n")
    return 0 if all(r["status"] in ("passed", "skipped") for r in done) else 1


if __name__ == "__main__":
    sys.exit(main())
