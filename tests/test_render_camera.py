"""OpenCV -> Mitsuba camera convention: known 3-D points land on the predicted pixels (principal points too)."""

from __future__ import annotations

import numpy as np
import pytest

from sim.render.base import RenderCamera, RenderError
from sim.render.mitsuba_env import load_mitsuba
from sim.render.mitsuba_renderer import instance_ids, sensor_dict
from sim.render.scene import PbrScene
from tests.render_helpers import camera

mi, VARIANT = load_mitsuba("auto")


def _ray_through(cam: RenderCamera, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    sensor = mi.load_dict(sensor_dict(cam))
    u = np.asarray(uv[:, 0] / cam.width, np.float32)
    v = np.asarray(uv[:, 1] / cam.height, np.float32)
    if VARIANT.startswith("scalar"):
        rays = [sensor.sample_ray(0.0, 0.5, mi.Point2f(float(a), float(b)), mi.Point2f(0.5, 0.5))[0]
                for a, b in zip(u, v, strict=True)]
        return np.array([np.ravel(r.o) for r in rays]), np.array([np.ravel(r.d) for r in rays])
    ray, _ = sensor.sample_ray(0.0, 0.5, mi.Point2f(u, v), mi.Point2f(0.5, 0.5))
    return np.asarray(ray.o).T.reshape(-1, 3), np.asarray(ray.d).T.reshape(-1, 3)


@pytest.mark.parametrize("c", [None, (20.0, 30.0), (45.5, 12.25)])
def test_ray_through_projected_pixel_passes_through_the_point(c):
    cam = camera(width=64, height=48, f=50.0, c=c)
    rng = np.random.default_rng(0)
    pts = np.array([0.02, 0.0, 0.02]) + rng.uniform(-0.05, 0.05, (20, 3))
    uv = cam.project(pts)
    o, d = _ray_through(cam, uv)
    d = d / np.linalg.norm(d, axis=1, keepdims=True)
    w = pts - o
    dist = np.linalg.norm(np.cross(d, w), axis=1)
    assert dist.max() < 1e-5  # metres: the ray hits the point
    # ... and comes from the camera centre (Mitsuba starts it on the near plane, 5 mm ahead)
    back = np.linalg.norm(np.cross(d, cam.T_world_cam[:3, 3] - o), axis=1)
    assert back.max() < 1e-5
    # rays point forward (+z of the OpenCV camera), not backwards
    assert np.all(np.einsum("ij,ij->i", d, w) > 0)


def test_principal_point_offset_moves_the_image_the_predicted_way():
    """A small sphere's id-pass centroid sits at its OpenCV projection for centred and off-centre principal points."""
    P = np.array([0.03, 0.01, 0.04])
    scene = mi.load_dict({"type": "scene", "ball": {"type": "sphere", "id": "ball", "radius": 0.006,
                                                    "to_world": mi.ScalarTransform4f().translate(P.tolist())}},
                         optimize=False)
    pbr = PbrScene({}, {"ball": 1}, None, None)
    for c in [(32.0, 24.0), (18.0, 33.0), (50.0, 10.0)]:
        cam = camera(width=64, height=48, f=60.0, c=c, eye=(0.12, -0.10, 0.14), target=(0.03, 0.01, 0.04))
        ids = instance_ids(pbr, scene, cam)
        jj, ii = np.nonzero(ids == 1)
        assert len(ii) > 5
        centroid = np.array([ii.mean() + 0.5, jj.mean() + 0.5])
        np.testing.assert_allclose(centroid, cam.project(P[None])[0], atol=0.35)


def test_non_square_pixels_are_refused_with_a_clear_error():
    cam = RenderCamera(np.array([[50.0, 0, 32], [0, 55.0, 24], [0, 0, 1]]), np.eye(4), 64, 48)
    with pytest.raises(RenderError, match="square pixels"):
        sensor_dict(cam)
