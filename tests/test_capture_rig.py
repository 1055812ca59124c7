"""Simulated camera rig: intrinsics, poses, masks and depth checked against known geometry."""

from __future__ import annotations

import math

import mujoco
import numpy as np
import pytest

from sim.cameras.rig import CameraRigConfig, SimCameraRig, hemisphere_poses, workspace_coverage
from torm.capture.provider import ImageProvider
from torm.errors import ConfigError
from torm.geometry import look_at_cv

BOX_POS = np.array([0.62, 0.07, 0.02])  # centre of a 4 cm opaque cube standing on the table (m)
SPHERE_POS = np.array([0.45, -0.08, 0.05])  # centre of a 5 cm radius opaque sphere (m)
GLASS_POS = np.array([0.55, 0.0, 0.05])  # centre of a 10 x 10 x 10 cm glass box (m)


def _scene(glass: bool = False) -> tuple[mujoco.MjModel, mujoco.MjData, np.ndarray]:
    """Table (group 0), cube k=1 and sphere k=2 (group 4), optional glass box k=3 (group 2), a robot-ish
    sphere hovering over the workspace (group 1) and collision geoms (group 3), which must stay invisible."""
    s = mujoco.MjSpec()
    wb = s.worldbody
    wb.add_geom(type=mujoco.mjtGeom.mjGEOM_BOX, size=[0.6, 0.5, 0.02], pos=[0.55, 0, -0.02], group=0,
                rgba=[0.6, 0.5, 0.4, 1])
    wb.add_light(pos=[0.5, 0, 1.5], dir=[0, 0, -1])
    inst = []
    b = wb.add_body(name="cube", pos=BOX_POS)
    b.add_geom(type=mujoco.mjtGeom.mjGEOM_BOX, size=[0.02] * 3, group=4, rgba=[1, 0, 0, 1])
    b.add_geom(type=mujoco.mjtGeom.mjGEOM_BOX, size=[0.05] * 3, group=3, contype=0, conaffinity=0)
    inst += [1, 1]
    b = wb.add_body(name="sphere", pos=SPHERE_POS)
    b.add_geom(type=mujoco.mjtGeom.mjGEOM_SPHERE, size=[0.05, 0, 0], group=4, rgba=[0, 0, 1, 1])
    inst += [2]
    if glass:
        b = wb.add_body(name="glass", pos=GLASS_POS)
        b.add_geom(type=mujoco.mjtGeom.mjGEOM_BOX, size=[0.05] * 3, group=2, rgba=[0.8, 0.9, 1, 0.3])
        inst += [3]
    r = wb.add_body(name="robot", pos=[0.55, 0.0, 0.25])
    r.add_geom(type=mujoco.mjtGeom.mjGEOM_SPHERE, size=[0.08, 0, 0], group=1, rgba=[0, 1, 0, 1])
    m = s.compile()
    d = mujoco.MjData(m)
    mujoco.mj_forward(m, d)
    g2i = np.zeros(m.ngeom, np.int32)
    g2i[1:1 + len(inst)] = inst
    return m, d, g2i


@pytest.fixture(scope="module")
def rig():
    m, d, g2i = _scene(glass=False)
    r = SimCameraRig(m, d, g2i, CameraRigConfig(n_views=8, width=160, height=90), object_names=["cube", "sphere"])
    yield r
    r.close()


def test_default_intrinsics_match_d455_virtual_camera():
    cfg = CameraRigConfig()
    K = cfg.K()
    W, H = cfg.image_width, cfg.image_height
    assert (W, H) == (1280, 720)
    assert math.degrees(2 * math.atan(W / (2 * K[0, 0]))) == pytest.approx(91.5, abs=1e-9)
    assert math.degrees(2 * math.atan(H / (2 * K[1, 1]))) == pytest.approx(60.0, abs=0.05)
    assert K[0, 0] == K[1, 1] and K[0, 2] == W / 2 and K[1, 2] == H / 2
    half = CameraRigConfig(scale=0.5)
    assert (half.image_width, half.image_height) == (640, 360)
    assert half.K()[0, 0] == pytest.approx(K[0, 0] / 2)


def test_layout_is_deterministic_on_the_sphere_and_looks_at_the_centre():
    cfg = CameraRigConfig()
    Ts = cfg.poses()
    assert Ts.shape == (50, 4, 4)
    np.testing.assert_array_equal(Ts, cfg.poses())
    centre = np.array(cfg.centre)
    r = np.linalg.norm(Ts[:, :3, 3] - centre, axis=1)
    np.testing.assert_allclose(r, 0.5, atol=1e-12)
    el = np.degrees(np.arcsin((Ts[:, 2, 3] - centre[2]) / 0.5))
    assert el.min() >= 20.0 and el.max() <= 80.0
    # optical axis (OpenCV +z) points at the centre; image "down" has a negative world z component
    to_c = (centre - Ts[:, :3, 3]) / r[:, None]
    np.testing.assert_allclose(np.einsum("vi,vi->v", Ts[:, :3, 2], to_c), 1.0, atol=1e-12)
    assert np.all(Ts[:, 2, 1] < 0)
    # azimuths cover the circle: the view directions' xy parts point every way
    az = np.arctan2(Ts[:, 1, 3], Ts[:, 0, 3] - centre[0])
    assert np.histogram(az, bins=8, range=(-np.pi, np.pi))[0].min() >= 4
    # objects near the centre are in every view
    near_box = np.array([[0.45, -0.1, 0.0], [0.65, 0.1, 0.12]])
    assert workspace_coverage(cfg, near_box).all()


def test_config_validation():
    with pytest.raises(ConfigError, match="n_views"):
        CameraRigConfig(n_views=0)
    with pytest.raises(ConfigError, match="elevation"):
        CameraRigConfig(elevation_min_deg=50, elevation_max_deg=30)
    with pytest.raises(ConfigError, match="channels"):
        CameraRigConfig(channels=("depth",))


def test_known_points_project_inside_their_masks(rig):
    Ts = rig.poses()
    assert isinstance(rig, ImageProvider)
    cap = rig.capture(channels=("rgb", "mask", "depth"))
    assert cap.object_ids == (1, 2) and cap.object_names == ("cube", "sphere")
    inner_box = BOX_POS + 0.7 * 0.02 * np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)])
    hits = 0
    for v, T in zip(cap.views, Ts, strict=True):
        np.testing.assert_array_equal(v.T_world_cam, T)
        assert v.rgb.shape == (90, 160, 3) and v.rgb.dtype == np.uint8
        for k, pts in ((1, np.vstack([BOX_POS, inner_box])), (2, SPHERE_POS[None])):
            uv, z = v.project(pts)
            ij = np.floor(uv).astype(int)
            inside = (ij[:, 0] >= 0) & (ij[:, 0] < 160) & (ij[:, 1] >= 0) & (ij[:, 1] < 90) & (z > 0)
            assert inside.all()
            # a point on the far side of the cube may be hidden by the sphere; the centre is never hidden here
            labels = v.mask[ij[:, 1], ij[:, 0]]
            assert labels[0] == k
            hits += int(np.sum(labels == k))
        # the robot (group 1) and collision geoms (group 3) are invisible: the 10 cm collision box would
        # make the cube's mask much larger than the cube itself
        assert (v.mask == 1).sum() < 0.25 * 160 * 90
    assert hits >= 0.9 * len(cap) * 10


def test_depth_backprojects_onto_the_sphere_for_general_intrinsics(rig):
    # non-square pixels and an off-centre principal point (e.g. a real D455 calibration)
    K = np.array([[70.0, 0.0, 75.0], [0.0, 82.0, 48.0], [0.0, 0.0, 1.0]])
    T = look_at_cv(SPHERE_POS + np.array([0.3, -0.2, 0.25]), SPHERE_POS)
    v = rig.render_view(T, K, channels=("mask", "depth"))
    vv, uu = np.nonzero(v.mask == 2)
    assert len(uu) > 50
    z = v.depth[vv, uu].astype(np.float64)
    p_cam = np.stack([(uu + 0.5 - K[0, 2]) / K[0, 0] * z, (vv + 0.5 - K[1, 2]) / K[1, 1] * z, z], axis=1)
    p = p_cam @ T[:3, :3].T + T[:3, 3]
    r = np.linalg.norm(p - SPHERE_POS, axis=1)
    # MuJoCo's sphere is a tessellated polyhedron: radial error below 1.5% of the radius
    assert np.abs(r - 0.05).max() < 0.0008
    # the silhouette matches the projected sphere's extent in both image axes
    uv, zc = v.project(SPHERE_POS[None])
    ru, rv = K[0, 0] * 0.05 / zc[0], K[1, 1] * 0.05 / zc[0]
    assert (uu.max() - uu.min() + 1) == pytest.approx(2 * ru, rel=0.15)
    assert (vv.max() - vv.min() + 1) == pytest.approx(2 * rv, rel=0.15)


def test_sensor_depth_sees_through_glass_and_ideal_depth_hits_it():
    m, d, g2i = _scene(glass=True)
    with SimCameraRig(m, d, g2i, CameraRigConfig(n_views=1, width=64, height=36)) as rig:
        T = look_at_cv(GLASS_POS + np.array([0.0, 0.0, 0.45]), GLASS_POS - np.array([0, 0, 0.05]))
        v = rig.render_view(T)
        c = (18, 32)  # centre pixel: straight down through the glass box onto the table at z = 0
        cam_z = T[2, 3]
        assert v.mask[c] == 3
        assert v.depth[c] == pytest.approx(cam_z - 0.10, abs=2e-4)  # glass top face at z = 0.10 m
        assert v.sensor_depth[c] == pytest.approx(cam_z - 0.0, abs=2e-4)  # the table behind it
        # away from the glass both depths agree
        off = v.mask == 0
        np.testing.assert_allclose(v.depth[off], v.sensor_depth[off], atol=1e-6)


def test_hemisphere_poses_small_counts():
    Ts = hemisphere_poses(1, 0.5, (0.55, 0, 0), 30, 30)
    assert Ts.shape == (1, 4, 4)
    assert Ts[0, 2, 3] == pytest.approx(0.5 * math.sin(math.radians(30)))


def test_masks_with_more_than_255_rendered_geoms():
    # segmentation ids then spill into the green channel; the decoder must still map them
    s = mujoco.MjSpec()
    wb = s.worldbody
    for i in range(300):  # a grid of flat tiles on the table (group 0), all rendered
        x, y = 0.3 + 0.02 * (i % 25), -0.12 + 0.02 * (i // 25)
        wb.add_geom(type=mujoco.mjtGeom.mjGEOM_BOX, size=[0.009, 0.009, 0.001], pos=[x, y, 0.001], group=0)
    b = wb.add_body(pos=BOX_POS)
    b.add_geom(type=mujoco.mjtGeom.mjGEOM_BOX, size=[0.02] * 3, group=4)
    m = s.compile()
    d = mujoco.MjData(m)
    g2i = np.zeros(m.ngeom, np.int32)
    g2i[300] = 7
    with SimCameraRig(m, d, g2i, CameraRigConfig(n_views=1, width=80, height=45)) as rig:
        T = look_at_cv(BOX_POS + np.array([0.25, 0.1, 0.3]), BOX_POS)
        ids = rig.render_geom_ids(T)
        assert ids.max() == 300 and (ids > 255).sum() > 0
        v = rig.render_view(T, channels=("mask",))
        uv, _ = v.project(BOX_POS[None])
        assert v.mask[int(uv[0, 1]), int(uv[0, 0])] == 7
        assert set(np.unique(v.mask)) == {0, 7}
