"""nearest_rotation: proper rotations nearest to a matrix (Frobenius), batched, reflections mended."""

import numpy as np
from scipy.spatial.transform import Rotation

from torm.geometry import is_rotation, nearest_rotation


def test_nearest_rotation_recovers_rotations_from_noise_and_mends_reflections():
    R = Rotation.random(8, random_state=0).as_matrix()
    noisy = R + np.random.default_rng(0).normal(0, 1e-3, R.shape)
    out = nearest_rotation(noisy)
    assert out.shape == (8, 3, 3) and all(is_rotation(r) for r in out)
    assert np.abs(out - R).max() < 5e-3
    np.testing.assert_allclose(nearest_rotation(R), R, atol=1e-12)  # a rotation is its own nearest
    flip = R[0] @ np.diag([1.0, 1.0, -1.0])  # det -1: the nearest proper rotation, not the reflection
    assert np.linalg.det(nearest_rotation(flip)) > 0.99
    # on a scaled rotation the nearest rotation is the rotation (polar decomposition)
    np.testing.assert_allclose(nearest_rotation(3.0 * R[1]), R[1], atol=1e-12)
