"""Table-plane estimation from capture depth: analytic plane + box scenes, and one simulated rw3 capture."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from torm.capture.table_plane import TablePlane, estimate_table_plane
from torm.errors import CaptureError, UnknownNameError
from torm.geometry import look_at_cv
from torm.types import CameraView, Capture

TABLE_Z = 0.0123  # table top height (m)
HW = (60, 80)  # (H, W) pixels
K = np.array([[60.0, 0, 40.0], [0, 60.0, 30.0], [0, 0, 1]])
EYES = ([0.45, 0.0, 0.45], [0.0, 0.45, 0.40], [-0.35, -0.3, 0.50])  # camera centres (m), looking at the origin


def _rays(T_world_cam: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Camera centre (3,) and (H, W, 3) world ray directions whose camera-z component is 1 (so t = z-depth)."""
    v, u = np.mgrid[0:HW[0], 0:HW[1]]
    d_cam = np.stack([(u + 0.5 - K[0, 2]) / K[0, 0], (v + 0.5 - K[1, 2]) / K[1, 1], np.ones(HW)], axis=-1)
    return T_world_cam[:3, 3], d_cam @ T_world_cam[:3, :3].T


def _hit_plane(o: np.ndarray, d: np.ndarray, normal: np.ndarray, point: np.ndarray) -> np.ndarray:
    """(H, W) ray parameter of the plane hit (inf where missed or behind)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        t = ((point - o) @ normal) / (d @ normal)
    return np.where(np.isfinite(t) & (t > 0), t, np.inf)


def _hit_box(o: np.ndarray, d: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """(H, W) ray parameter of the entry into the axis-aligned box [lo, hi] (slab method; inf where missed)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        t0, t1 = (lo - o) / d, (hi - o) / d
    t_near = np.minimum(t0, t1).max(axis=-1)
    t_far = np.maximum(t0, t1).min(axis=-1)
    return np.where((t_near <= t_far) & (t_near > 0), t_near, np.inf)


def _depth(o: np.ndarray, d: np.ndarray, normal: np.ndarray, table_z: float, t_box: np.ndarray,
           noise: np.ndarray) -> np.ndarray:
    """(H, W) float32 z-depth (m) of the nearer of the table plane through (0, 0, table_z) and the box, plus noise."""
    t = np.minimum(_hit_plane(o, d, normal, np.array([0.0, 0.0, table_z])), t_box)
    return np.where(np.isfinite(t), t + noise, 0.0).astype(np.float32)


def _capture(
    box: tuple[list[float], list[float]] | None = ((-0.04, -0.03, 0.0), (0.04, 0.05, 0.08)),
    tilt_deg: float = 0.0, noise_m: float = 0.001, masks: bool = True, depth: bool = True,
    sensor_table_z: float | None = None, seed: int = 0,
) -> Capture:
    """Views of a plane through (0, 0, TABLE_Z) tilted ``tilt_deg`` about x, with an optional box on it.

    ``depth`` is the ideal z-depth (m) plus Gaussian noise ``noise_m``; ``sensor_table_z`` adds a
    ``sensor_depth`` channel that sees the table at that height (m) instead.
    """
    rng = np.random.default_rng(seed)
    a = math.radians(tilt_deg)
    normal = np.array([0.0, -math.sin(a), math.cos(a)])
    views = []
    for i, eye in enumerate(EYES):
        T = look_at_cv(np.array(eye), np.zeros(3))
        o, d = _rays(T)
        t_box = _hit_box(o, d, np.array(box[0]), np.array(box[1])) if box is not None else np.full(HW, np.inf)
        noise = rng.normal(0.0, noise_m, HW)
        mask = (t_box < _hit_plane(o, d, normal, np.array([0.0, 0.0, TABLE_Z]))).astype(np.int32)
        kw = {"depth": _depth(o, d, normal, TABLE_Z, t_box, noise)} if depth else {}
        if sensor_table_z is not None:
            kw["sensor_depth"] = _depth(o, d, normal, sensor_table_z, t_box, noise)
        views.append(CameraView(K=K, T_world_cam=T, rgb=np.zeros((*HW, 3), np.uint8),
                                mask=mask if masks else None, name=f"v{i}", **kw))
    return Capture(views=tuple(views), scenario="synthetic", object_ids=(1,) if box is not None else ())


def test_height_and_normal_recovered_from_noisy_views_of_plane_and_box():
    plane = estimate_table_plane(_capture())
    assert isinstance(plane, TablePlane) and plane.channel == "depth"
    assert abs(plane.height_m - TABLE_Z) < 1e-3
    assert plane.tilt_deg < 1.0 and plane.normal[2] > 0 and np.linalg.norm(plane.normal) == pytest.approx(1.0)
    assert plane.inlier_share > 0.9 and plane.residual_std_m == pytest.approx(1e-3, rel=0.3)
    d = plane.as_dict()
    assert json.loads(json.dumps(d)) == d and d["channel"] == "depth"
    # deterministic for a given rng; subsampling caps the fit points
    again = estimate_table_plane(_capture(), rng=np.random.default_rng(0))
    assert again.height_m == plane.height_m
    small = estimate_table_plane(_capture(), max_points=2_000, rng=np.random.default_rng(1))
    assert small.n_points == 2_000 and abs(small.height_m - TABLE_Z) < 1e-3


def test_masked_object_pixels_are_left_out():
    big = ((-0.3, -0.3, 0.0), (0.3, 0.3, 0.05))  # a wide box whose top would out-vote the table
    masked = estimate_table_plane(_capture(box=big, noise_m=0.0005))
    assert abs(masked.height_m - TABLE_Z) < 1e-3
    unmasked = estimate_table_plane(_capture(box=big, noise_m=0.0005, masks=False))
    assert abs(unmasked.height_m - 0.05) < 1e-3  # proof the box top dominates when the mask is ignored
    assert masked.n_points < unmasked.n_points


def test_sensor_depth_preferred_and_channel_choice():
    cap = _capture(sensor_table_z=TABLE_Z - 0.006)
    sensor = estimate_table_plane(cap)
    assert sensor.channel == "sensor_depth" and abs(sensor.height_m - (TABLE_Z - 0.006)) < 1e-3
    ideal = estimate_table_plane(cap, channel="depth")
    assert ideal.channel == "depth" and abs(ideal.height_m - TABLE_Z) < 1e-3
    with pytest.raises(UnknownNameError, match="sensor_depth"):
        estimate_table_plane(cap, channel="stereo")
    with pytest.raises(CaptureError, match="no 'sensor_depth'"):
        estimate_table_plane(_capture(), channel="sensor_depth")


def test_tilted_plane_is_refused():
    with pytest.raises(CaptureError, match=r"near-horizontal.*20%"):
        estimate_table_plane(_capture(box=None, tilt_deg=30.0))
    assert estimate_table_plane(_capture(box=None, tilt_deg=5.0)).tilt_deg == pytest.approx(5.0, abs=1.0)


def test_capture_without_depth_or_with_too_few_points_raises():
    with pytest.raises(CaptureError, match="capture with depth, or declare the table height"):
        estimate_table_plane(_capture(depth=False))
    cap = _capture()
    sparse = [v.with_(depth=np.where(np.arange(v.depth.size).reshape(HW) < 100, v.depth, 0).astype(np.float32))
              for v in cap.views]
    with pytest.raises(CaptureError, match=r"only \d+ valid depth points .*500"):
        estimate_table_plane(Capture(views=tuple(sparse)))


def test_simulated_rw3_capture_matches_the_true_table_height():
    pytest.importorskip("mujoco")
    from sim.backend import SimBackend
    from sim.cameras.rig import CameraRigConfig
    from sim.world import build_world

    backend = SimBackend(build_world("rw3", seed=0),
                         camera_config=CameraRigConfig(n_views=6, scale=0.1, channels=("sensor_depth", "mask")))
    try:
        cap = backend.capture()
        plane = estimate_table_plane(cap)
        true_z = backend.ground_truth.table_height()
    finally:
        backend.close()
    assert plane.channel == "sensor_depth"
    assert abs(plane.height_m - true_z) < 2e-3, plane.as_dict()
    assert plane.tilt_deg < 1.0


def test_the_loop_fits_the_table_without_the_captures_masks():
    """table=capture in the loop never reads instance masks (in simulation, the simulator's truth): with the masks
    replaced by garbage (every pixel an object) it still fits the table from sensor depth, objects as outliers,
    within 2 mm of the truth (rw7: a dense scene, the most object pixels of the rw suite)."""
    pytest.importorskip("mujoco")
    from sim.backend import SimBackend
    from sim.cameras.rig import CameraRigConfig
    from sim.world import build_world
    from torm import config as cfgmod
    from torm.loop import table_height
    from torm.pipeline import TrialConfig

    backend = SimBackend(build_world("rw7", seed=0),
                         camera_config=CameraRigConfig(n_views=6, scale=0.1, channels=("sensor_depth", "mask")))
    try:
        cap = backend.capture()
        true_z = backend.ground_truth.table_height()
    finally:
        backend.close()
    poisoned = Capture(views=tuple(v.with_(mask=np.ones_like(v.mask)) for v in cap.views))
    with pytest.raises(CaptureError):  # reading the masks would leave no table point at all
        estimate_table_plane(poisoned)
    cfg = cfgmod.from_dict(TrialConfig, {"scenario": "rw7"}, ["table=capture"])
    z, info = table_height(cfg, backend, poisoned)
    assert info["source"] == "capture" and info["channel"] == "sensor_depth"
    assert abs(z - true_z) < 2e-3, info
