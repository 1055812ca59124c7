"""Bring your own method (issue 40): plug-ins found by entry point or module:callable run trials and benchmarks
like built-ins; their outputs are checked; a crashing plug-in costs one error row."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

from torm.errors import PluginError

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"
BOUNDS = np.array([[0.15, -0.45, -0.03], [0.95, 0.45, 0.40]])


def _install(site: Path, package: str, dist_name: str, group: str, entry: str, monkeypatch) -> Path:
    """An example package as pip installs it: its ``src`` importable and a dist-info declaring ``entry`` in
    ``group``; returns the package's ``src`` folder."""
    src = EXAMPLES / package / "src"
    dist = site / f"{package}-0.1.0.dist-info"
    dist.mkdir(parents=True)
    (dist / "METADATA").write_text(f"Metadata-Version: 2.1\nName: {dist_name}\nVersion: 0.1.0\n")
    (dist / "entry_points.txt").write_text(f"[{group}]\n{entry}\n")
    monkeypatch.syspath_prepend(str(site))
    monkeypatch.syspath_prepend(str(src))
    return src


@pytest.fixture
def installed_plane_fill(tmp_path, monkeypatch):
    """The example perception plug-in installed (workers find it through PYTHONPATH too)."""
    site = tmp_path / "site"
    src = _install(site, "torm_plane_fill", "torm-plane-fill", "torm.methods", "plane_fill = torm_plane_fill:PlaneFill",
                   monkeypatch)
    monkeypatch.setenv("PYTHONPATH", f"{src}:{site}:{Path(__file__).parent}")
    yield "plane_fill"
    sys.modules.pop("torm_plane_fill", None)


@pytest.fixture
def installed_scene_graspnet(tmp_path, monkeypatch):
    """The example planner plug-in installed (its ``torm.planners`` entry point) and a tiny model."""
    _install(tmp_path / "site_planner", "torm_scene_graspnet", "torm-scene-graspnet", "torm.planners",
             "scene_graspnet = torm_scene_graspnet:SceneGraspNet", monkeypatch)
    from torm_scene_graspnet.tiny_model import build_tiny_model

    yield build_tiny_model(tmp_path / "tiny_scene_graspnet.onnx")
    for mod in ("torm_scene_graspnet", "torm_scene_graspnet.tiny_model"):
        sys.modules.pop(mod, None)


def test_registry_lists_builtins_and_installed_plugins_and_names_bad_ones(installed_plane_fill):
    from torm.errors import UnknownNameError
    from torm.methods import list_methods, load_method, method_info

    rows = {r.name: r for r in list_methods()}
    assert {"torm", "depth", "depth_fusion", "oracle", "plane_fill"} <= set(rows)
    assert rows["plane_fill"].version == "0.1.0" and "entry point" in rows["plane_fill"].source
    assert method_info("plugin_methods:Returns").source == "module:callable"
    with pytest.raises(UnknownNameError, match="plane_fill"):
        load_method("plane_fil")
    with pytest.raises(PluginError, match="cannot import"):
        load_method("plugin_methods:Nope")
    with pytest.raises(PluginError, match="does not accept the options"):
        load_method("plugin_methods:Returns", {"colour": "red"})
    with pytest.raises(PluginError, match="lacks"):
        load_method("json:JSONDecoder")


@pytest.mark.parametrize(("kind", "match"), [
    ("nan", "NaN or inf"), ("camera_frame", "world frame"), ("mm", "millimetres"), ("shape", r"shape \(50, 2\)"),
    ("array", "returned ndarray")])
def test_malformed_plugin_output_is_a_named_error(kind, match):
    from torm.methods import MethodContext, load_method, validate_estimates

    m = load_method("plugin_methods:Returns", {"kind": kind})
    ctx = MethodContext(64, np.random.default_rng(0), 0.0, BOUNDS)
    with pytest.raises(PluginError, match=f"method 'plugin_methods:Returns'.*{match}"):
        validate_estimates("plugin_methods:Returns", m.perceive(None, ctx), BOUNDS)
    assert len(validate_estimates("x", load_method("plugin_methods:Returns").perceive(None, ctx), BOUNDS)) == 1


@pytest.mark.slow
def test_an_installed_plugin_runs_a_trial_and_its_row_names_it(installed_plane_fill):
    from torm import config
    from torm.pipeline import TrialConfig, run_trial

    cfg = config.from_dict(TrialConfig, {"scenario": "rw1", "method": installed_plane_fill}, [
        "capture.n_views=6", "capture.scale=0.25", "capture.depth_model=statistical"])
    rec = run_trial(cfg)
    ctx = rec["context"]
    assert (ctx["method_name"], ctx["method_version"]) == ("plane_fill", "0.1.0")
    assert "entry point" in ctx["method_source"]
    assert rec["perception"]["capture_info"]["needs"]["views"] == "top_down"
    assert rec["perception"]["capture_info"]["views_captured"] == 1  # it paid for one view, as it declared
    assert rec["n_objects"] == 1 and "failure" in rec


@pytest.mark.slow
def test_module_callable_plugins_run_in_the_bench_and_a_crashing_one_costs_one_row(installed_plane_fill, tmp_path):
    from torm.bench import BenchConfig, run_benchmark
    from torm.bench.results import read_results

    kw = {"suite": "rw", "scenarios": ("rw1",), "trials": 1, "timeout_s": 300.0, "workers": 1,
          "methods": ("torm_plane_fill:PlaneFill", "plugin_methods:Crashing"),
          "overrides": ("capture.n_views=6", "capture.scale=0.25")}
    run_benchmark(BenchConfig(**kw), tmp_path / "run", progress=False)
    rows = {r["method"]: r for r in read_results(tmp_path / "run" / "results.jsonl").rows}
    assert set(rows) == {"torm_plane_fill:PlaneFill", "plugin_methods:Crashing"}
    ok = rows["torm_plane_fill:PlaneFill"]
    assert ok["status"] == "ok", ok.get("message")
    assert ok["context"]["method_version"] == "0.1.0" and ok["context"]["method_source"] == "module:callable"
    bad = rows["plugin_methods:Crashing"]
    assert bad["status"] != "ok" and "this plug-in always fails" in str(bad.get("message", bad))


def test_planner_plugins_are_found_checked_and_their_mistakes_named():
    from torm.errors import UnknownNameError
    from torm.grasp.gripper import GripperGeometry
    from torm.methods.planner_plugins import PlannerContext, load_planner, validate_grasps
    from torm.pipeline import TrialConfig
    from torm.types import ObjectPointCloud

    with pytest.raises(UnknownNameError, match="antipodal, onnx_graspnet"):
        TrialConfig(planner="graspnett")
    with pytest.raises(PluginError, match="model_path"):
        load_planner("onnx_graspnet")
    p = np.random.default_rng(0).normal([0.55, 0.0, 0.04], 0.015, (200, 3))
    clouds = [ObjectPointCloud(p, np.tile([0.0, 0.0, 1.0], (200, 1)), 1000)]
    ctx = PlannerContext(0.0, GripperGeometry(), None, np.random.default_rng(0), None)
    good = load_planner("plugin_methods:TopDown").plan(clouds, None, ctx)
    assert len(validate_grasps("td", good, clouds, 0.085)[0]) == 1
    with pytest.raises(PluginError, match="world frame"):
        validate_grasps("td", load_planner("plugin_methods:TopDown", {"frame": "object"}).plan(clouds, None, ctx),
                        clouds, 0.085)
    with pytest.raises(PluginError, match="one list per input cloud"):
        validate_grasps("td", good * 2, clouds, 0.085)
    with pytest.raises(PluginError, match="exceeds the gripper's stroke"):
        validate_grasps("td", good, clouds, 0.01)


def test_a_planner_plugin_that_raises_is_one_named_error():
    from types import SimpleNamespace

    from torm.grasp.gripper import GripperGeometry
    from torm.loop import plan_with_planner
    from torm.pipeline import TrialConfig
    from torm.types import ObjectPointCloud

    p = np.random.default_rng(0).normal([0.55, 0.0, 0.04], 0.015, (50, 3))
    per = SimpleNamespace(point_clouds=[ObjectPointCloud(p, np.tile([0.0, 0.0, 1.0], (50, 1)), 1)], meshes=None)
    cfg = TrialConfig(scenario="rw1", planner="plugin_methods:RaisingPlanner")
    with pytest.raises(PluginError, match=r"planner plug-in 'plugin_methods:RaisingPlanner' \(version 0.0.2\) "
                                          r"raised ZeroDivisionError: division by zero in my grasp scorer; fix"):
        plan_with_planner(cfg, per, 0.0, GripperGeometry(), np.random.default_rng(0), None)


@pytest.mark.slow
def test_a_planner_plugin_plans_a_trial_and_the_row_names_it():
    from torm import config
    from torm.pipeline import TrialConfig, run_trial

    cfg = config.from_dict(TrialConfig, {"scenario": "rw1", "method": "oracle", "planner": "plugin_methods:TopDown"},
                           ["capture.n_views=2", "capture.scale=0.25"])
    rec = run_trial(cfg)
    assert rec["context"]["planner"] == "plugin_methods:TopDown" and rec["context"]["planner_version"] == "0.0.1"
    assert rec["n_objects"] == 1 and rec["objects"][0]["outcome"] not in ("error", None)


@pytest.mark.slow
def test_plugins_run_on_the_ray_engine_like_on_the_pool(local_ray, tmp_path):
    """Method and planner plug-ins by module:callable on Ray: their rows name them; a crashing plug-in is one
    error row and the other trials go on."""
    from torm.bench import BenchConfig, run_benchmark
    from torm.bench.results import read_results

    kw = {"suite": "rw", "scenarios": ("rw1",), "trials": 1, "timeout_s": 300.0, "workers": 2, "engine": "ray",
          "methods": ("plugin_methods:Returns", "plugin_methods:Crashing"),
          "overrides": ("capture.n_views=6", "capture.scale=0.25", "planner=plugin_methods:TopDown")}
    s = run_benchmark(BenchConfig(**kw), tmp_path / "run", progress=False)
    assert s["ran"] == 2
    rows = {r["method"]: r for r in read_results(tmp_path / "run" / "results.jsonl").rows}
    ok, bad = rows["plugin_methods:Returns"], rows["plugin_methods:Crashing"]
    assert ok["run"]["engine"] == "ray" and ok["status"] == "ok", ok.get("message")
    assert ok["context"]["method_version"] == "0.0.1" and ok["context"]["method_source"] == "module:callable"
    assert ok["context"]["planner"] == "plugin_methods:TopDown" and ok["context"]["planner_version"] == "0.0.1"
    assert bad["status"] != "ok" and "this plug-in always fails" in str(bad.get("message", bad))


@pytest.mark.slow
def test_an_installed_planner_plugin_plans_a_trial_and_its_row_names_it(installed_scene_graspnet):
    """The example planner package, found through its entry point, plans a real trial (oracle clouds)."""
    from torm import config
    from torm.pipeline import TrialConfig, run_trial

    cfg = config.from_dict(TrialConfig, {"scenario": "rw1", "method": "oracle", "planner": "scene_graspnet",
                                         "planner_options": {"model_path": str(installed_scene_graspnet)}},
                           ["capture.n_views=2", "capture.scale=0.25"])
    rec = run_trial(cfg)
    ctx = rec["context"]
    assert (ctx["planner"], ctx["planner_version"]) == ("scene_graspnet", "0.1.0")
    assert rec["n_objects"] == 1 and rec["objects"][0]["outcome"] not in ("error", None)
    assert rec["attempts"] and rec["attempts"][0]["n_candidates"] > 0, rec["attempts"]
