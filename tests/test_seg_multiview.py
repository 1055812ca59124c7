"""Union silhouettes and cross-view consistency checks on a geometrically exact synthetic capture."""

from __future__ import annotations

import numpy as np
import pytest

from torm.errors import ConfigError, SegmentationError
from torm.segmentation.multiview import ConsistencyConfig, check_views, union_silhouettes
from torm.segmentation.sphere_capture import sphere_capture


@pytest.fixture(scope="module")
def cap():
    return sphere_capture(n_views=30, size_px=128, seed=2)


def _broken(cap):
    m = cap.masks().copy()
    m[3][:] = 0  # segmenter found nothing
    m[7][m[7] == 2] = 0  # the biggest object missed
    m[11] = np.roll(m[11], 25, axis=1)  # silhouettes in the wrong place (same area)
    m[15][10:50, 10:50] = 9  # a large spurious blob
    return m


def test_union_silhouettes():
    m = np.array([[[0, 2], [5, 0]]])
    np.testing.assert_array_equal(union_silhouettes(m), [[[False, True], [True, False]]])
    with pytest.raises(SegmentationError):
        union_silhouettes(np.zeros((4, 4)))


def test_clean_views_are_all_kept(cap):
    rep = check_views(cap)
    assert rep.kept == list(range(30)) and rep.reasons == {}
    assert min(rep.stats["hull_iou"]) > 0.5  # every clean view agrees with the others' hull


def test_broken_views_are_found_by_each_check(cap):
    m = _broken(cap)
    area = check_views(cap, ConsistencyConfig(checks=("area",)), masks_vxhxw=m)
    assert {3, 7, 15} <= set(area.flagged) and 11 not in area.flagged  # a shift keeps the area
    hull = check_views(cap, ConsistencyConfig(checks=("hull",)), masks_vxhxw=m)
    assert set(hull.flagged) == {3, 7, 11, 15}
    assert hull.kept == [i for i in range(30) if i not in (3, 7, 11, 15)]
    both = check_views(cap, masks_vxhxw=m)
    assert set(both.flagged) == {3, 7, 11, 15} and "visual hull" in both.reasons[11][0]
    flag_only = check_views(cap, ConsistencyConfig(action="flag"), masks_vxhxw=m)
    assert flag_only.kept == list(range(30)) and set(flag_only.flagged) == {3, 7, 11, 15}


def test_config_validation(cap):
    with pytest.raises(ConfigError, match="unknown check"):
        ConsistencyConfig(checks=("colour",))
    with pytest.raises(SegmentationError, match="every view"):
        check_views(cap, ConsistencyConfig(checks=("hull",), hull_min_iou=0.99))
