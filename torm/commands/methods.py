"""``torm methods``: the perception methods and grasp planners a trial or a benchmark can run, built-in and plug-in.

Examples::

    torm methods list
    torm methods list --json

A plug-in registers a factory in the entry-point group ``torm.methods`` of its package (see
``docs/add_your_method.md``); ``torm trial --set method=NAME`` and ``torm bench --method NAME`` then
run it like a built-in. Any importable ``package.module:callable`` works as well without installation. Grasp
planners register in ``torm.planners`` and are chosen with ``--set planner=NAME``.
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


def _planners() -> list:
    from importlib import metadata

    import torm
    from torm.methods import MethodInfo
    from torm.methods.planner_plugins import BUILTIN_PLANNERS, ENTRY_POINT_GROUP, load_planner

    rows = [MethodInfo(n, torm.__version__, "builtin planner", d) for n, d in BUILTIN_PLANNERS.items()]
    for ep in sorted(metadata.entry_points(group=ENTRY_POINT_GROUP), key=lambda e: e.name):
        try:
            pl = load_planner(ep.name)
            rows.append(MethodInfo(ep.name, str(pl.version), "planner entry point", (type(pl).__doc__ or "")
                                   .strip().split("\n")[0]))
        except Exception as exc:  # listed, not fatal
            rows.append(MethodInfo(ep.name, "?", "planner entry point", f"fails to load: {exc}"))
    return rows


def run_list(args: argparse.Namespace) -> int:
    from torm.methods import list_methods

    rows = list_methods() + _planners()
    if args.json:
        print_json([{"name": r.name, "version": r.version, "source": r.source, "description": r.description}
                    for r in rows])
        return 0
    w = max(len(r.name) for r in rows)
    v = max(len(r.version) for r in rows)
    for r in rows:
        print(f"{r.name:<{w}}  {r.version:<{v}}  {r.source:<28}  {r.description}")
    return 0
