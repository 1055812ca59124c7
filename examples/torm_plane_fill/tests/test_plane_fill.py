"""The example plug-in on a hand-built view: a box whose depth is missing on half its pixels."""

import numpy as np
from torm_plane_fill import PlaneFill

from torm.methods import MethodContext
from torm.types import CameraView, Capture


def _view(drop: float) -> Capture:
    from torm.geometry import look_at_cv

    H, W = 60, 80
    K = np.array([[70.0, 0, 40], [0, 70.0, 30], [0, 0, 1]])
    T = look_at_cv(np.array([0.55, 0.0, 0.5]), np.array([0.55, 0.0, 0.0]))  # looking straight down from 0.5 m
    depth = np.full((H, W), 0.5, np.float32)  # the table at z = 0
    mask = np.zeros((H, W), np.int32)
    mask[20:40, 30:50] = 1
    depth[mask == 1] = 0.45  # a box 5 cm tall
    rng = np.random.default_rng(0)
    holes = (mask == 1) & (rng.random((H, W)) < drop)
    depth[holes] = 0.0  # glass: no return
    return Capture(views=(CameraView(K, T, sensor_depth=depth, mask=mask),))


def test_plane_fill_recovers_the_top_of_a_box_with_missing_depth():
    ctx = MethodContext(n_points=256, rng=np.random.default_rng(0), table_height=0.0,
                        workspace_bounds=np.array([[0.2, -0.4, -0.03], [0.9, 0.4, 0.4]]))
    for drop in (0.5, 1.0):  # half the depth missing: plane fit; all missing: the table-plane fallback
        (obj,) = PlaneFill().perceive(_view(drop), ctx)
        top = obj.points_nx3[:, 2].max()
        assert obj.points_nx3.shape[1] == 3 and np.isfinite(obj.points_nx3).all()
        assert (0.04 < top < 0.06) if drop < 1 else (top < 0.02)  # the fallback knows only the base
        assert abs(obj.points_nx3[:, 0].mean() - 0.55) < 0.03
