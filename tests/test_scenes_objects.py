"""Object library: geometry, mass, the hollow open cup, and the on-disk CoACD hull cache."""

from __future__ import annotations

import mujoco
import numpy as np
import pytest
import trimesh

from sim.scenes import hulls, meshes, objects
from sim.scenes.objects import CERAMIC_DENSITY, GLASS_DENSITY, get_object, list_objects
from sim.scenes.scenario import Scenario
from sim.world import build_world
from torm.errors import UnknownNameError

PAPER_OBJECTS = {"cylinder", "cup", "opaque_cup", "ball", "cube", "hexagonal_prism", "pyramidal_frustum", "heart",
                 "ice_cube", "toothpick_box"}


def test_library_has_the_paper_objects_and_the_lab_glassware():
    assert set(list_objects()) == PAPER_OBJECTS | set(objects.GLASSWARE)


@pytest.mark.parametrize("name", sorted(PAPER_OBJECTS))
def test_object_mesh_frame_size_and_mass(name):
    a = get_object(name)
    m = a.mesh
    assert m.is_watertight and m.is_volume
    lo, hi = m.bounds
    assert lo[2] == pytest.approx(0.0, abs=1e-9)  # sits on z = 0
    assert (lo[:2] + hi[:2]) / 2 == pytest.approx([0.0, 0.0], abs=1e-9)  # footprint centred
    # graspable by an 85 mm gripper: the footprint's narrowest width (over yaw) is below 75 mm
    fp = a.footprint_kx2
    widths = [np.ptp(fp @ np.array([np.cos(t), np.sin(t)])) for t in np.linspace(0, np.pi, 90)]
    assert 0.02 < min(widths) < 0.075
    assert 0.02 < a.height <= 0.10
    density = CERAMIC_DENSITY if name == "opaque_cup" else GLASS_DENSITY
    assert a.mass == pytest.approx(m.volume * density, rel=0.01)
    # independent check of the volume: the analytic volume of simple solids
    analytic = {"cylinder": np.pi * 0.03**2 * 0.1, "cube": 0.05**3, "ball": 4 / 3 * np.pi * 0.03**3,
                "pyramidal_frustum": 0.06 / 3 * (0.06**2 + 0.03**2 + 0.06 * 0.03),
                "toothpick_box": 0.06 * 0.04 * 0.08 - 0.054 * 0.034 * 0.074}
    if name in analytic:
        assert m.volume == pytest.approx(analytic[name], rel=0.01)
    assert a.transparent == (name != "opaque_cup")


def test_simulated_masses_match_volume_times_density():
    sc = Scenario(name="all", objects=tuple(sorted(PAPER_OBJECTS - {"opaque_cup"})), spacing="moderate")
    w = build_world(sc, seed=0, robot=None)
    for o in w.objects:
        a = get_object(o.name)
        assert w.model.body_mass[o.body_id] == pytest.approx(a.volume * a.density, rel=0.01)


def test_cup_is_open_top_and_hollow():
    cup = get_object("cup")
    assert cup.mesh.volume < 0.3 * cup.mesh.convex_hull.volume
    # open top: every face in the rim plane z = 90 mm lies on the 3 mm annulus, none covers the opening
    v, f = cup.mesh.vertices, cup.mesh.faces
    top = np.all(np.abs(v[f][:, :, 2] - 0.09) < 1e-6, axis=1)
    assert top.any()
    assert np.linalg.norm(v[f[top]][:, :, :2], axis=-1).min() > 0.032 - 1e-6
    # the cavity floor (inner base) sits at 6 mm and spans the axis
    floor = np.all(np.abs(v[f][:, :, 2] - 0.006) < 1e-6, axis=1)
    assert np.linalg.norm(v[f[floor]][:, :, :2], axis=-1).min() < 1e-6
    assert len(cup.collision_hulls()) > 4  # concave: CoACD pieces, not one convex hull


def _drop_ball(into_cup: bool) -> np.ndarray:
    sc = Scenario(name="cup_drop", objects=("cup",), poses=((0.55, 0.0, 0.0),))
    w = build_world(sc, seed=0, robot=None)
    spec = w.spec
    r = 0.015
    body = spec.worldbody.add_body(name="probe", pos=[0.55 if into_cup else 0.65, 0.0, 0.15])
    body.add_freejoint()
    body.add_geom(type=mujoco.mjtGeom.mjGEOM_SPHERE, size=[r, 0, 0], density=2500, group=3)
    model = spec.compile()
    data = mujoco.MjData(model)
    mujoco.mj_step(model, data, nstep=750)
    return data.body("probe").xpos.copy()


def test_ball_dropped_into_cup_stays_inside():
    p = _drop_ball(into_cup=True)
    assert np.linalg.norm(p[:2] - [0.55, 0.0]) < 0.032 - 0.015 + 1e-3  # within the inner radius
    assert 0.006 + 0.015 - 2e-3 < p[2] < 0.03  # rests on the inner base, far below the 90 mm rim
    q = _drop_ball(into_cup=False)  # control: next to the cup it lands on the table
    assert q[2] == pytest.approx(0.015, abs=2e-3)


def test_unknown_object_lists_valid_names():
    with pytest.raises(UnknownNameError) as exc:
        get_object("cilinder")
    assert "cylinder" in str(exc.value) and "toothpick_box" in str(exc.value)


def test_shipped_hull_cache_avoids_coacd(monkeypatch):
    def boom(*args, **kwargs):
        raise AssertionError("CoACD must not run for shipped meshes")

    monkeypatch.setattr(hulls, "_run_coacd", boom)
    objects._collision_hulls.cache_clear()
    try:
        for name in ("cup", "opaque_cup", "heart", *(n for n in objects.GLASSWARE
                                                      if get_object(n).collision == "coacd")):
            pieces = get_object(name).collision_hulls()
            assert pieces and all(p.is_convex for p in pieces)
    finally:
        objects._collision_hulls.cache_clear()


def test_user_hull_cache_hits_on_second_call(monkeypatch, tmp_path):
    monkeypatch.setenv("TORM_CACHE_DIR", str(tmp_path))
    calls = []
    real = hulls._run_coacd

    def spy(mesh, params):
        calls.append(1)
        return real(mesh, params)

    monkeypatch.setattr(hulls, "_run_coacd", spy)
    mesh = meshes.frustum(0.041, 0.017, 0.033)  # a new shape: not in the shipped cache; CoACD is fast on it
    params = hulls.CoacdParams(resolution=500)
    first = hulls.convex_decomposition("test_frustum", mesh, params)
    assert len(calls) == 1
    assert list((tmp_path / "hulls").glob("test_frustum_*.npz"))
    second = hulls.convex_decomposition("test_frustum", mesh, params)
    assert len(calls) == 1  # cache hit: CoACD not called again
    assert len(first) == len(second)
    for a, b in zip(first, second, strict=True):
        assert np.allclose(a.vertices, b.vertices)
    # the key covers the mesh and the parameters
    assert hulls.cache_key(mesh, params) != hulls.cache_key(mesh, hulls.CoacdParams(resolution=600))
    moved = trimesh.Trimesh(mesh.vertices + [0.001, 0, 0], mesh.faces)
    assert hulls.cache_key(mesh, params) != hulls.cache_key(moved, params)
