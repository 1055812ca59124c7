"""A tiny hand-built world for renderer tests: a table box, a glass box (object 1), an opaque sphere (object 2)."""

from __future__ import annotations

from types import SimpleNamespace

import mujoco
import numpy as np

from sim.render.base import RenderCamera
from torm.geometry import look_at_cv


def tiny_world(glass_pos=(0.0, 0.0, 0.03), ball_pos=(0.07, 0.04, 0.025), seed: int = 3) -> SimpleNamespace:
    """A world-like object (``model``, ``data``, ``geom_to_instance``, ``objects``, ``seed``, ``scenario``)."""
    s = mujoco.MjSpec()
    wb = s.worldbody
    wb.add_geom(name="table", type=mujoco.mjtGeom.mjGEOM_BOX, size=[0.4, 0.4, 0.02], pos=[0, 0, -0.02], group=0)
    b1 = wb.add_body(name="obj1_box", pos=list(glass_pos))
    b1.add_geom(name="obj1_box_visual", type=mujoco.mjtGeom.mjGEOM_BOX, size=[0.03, 0.02, 0.03], group=2)
    b2 = wb.add_body(name="obj2_ball", pos=list(ball_pos))
    b2.add_geom(name="obj2_ball_visual", type=mujoco.mjtGeom.mjGEOM_SPHERE, size=[0.025, 0, 0], group=4,
                rgba=[0.9, 0.2, 0.2, 1])
    b3 = wb.add_body(name="robot_link", pos=[-0.05, -0.05, 0.05])
    b3.add_geom(name="robot_geom", type=mujoco.mjtGeom.mjGEOM_SPHERE, size=[0.02, 0, 0], group=1)
    model = s.compile()
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    g2i = np.zeros(model.ngeom, np.int32)
    g2i[model.geom("obj1_box_visual").id] = 1
    g2i[model.geom("obj2_ball_visual").id] = 2
    objects = [SimpleNamespace(instance_id=1, name="box", ior=1.5), SimpleNamespace(instance_id=2, name="ball")]
    return SimpleNamespace(model=model, data=data, geom_to_instance=g2i, objects=objects, seed=seed,
                           scenario="tiny", table_height=0.0, workspace_bounds=None)


def camera(eye=(0.25, -0.2, 0.25), target=(0.02, 0.0, 0.02), width=64, height=48, f=None, c=None) -> RenderCamera:
    """An OpenCV camera at ``eye`` looking at ``target`` (m) with focal ``f`` px and principal point ``c`` px."""
    f = f if f is not None else 0.9 * width
    c = c if c is not None else (width / 2, height / 2)
    K = np.array([[f, 0, c[0]], [0, f, c[1]], [0, 0, 1.0]])
    return RenderCamera(K, look_at_cv(np.asarray(eye, float), np.asarray(target, float)), width, height)


def one_glass_cylinder_view(height_m: float) -> tuple:
    """(world, T_world_cam (4, 4), K (3, 3)) of an 80x60 camera 0.45 m from a lone glass cylinder, ``height_m``
    above its centre: the tiny PBR scenes of the look-alike tests."""
    from sim.scenes.scenario import Scenario
    from sim.world import build_world

    world = build_world(Scenario(name="t", objects=("cylinder",), spacing="moderate"), 2, robot=None)
    c = world.object_pose(1)[:3, 3]
    T = look_at_cv(c + np.array([0.45, 0.0, height_m]), c + np.array([0.0, 0.0, 0.04]))
    return world, T, np.array([[60.0, 0, 40], [0, 60.0, 30], [0, 0, 1]])

