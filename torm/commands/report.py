"""``torm report RUN [RUN2] [--out DIR]``: tables and plots of a benchmark run folder (or two, compared).

Writes ``report.md``, ``report.html`` and PNG plots (success by scenario and method, silhouette IoU
distribution, time per stage) into ``--out`` (default: the first run folder) and prints a JSON summary.
Corrupted lines of ``results.jsonl`` are reported with their line numbers; the valid lines are used.
"""

from __future__ import annotations

import argparse

from torm.commands._common import print_json


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser("report", help="Markdown/HTML report with tables and plots of benchmark run folder(s)",
                              description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("runs", nargs="+", metavar="RUN", help="run folder (written by torm bench); a second one compares")
    p.add_argument("--out", default=None, help="output folder (default: the first run folder)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from torm.bench.report import write_report

    print_json(write_report(args.runs, args.out))
    return 0
