"""The built-in methods and planner implement the plug-in interface (issue 40): loaded by name like a plug-in, their
``perceive`` passes the plug-in output checks, and a built-in run as a ``module:callable`` plug-in gives the same
geometry as the built-in path of the loop."""

from __future__ import annotations

import numpy as np
import pytest

from torm.errors import ConfigError
from torm.geometry import look_at_cv
from torm.types import CameraView, Capture

BOUNDS = np.array([[0.15, -0.45, -0.03], [0.95, 0.45, 0.40]])


def _box_capture(n_views: int = 1) -> Capture:
    """Views from 0.5 m above a 13 x 13 x 5 cm block on a table at z = 0, its centre near (0.55, 0); exact depth and
    masks."""
    H, W = 60, 80
    K = np.array([[70.0, 0, 40], [0, 70.0, 30], [0, 0, 1]])
    views = []
    for k in range(n_views):
        eye = np.array([0.55 + 0.05 * k, 0.0, 0.5])
        T = look_at_cv(eye, np.array([0.55, 0.0, 0.0]))
        depth = np.full((H, W), 0.5, np.float32)
        mask = np.zeros((H, W), np.int32)
        mask[20:40, 30:50] = 1
        depth[mask == 1] = 0.45
        views.append(CameraView(K, T, sensor_depth=depth, mask=mask))
    return Capture(views=tuple(views))


def _ctx(seed: int = 0):
    from torm.methods import MethodContext

    return MethodContext(n_points=256, rng=np.random.default_rng(seed), table_height=0.0, workspace_bounds=BOUNDS)


def test_every_builtin_loads_by_name_and_satisfies_the_interface():
    from torm.methods import BUILTINS, PerceptionMethod, load_method, method_info

    for name in BUILTINS:
        opts = {"meshes": dict} if name == "oracle" else {}
        m = load_method(name, opts)
        assert isinstance(m, PerceptionMethod) and m.name == name
        assert method_info(name).source == "builtin" and m.version == method_info(name).version
    # what each declares is what the loop captures for it
    assert load_method("depth").needs.channels() == ("sensor_depth", "mask")
    assert load_method("depth").needs.views == "top_down"
    assert load_method("torm", {"segmenter": "learned"}).needs.rgb
    assert not load_method("torm").needs.rgb and load_method("torm").needs.masks
    with pytest.raises(ConfigError, match="real backend has none"):
        load_method("oracle")
    with pytest.raises(ConfigError, match="view must be >= 0"):
        load_method("depth", {"view": -1})


def test_builtin_depth_perceive_passes_the_plugin_checks_and_equals_run():
    from torm.methods import load_method, validate_estimates

    m = load_method("depth")
    per = m.run(_box_capture(), _ctx())
    est = validate_estimates("depth", m.perceive(_box_capture(), _ctx()), BOUNDS)
    assert len(est) == len(per.point_clouds) == 1
    np.testing.assert_array_equal(est[0].points_nx3, per.point_clouds[0].points_nx3)
    top = est[0].points_nx3[:, 2].max()
    assert abs(top - 0.05) < 0.005  # the box top, 5 cm above the table
    # a view index picks that view of a multi-view capture; outside the capture it is a named error
    assert len(load_method("depth", {"view": 2}).perceive(_box_capture(3), _ctx())) == 1
    with pytest.raises(ConfigError, match="outside the capture's views 0..2"):
        load_method("depth", {"view": 5}).perceive(_box_capture(3), _ctx())


def test_builtin_oracle_samples_the_meshes_it_is_given():
    from torm.methods import load_method, validate_estimates
    from torm.types import TriMesh

    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], float) * 0.05 + [0.5, 0.0, 0.0]
    f = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])
    est = validate_estimates("oracle", load_method("oracle", {"meshes": lambda: {7: TriMesh(v, f)}}).perceive(
        _box_capture(), _ctx()), BOUNDS)
    assert len(est) == 1 and est[0].mesh is not None
    p = est[0].points_nx3
    assert len(p) == 256 and p.min() >= -1e-9 and np.all(p[:, 0] >= 0.5 - 1e-9)


def test_builtin_torm_method_accepts_a_segmenter_object():
    from torm.methods.builtin_methods import TormMethod

    class Seg:
        needs_reference = True

        def segment(self, capture):  # pragma: no cover - not called
            raise AssertionError

    m = TormMethod(Seg(), segmenter_name="learned")
    assert m.needs.rgb and m.needs.reference and not m.needs.masks
    with pytest.raises(ConfigError, match="segment\\(capture\\)"):
        TormMethod(object())


def test_builtin_antipodal_planner_goes_through_the_planner_interface():
    import trimesh

    from torm.grasp.gripper import GripperGeometry
    from torm.grasp.planner import GraspPlannerConfig
    from torm.methods import load_method
    from torm.methods.planner_plugins import PlannerContext, load_planner, validate_grasps
    from torm.types import TriMesh

    box = trimesh.creation.box((0.04, 0.04, 0.05))
    box.apply_translation((0.55, 0.0, 0.025))
    per = load_method("oracle", {"meshes": lambda: {1: TriMesh(np.asarray(box.vertices), np.asarray(box.faces))}}
                      ).run(_box_capture(), _ctx())
    planner = load_planner("antipodal")
    ctx = PlannerContext(table_height=0.0, gripper=GripperGeometry(), obstacles=None, rng=np.random.default_rng(0),
                         config=GraspPlannerConfig())
    grasps = validate_grasps("antipodal", planner.plan(per.point_clouds, per.meshes, ctx), per.point_clouds,
                             GripperGeometry().max_opening)
    assert len(grasps) == 1 and grasps[0], "a 4 cm box has antipodal grasps"


@pytest.mark.slow
def test_a_builtin_run_as_a_module_callable_plugin_sees_the_same_depth_as_the_builtin():
    """The loop's built-in path and the plug-in path give the same single-view clouds (the plug-in path resamples
    them, so its points are a subset of the built-in's)."""
    from torm import config
    from torm.backend.blind import LoopBackend
    from torm.loop import grants_masks, perceive
    from torm.pipeline import TrialConfig, make_backend

    clouds = {}
    for method in ("depth", "torm.methods.builtin_methods:DepthMethod"):
        cfg = config.from_dict(TrialConfig, {"scenario": "rw1", "method": method}, [
            "capture.n_views=6", "capture.scale=0.25", "capture.depth_model=statistical"])
        backend = make_backend(cfg)
        try:
            assert grants_masks(cfg)  # the depth baseline cuts with the capture's masks: declared
            per = perceive(cfg, LoopBackend(backend, grant_masks=True), np.random.default_rng(3), {})
        finally:
            backend.close()
        assert per.info["capture_info"]["views_captured"] == 1
        clouds[method] = np.vstack([c.points_nx3 for c in per.point_clouds])
    builtin, plugin = clouds.values()
    d = np.min(np.linalg.norm(plugin[:, None, :] - builtin[None, ::4, :], axis=2), axis=1)
    assert np.median(d) < 0.004, "the plug-in path must see the same object surface"
    assert np.isin(plugin.view(np.void(24)), builtin.view(np.void(24))).mean() > 0.99
