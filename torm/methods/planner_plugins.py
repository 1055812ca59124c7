"""Grasp-planner plug-ins: per-object clouds in, ranked grasps out, like the built-in planners (issue 40).

A planner is any object with ``name``, ``version`` and ``plan(point_clouds, meshes, context) ->
list[list[Grasp]]``: one list per input cloud (input order), best first, each :class:`torm.types.Grasp` in the
**world frame** (m; grasp frame x = approach into the object, y = closing axis, z = finger height: GraspNet's),
``width`` the opening (m). The harness checks the output (:func:`validate_grasps`) and executes the grasps with the
same IK and judge as the built-in planner.

Names a trial's ``planner`` may take: ``antipodal`` (the analytic planner, :func:`torm.grasp.planner.plan_grasps`,
the default), ``onnx_graspnet`` (:class:`torm.grasp.onnx_graspnet.OnnxGraspPlanner`: a GraspNet-format ONNX model;
option ``model_path``), an entry point of the group ``torm.planners``, or ``package.module:callable`` (a factory
called with ``planner_options``).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from torm.errors import PluginError
from torm.types import Grasp, ObjectPointCloud

ENTRY_POINT_GROUP = "torm.planners"
BUILTIN_PLANNERS: dict[str, str] = {
    "antipodal": "analytic antipodal sampling, collision-aware, all objects at once (the paper's planner)",
    "onnx_graspnet": "a GraspNet-format ONNX model (planner_options.model_path) + the analytic collision filter",
}


@dataclass(frozen=True, eq=False)
class PlannerContext:
    """What the harness tells a planner: ``table_height`` (m, world z), ``gripper``
    (:class:`torm.grasp.gripper.GripperGeometry`: stroke, finger and palm boxes, m), ``obstacles`` ((M, 3) m points
    of declared fixtures no gripper box may touch, or None), ``rng`` (the trial's generator), ``config`` (the trial's
    :class:`~torm.grasp.planner.GraspPlannerConfig`) and ``options`` (``planner_options``)."""

    table_height: float
    gripper: Any
    obstacles: np.ndarray | None
    rng: np.random.Generator
    config: Any
    options: dict[str, Any] = field(default_factory=dict)


class _Antipodal:
    name, version = "antipodal", ""

    def plan(self, point_clouds: Sequence[ObjectPointCloud], meshes: Any, context: PlannerContext
             ) -> list[list[Grasp]]:
        from torm.grasp.planner import plan_grasps

        return plan_grasps(point_clouds, meshes, context.table_height, context.gripper, context.config, context.rng,
                           context.obstacles)


class _OnnxGraspNet:
    name, version = "onnx_graspnet", ""

    def __init__(self, model_path: str = "", min_score: float = 0.0) -> None:
        if not model_path:
            raise PluginError("planner 'onnx_graspnet' needs planner_options.model_path: a GraspNet-format ONNX file "
                              "(see torm/grasp/onnx_graspnet.py for its signature)")
        self.model_path, self.min_score = model_path, float(min_score)

    def plan(self, point_clouds: Sequence[ObjectPointCloud], meshes: Any, context: PlannerContext
             ) -> list[list[Grasp]]:
        from torm.grasp.onnx_graspnet import OnnxGraspPlanner

        return OnnxGraspPlanner(self.model_path, context.gripper, context.config, self.min_score).plan(
            point_clouds, meshes, context.table_height)


def load_planner(name: str, options: dict[str, Any] | None = None) -> Any:
    """The planner object for ``name`` (see the module docstring), checked against the interface."""
    import torm

    options = dict(options or {})
    if name == "antipodal":
        if options:
            raise PluginError(f"planner 'antipodal' takes no planner_options ({sorted(options)}); its settings are "
                              "grasp.*")
        p: Any = _Antipodal()
        p.version = torm.__version__
        return p
    if name == "onnx_graspnet":
        p = _OnnxGraspNet(**options)
        p.version = torm.__version__
        return p
    from torm.methods.registry import resolve_factory

    factory, _ = resolve_factory(name, ENTRY_POINT_GROUP, "planner", tuple(BUILTIN_PLANNERS))
    try:
        planner = factory(**options) if callable(factory) else factory
    except TypeError as exc:
        raise PluginError(f"planner {name!r}: its factory does not accept the options {sorted(options)}: {exc}") \
            from exc
    if not all(hasattr(planner, a) for a in ("name", "version")) or not callable(getattr(planner, "plan", None)):
        raise PluginError(f"planner {name!r} needs name, version and plan(point_clouds, meshes, context)")
    return planner


def check_planner_name(name: str) -> None:
    """Raise unless ``name`` is a built-in planner, an installed ``torm.planners`` entry point or importable."""
    if name not in BUILTIN_PLANNERS:
        from torm.methods.registry import resolve_factory

        resolve_factory(name, ENTRY_POINT_GROUP, "planner", tuple(BUILTIN_PLANNERS))


def validate_grasps(planner: str, grasps: Any, point_clouds: Sequence[ObjectPointCloud], max_opening: float,
                    margin_m: float = 0.05) -> list[list[Grasp]]:
    """``grasps`` checked: one list per cloud of :class:`Grasp`; finite, opening within the stroke, the grasp centre
    within ``margin_m`` of its object's points (a grasp in another frame is caught). PluginError names the planner."""
    if not isinstance(grasps, Sequence) or len(grasps) != len(point_clouds):
        n = len(grasps) if isinstance(grasps, Sequence) else type(grasps).__name__
        raise PluginError(f"planner {planner!r}: returned {n} grasp lists for {len(point_clouds)} objects; return one "
                          "list per input cloud, in input order")
    for k, (gl, cloud) in enumerate(zip(grasps, point_clouds, strict=True)):
        lo = cloud.points_nx3.min(axis=0) - margin_m
        hi = cloud.points_nx3.max(axis=0) + margin_m
        for j, g in enumerate(gl):
            where = f"planner {planner!r}, object {k}, grasp {j}"
            if not isinstance(g, Grasp):
                raise PluginError(f"{where}: {type(g).__name__} is not a torm.types.Grasp")
            if not (np.isfinite(g.score) and np.all(np.isfinite(g.T_world_grasp))):
                raise PluginError(f"{where}: non-finite score or pose")
            if g.width > max_opening + 1e-6:
                raise PluginError(f"{where}: opening {g.width:.3f} m exceeds the gripper's stroke {max_opening:.3f} m "
                                  "(widths are metres)")
            c = g.T_world_grasp[:3, 3]
            if np.any(c < lo) or np.any(c > hi):
                raise PluginError(f"{where}: its centre {np.round(c, 3).tolist()} lies outside its object's box "
                                  f"{np.round(lo, 3).tolist()}..{np.round(hi, 3).tolist()} m: grasps must be in the "
                                  "world frame, at the object they are for")
    return [list(gl) for gl in grasps]


