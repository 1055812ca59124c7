"""``torm methods``: the perception methods a trial or a benchmark can run, built-in and plug-in.

Examples::

    torm methods list
    torm methods list --json

A plug-in registers a factory in the entry-point group ``torm.methods`` of its package (see
``docs/methods.md``, "Add your method"); ``torm trial --set method=NAME`` and ``torm bench --method NAME`` then
run it like a built-in. Any importable ``package.module:callable`` works as well without installation.
"""

from __future__ import annotations

import argparse

from torm.commands._common import add_overrides, add_parser, print_json


def register(subparsers: argparse._SubParsersAction) -> None:
    p = add_parser(subparsers, "methods", __doc__, help="list the perception methods (built-in and plug-ins)")
    sub = p.add_subparsers(dest="action", required=True, metavar="ACTION")
    lst = add_parser(sub, "list", __doc__, help="every method with its version and where it comes from")
    lst.add_argument("--json", action="store_true", help="print JSON instead of a table")
    add_overrides(lst, example="json=true", target="methods list (its options)")
    lst.set_defaults(func=run_list)


def run_list(args: argparse.Namespace) -> int:
    from torm.methods import list_methods

    rows = list_methods()
    if args.json:
        print_json([{"name": r.name, "version": r.version, "source": r.source, "description": r.description}
                    for r in rows])
        return 0
    w = max(len(r.name) for r in rows)
    v = max(len(r.version) for r in rows)
    for r in rows:
        print(f"{r.name:<{w}}  {r.version:<{v}}  {r.source:<28}  {r.description}")
    return 0
