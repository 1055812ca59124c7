"""``torm report``: tables and plots of a benchmark run folder (or two, compared).

Examples::

    torm report runs/rw-night
    torm report runs/rw-night runs/rw-night-lowfriction --out runs/compare

Writes ``report.md``, ``report.html`` and PNG plots (success by scenario and method, silhouette IoU
distribution, time per stage) into ``--out`` (default: the first run folder) and prints a JSON summary.
Corrupted lines of ``results.jsonl`` are reported with their line numbers; the valid lines are used.
"""

from __future__ import annotations

import argparse

from torm.commands._common import add_parser, check_output_dir, print_json


def register(subparsers: argparse._SubParsersAction) -> None:
    p = add_parser(subparsers, "report", __doc__,
                   help="Markdown/HTML report with tables and plots of benchmark run folder(s)")
    p.add_argument("runs", nargs="+", metavar="RUN", help="run folder (written by torm bench); a second one compares")
    p.add_argument("--out", default=None, help="output folder (default: the first run folder)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from torm.bench.report import write_report

    if args.out is not None:
        check_output_dir(args.out)  # a file on the way is a named error before any run is read
    print_json(write_report(args.runs, args.out))
    return 0
