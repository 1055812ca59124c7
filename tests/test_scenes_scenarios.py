"""Scenario suites (YAML), loading errors and seeded placement."""

from __future__ import annotations

import numpy as np
import pytest

from sim.scenes.objects import get_object
from sim.scenes.placement import (
    Placement,
    PlacementConfig,
    footprint_world,
    pairwise_gaps,
    place_objects,
    polygon_gap,
    scenario_rules,
)
from sim.scenes.scenario import Scenario, get_scenario, list_scenarios, load_suite
from torm.errors import ConfigError, SceneError, UnknownNameError

TABLE_III = {
    "rw1": ["cylinder"],
    "rw2": ["opaque_cup"],
    "rw3": ["cylinder", "hexagonal_prism"],
    "rw4": ["ball", "cube", "toothpick_box"],
    "rw5": ["ball", "opaque_cup"],
    "rw6": ["ball", "heart", "ice_cube", "toothpick_box"],
    "rw7": ["ball", "cylinder", "toothpick_box"],
    "rw8": ["cylinder", "pyramidal_frustum", "toothpick_box"],
}


def test_suites_match_the_paper():
    assert list_scenarios("rw") == [f"rw{i}" for i in range(1, 9)]
    assert list_scenarios("syn") == [f"syn{i}" for i in range(1, 13)]
    for name, objs in TABLE_III.items():
        sc = get_scenario(name)
        assert list(sc.objects) == objs and sc.suite == "rw"
        assert sc.spacing == ("dense" if name in ("rw7", "rw8") else "moderate")
    for i in range(1, 13):
        sc = get_scenario(f"syn{i}")
        assert 2 <= len(sc.objects) <= 10
        assert sc.spacing == ("dense" if i >= 10 else "moderate")
        assert "opaque_cup" not in sc.objects  # the synthetic scenes are all glass
    assert max(len(get_scenario(f"syn{i}").objects) for i in range(1, 13)) == 10


def test_unknown_scenario_lists_valid_names():
    with pytest.raises(UnknownNameError) as exc:
        get_scenario("rw9")
    msg = str(exc.value)
    assert "rw9" in msg and "rw8" in msg and "syn12" in msg


def _write(tmp_path, text):
    p = tmp_path / "bad.yaml"
    p.write_text(text)
    return p


@pytest.mark.parametrize(
    ("body", "needle"),
    [
        ("scenarios:\n  - {name: a, objects: [cylinder], spacing: tight}\n", "spacing"),
        ("scenarios:\n  - {name: a, objectz: [cylinder]}\n", "objectz"),
        ("scenarios:\n  - {name: a, objects: [cylinder, cilinder]}\n", "objects[1]"),
        ("scenarios:\n  - {name: a, objects: [cylinder], poses: [[0.5, 0.0]]}\n", "poses"),
        ("scenarios:\n  - {name: a, objects: [cylinder, ball], poses: [[0.5, 0.0, 0.0]]}\n", "poses"),
        ("scenarios:\n  - {objects: [cylinder]}\n", "name"),
        ("defaults: {spacing: 3}\nscenarios:\n  - {name: a, objects: [cylinder]}\n", "spacing"),
        ("scenarioz: []\n", "scenarioz"),
    ],
)
def test_malformed_suite_names_the_field(tmp_path, body, needle):
    with pytest.raises(ConfigError) as exc:
        load_suite(_write(tmp_path, body))
    assert needle in str(exc.value)
    assert "bad.yaml" in str(exc.value)


def test_suite_defaults_apply(tmp_path):
    p = _write(tmp_path, "suite: t\ndefaults: {spacing: dense}\nscenarios:\n  - {name: a, objects: [ball]}\n"
                         "  - {name: b, objects: [ball], spacing: moderate}\n")
    a, b = load_suite(p)
    assert (a.spacing, b.spacing, a.suite) == ("dense", "moderate", "t")


def _layout(name, seed):
    sc = get_scenario(name)
    poses = place_objects(sc, np.random.default_rng(seed))
    return sc, poses


def test_placement_is_deterministic_per_seed():
    _, a = _layout("syn9", 7)
    _, b = _layout("syn9", 7)
    _, c = _layout("syn9", 8)
    assert a == b
    assert a != c


@pytest.mark.parametrize("name", [f"syn{i}" for i in range(1, 13)] + [f"rw{i}" for i in range(1, 9)])
def test_placement_respects_workspace_and_gaps(name):
    for seed in range(3):
        sc, poses = _layout(name, seed)
        cfg = scenario_rules(sc, PlacementConfig())  # the scenario's own gap range where it declares one
        assets = [get_object(n) for n in sc.objects]
        for a, p in zip(assets, poses, strict=True):
            fp = footprint_world(a, p)
            assert fp[:, 0].min() >= 0.35 - 1e-9 and fp[:, 0].max() <= 0.75 + 1e-9
            assert fp[:, 1].min() >= -0.20 - 1e-9 and fp[:, 1].max() <= 0.20 + 1e-9
        gaps = pairwise_gaps(assets, poses)
        for i in range(len(assets)):
            for j in range(i + 1, len(assets)):
                w = 0.5 * (assets[i].width + assets[j].width)
                assert gaps[i, j] >= cfg.gap_range(sc.spacing, w)[0] - 1e-9
                assert gaps[i, j] >= 0.020 - 1e-9  # a finger always fits between two objects


def _nearest_gaps(name, seeds):
    out = []
    for s in seeds:
        sc, poses = _layout(name, s)
        g = pairwise_gaps([get_object(n) for n in sc.objects], poses)
        out.extend(g.min(axis=1) / np.mean([get_object(n).width for n in sc.objects]))
    return np.array(out)


def test_dense_scenes_have_smaller_gaps_than_moderate():
    dense = _nearest_gaps("rw7", range(10))  # ball, cylinder, toothpick box (dense)
    moderate = _nearest_gaps("rw4", range(10))  # ball, cube, toothpick box (moderate)
    assert dense.max() < moderate.min()
    assert 0.3 < np.median(dense) < 0.7  # about half an object width
    assert np.median(moderate) >= 1.0


def test_polygon_gap_is_exact_for_boxes():
    sq = np.array([[0, 0], [1, 0], [1, 1], [0, 1]], dtype=float)
    assert polygon_gap(sq, sq + [3, 0]) == pytest.approx(2.0)
    assert polygon_gap(sq, sq + [2, 2]) == pytest.approx(np.sqrt(2))
    assert polygon_gap(sq, sq + [0.5, 0.5]) == 0.0


def test_impossible_layout_raises_scene_error_naming_the_scenario():
    sc = Scenario(name="too_many", objects=("cup",) * 25, spacing="moderate")
    with pytest.raises(SceneError) as exc:
        place_objects(sc, 0, PlacementConfig(tries_per_object=20, max_layouts=3))
    assert "too_many" in str(exc.value) and "3 layouts" in str(exc.value)


def test_fixed_poses_are_used_and_checked():
    sc = Scenario(name="fixed", objects=("cylinder", "ball"), poses=((0.5, -0.1, 0.0), (0.6, 0.1, 1.0)))
    assert place_objects(sc, 123) == [Placement(0.5, -0.1, 0.0), Placement(0.6, 0.1, 1.0)]
    overlap = Scenario(name="overlap", objects=("cylinder", "ball"), poses=((0.5, 0.0, 0.0), (0.52, 0.0, 0.0)))
    with pytest.raises(SceneError, match="overlap"):
        place_objects(overlap, 0)
    outside = Scenario(name="outside", objects=("cylinder",), poses=((0.9, 0.0, 0.0),))
    with pytest.raises(SceneError, match="workspace"):
        place_objects(outside, 0)


def test_scenario_targets_name_the_classes_the_task_picks():
    """RW2 and RW5 target the opaque cup as the paper's prompt does; the rest target glass; a bad class is refused."""
    from sim.scenes.scenario import Scenario, get_scenario
    from torm.errors import ConfigError

    assert get_scenario("rw2").targets == ("transparent", "opaque") == get_scenario("rw5").targets
    assert all(get_scenario(f"rw{k}").targets == ("transparent",) for k in (1, 3, 4, 6, 7, 8))
    with pytest.raises(ConfigError, match="among transparent, opaque"):
        Scenario(name="x", objects=("cylinder",), targets=("glass",))
    with pytest.raises(ConfigError, match="among transparent, opaque"):
        Scenario(name="x", objects=("cylinder",), targets=())


def test_a_trial_prompts_a_learned_segmenter_with_its_scenarios_targets(caplog):
    """Without a class head the prompt stays 'transparent' and a warning names what cannot be picked; an explicit
    ``classes`` option is left alone."""
    from torm.methods.builtin_methods import prompt_scenario_targets, segmenter_for
    from torm.pipeline import SegmentationSettings, TrialConfig

    cfg = TrialConfig(scenario="rw5", segmentation=SegmentationSettings("learned", options={"model": "v4"}))
    seg = segmenter_for(cfg)
    assert seg.config.classes == ("transparent",)
    assert "cannot be prompted for opaque" in caplog.text
    assert prompt_scenario_targets(seg, "a_recorded_capture") == ("transparent",)


@pytest.mark.parametrize("kw, field", [({"gap": (1.0, 0.5)}, "gap"), ({"gap": (-0.1, 1.0)}, "gap"),
                                       ({"gap": (1.0, 40.0)}, "gap"), ({"gap": (1.0,)}, "gap"),
                                       ({"occ_paper": 46.0}, "occ_paper"), ({"occ_paper": -0.1}, "occ_paper")])
def test_a_bad_gap_or_paper_occ_is_refused_by_name(kw, field):
    with pytest.raises(ConfigError, match=f"scenario 'x': {field}"):
        Scenario(name="x", objects=("ball", "cube"), **kw)


def test_a_scenario_gap_replaces_its_spacing_class_rule():
    sc = Scenario(name="x", objects=("ball", "cube"), spacing="dense", gap=(1.5, 2.0))
    base = PlacementConfig()
    rules = scenario_rules(sc, base)
    assert rules.dense.lo == 1.5 and rules.dense.hi == 2.0 and rules.dense.hi_floor == base.dense.hi_floor
    assert rules.moderate == base.moderate and scenario_rules(get_scenario("rw3"), base) == base
    w = 0.5 * (get_object("ball").width + get_object("cube").width)
    for seed in range(5):
        poses = place_objects(sc, seed)
        gap = pairwise_gaps([get_object("ball"), get_object("cube")], poses)[0, 1]
        assert 1.5 * w - 1e-9 <= gap <= 2.0 * w + 1e-9  # two objects: the second sits within hi of the first


def test_rw_scenarios_state_the_papers_occlusion():
    occ = {n: get_scenario(n).occ_paper for n in list_scenarios("rw")}
    assert occ == {"rw1": 0.0, "rw2": 0.0, "rw3": 0.10, "rw4": 0.16, "rw5": 0.28, "rw6": 0.02, "rw7": 0.46,
                   "rw8": 0.42}  # Table III
