"""Bring your own perception method: the interface, the registry and the output checks (issue 40).

See ``docs/methods.md`` ("Add your method") and the example plug-in ``examples/torm_plane_fill``.
"""

from __future__ import annotations

from torm.methods.interface import MethodContext, Needs, ObjectEstimate, PerceptionMethod
from torm.methods.registry import (
    BUILTINS,
    ENTRY_POINT_GROUP,
    MethodInfo,
    check_method_name,
    is_builtin,
    list_methods,
    load_method,
    method_info,
    method_names,
)
from torm.methods.validate import validate_estimates

__all__ = ["BUILTINS", "ENTRY_POINT_GROUP", "MethodContext", "MethodInfo", "Needs", "ObjectEstimate",
           "PerceptionMethod", "check_method_name", "is_builtin", "list_methods", "load_method", "method_info",
           "method_names", "validate_estimates"]
