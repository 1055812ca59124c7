"""Start-up time of the command line: ``torm --help`` and every subcommand's ``--help``, median of ``--repeats``
runs each, in fresh processes; and which heavy packages building the parser imports (none of torch, mujoco, sim's
scene library should be).

Writes ``benchmarks/results/cli_startup.{json,md}``. Run: ``python benchmarks/cli_startup.py`` (seconds).
"""

from __future__ import annotations

import argparse
import statistics
import subprocess
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks._common import RESULTS, context, context_md, md_table, setup, write_json  # noqa: E402

COMMANDS = ("", "trial", "bench", "capture", "segment", "reconstruct", "report", "scenes", "train-segmenter",
            "methods", "export-models", "calibrate", "import", "config")
HEAVY = ("torch", "mujoco", "trimesh", "mitsuba", "onnxruntime", "sim.scenes")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=5)
    args = ap.parse_args(argv)
    setup()
    exe = str(Path(sys.executable).with_name("torm"))
    rows, out = [], {"context": context(vars(args)), "results": []}
    for c in COMMANDS:
        cmd = [exe, *([c] if c else []), "--help"]
        times = []
        for _ in range(args.repeats):
            t = time.perf_counter()
            subprocess.run(cmd, capture_output=True, check=True)
            times.append(time.perf_counter() - t)
        med = statistics.median(times)
        out["results"].append({"command": " ".join(cmd[1:]), "median_s": med, "runs_s": times})
        rows.append([f"`torm {' '.join(cmd[1:])}`", med, min(times), max(times)])
    probe = ("import sys; from torm.cli import build_parser; build_parser(); "
             f"print(','.join(m for m in {HEAVY!r} if m in sys.modules))")
    heavy = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, check=True).stdout.strip()
    out["heavy_imports_of_the_parser"] = [m for m in heavy.split(",") if m]
    write_json(RESULTS / "cli_startup.json", out)
    L = ["# Command-line start-up time", "", context_md(out["context"]), "",
         f"Median of {args.repeats} fresh processes per command (wall seconds, interpreter start included).", "",
         md_table(["command", "median s", "min s", "max s"], rows), "",
         "Heavy packages imported by building the parser: "
         + (", ".join(out["heavy_imports_of_the_parser"]) or "none") + f" (checked: {', '.join(HEAVY)}).", ""]
    (RESULTS / "cli_startup.md").write_text("\n".join(L) + "\n")
    print("\n".join(str(r) for r in rows))
    return 0


if __name__ == "__main__":
    sys.exit(main())
