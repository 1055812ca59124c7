"""World builder: every scenario builds and rests; conventions (groups, names, ids, options); reset; robot."""

from __future__ import annotations

import mujoco
import numpy as np
import pytest

from sim.scenes.scenario import list_scenarios
from sim.world import WORKSPACE_BOUNDS, World, WorldConfig, build_world, check_world
from torm.errors import SceneError

ALL = list_scenarios("syn") + list_scenarios("rw")


@pytest.mark.parametrize("name", ALL)
def test_every_scenario_builds_and_rests(name):
    w = build_world(name, seed=0, robot=None)
    assert [o.name for o in w.objects] == list(w.scenario_spec.objects)
    for o in w.objects:  # standing on the table top (z = 0), upright, inside the workspace
        T = o.T_world_obj
        assert abs(T[2, 3]) < 1e-3 and T[2, 2] > np.cos(np.radians(3))
        assert WORKSPACE_BOUNDS[0, 0] < T[0, 3] < WORKSPACE_BOUNDS[1, 0]
        assert WORKSPACE_BOUNDS[0, 1] < T[1, 3] < WORKSPACE_BOUNDS[1, 1]
    stats = check_world(w, seconds=1.0, max_move=0.005)  # raises on MuJoCo warnings or > 5 mm motion
    assert stats["max_move_m"] < 0.005
    assert all(wn.number == 0 for wn in w.data.warning)


def test_world_conventions():
    w = build_world("syn6", seed=3, robot=None)
    m = w.model
    assert isinstance(w, World) and w.scenario == "syn6" and w.seed == 3
    assert m.opt.timestep == 0.002 and m.opt.cone == mujoco.mjtCone.mjCONE_ELLIPTIC and m.opt.impratio == 10
    assert not m.opt.disableflags & int(mujoco.mjtDisableBit.mjDSBL_MULTICCD)
    assert w.table_height == 0.0
    assert np.allclose(w.workspace_bounds, [[0.33, -0.22, -0.005], [0.77, 0.22, 0.20]])
    assert w.geom_to_instance.shape == (m.ngeom,) and w.geom_to_instance.dtype == np.int32
    for k, o in enumerate(w.objects, start=1):
        assert o.instance_id == k and o.body_name == f"obj{k}_{o.name}"
        assert m.body(o.body_id).name == o.body_name
        owned = set(np.nonzero(w.geom_to_instance == k)[0])
        assert owned == set(o.visual_geom_ids) | set(o.collision_geom_ids)
        for g in o.visual_geom_ids:
            assert m.geom_group[g] == (2 if o.transparent else 4)
            assert m.geom_contype[g] == 0 and m.geom_conaffinity[g] == 0
        for g in o.collision_geom_ids:
            assert m.geom_group[g] == 3 and m.geom_contype[g] != 0
    table = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_GEOM, "table")
    assert w.geom_to_instance[table] == 0 and m.geom_group[table] == 0
    assert w.data.geom_xpos[table][2] + m.geom_size[table][2] == pytest.approx(0.0, abs=1e-9)


def test_object_meshes_world_match_rendered_geometry():
    w = build_world("syn8", seed=1, robot=None)
    m, d = w.model, w.data
    for o, mesh in zip(w.objects, w.object_meshes_world(), strict=True):
        g = o.visual_geom_ids[0]
        mid = m.geom_dataid[g]
        v = m.mesh_vert[m.mesh_vertadr[mid]:m.mesh_vertadr[mid] + m.mesh_vertnum[mid]]
        v_world = v @ d.geom_xmat[g].reshape(3, 3).T + d.geom_xpos[g]
        assert np.allclose(np.sort(v_world, axis=0), np.sort(mesh.vertices, axis=0), atol=1e-6)
        assert mesh.bounds[0, 2] == pytest.approx(0.0, abs=1e-3)  # lowest point on the table top


def test_same_seed_same_world_and_reset():
    a = build_world("rw6", seed=5, robot=None)
    b = build_world("rw6", seed=5, robot=None)
    c = build_world("rw6", seed=6, robot=None)
    assert np.array_equal(a.data.qpos, b.data.qpos)
    assert not np.allclose(a.data.qpos, c.data.qpos)
    settled = a.data.qpos.copy()
    a.data.qvel[:] = 0.3  # knock everything around
    mujoco.mj_step(a.model, a.data, nstep=200)
    assert not np.allclose(a.data.qpos, settled)
    a.reset()
    assert np.array_equal(a.data.qpos, settled) and not a.data.qvel.any()


def test_check_world_detects_motion_and_leaves_data_untouched():
    w = build_world("rw3", seed=0, robot=None)
    adr = w.model.jnt_dofadr[w.model.body_jntadr[w.objects[0].body_id]]
    w.data.qvel[adr] = 0.5  # object 1 slides at 0.5 m/s
    before = w.data.qpos.copy()
    with pytest.raises(SceneError, match="moved"):
        check_world(w, seconds=0.2)
    assert np.array_equal(w.data.qpos, before)


def test_rejected_layouts_raise_scene_error():
    # zero penetration tolerance: every resting contact (dist slightly < 0) fails the settle check
    cfg = WorldConfig(settle_time=0.1, max_penetration=0.0, max_resamples=2)
    with pytest.raises(SceneError, match=r"'rw1' seed 4: no layout settled cleanly in 2 attempt"):
        build_world("rw1", seed=4, robot=None, config=cfg)
    with pytest.raises(SceneError, match="penetrates"):
        build_world("rw1", seed=4, robot=None, config=cfg)


def test_world_with_robot():
    from sim.robots.config import load_robot_config

    w = build_world("rw7", seed=2)
    rcfg = load_robot_config("inovo_2f85", validate=False)
    rcfg.validate_against(w.model)  # every joint/actuator/site the harness needs, under its own name
    for j, q in zip(rcfg.arm.joints, rcfg.arm.home, strict=True):
        assert w.data.joint(j).qpos[0] == pytest.approx(q, abs=1e-3)
    robot_geoms = [g for g in range(w.model.ngeom) if w.model.geom_group[g] == 1]
    assert robot_geoms and not w.geom_to_instance[robot_geoms].any()
    check_world(w, seconds=1.0)
