"""Antipodal, collision-aware grasp planner on ground-truth primitives (cylinder, box, ball)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import trimesh
import yaml

from torm.errors import ConfigError, GraspError
from torm.grasp import (
    BOX_NAMES,
    AntipodalGraspPlanner,
    GraspPlanner,
    GraspPlannerConfig,
    GripperGeometry,
    grasps_to_graspnet,
    load_graspnet,
    plan_grasps,
    save_graspnet,
)
from torm.types import ObjectPointCloud, TriMesh

GRIPPER = GripperGeometry()
MU = 0.5
COS_CONE = 1.0 / np.sqrt(1.0 + MU**2)


def cylinder(x: float, y: float, r: float = 0.03, h: float = 0.10) -> trimesh.Trimesh:
    m = trimesh.creation.cylinder(radius=r, height=h, sections=64)
    m.apply_translation([x, y, h / 2])
    return m


def box(x: float, y: float, size=(0.05, 0.05, 0.05)) -> trimesh.Trimesh:
    m = trimesh.creation.box(size)
    m.apply_translation([x, y, size[2] / 2])
    return m


def ball(x: float, y: float, r: float = 0.03) -> trimesh.Trimesh:
    m = trimesh.creation.icosphere(subdivisions=3, radius=r)
    m.apply_translation([x, y, r])
    return m


def sample(mesh: trimesh.Trimesh, n: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    pts, fi = trimesh.sample.sample_surface(mesh, n, seed=seed)
    return np.asarray(pts), mesh.face_normals[fi].copy()


def clouds(meshes: list[trimesh.Trimesh], n: int = 2048) -> tuple[list[ObjectPointCloud], list[TriMesh]]:
    pcs, tms = [], []
    for k, m in enumerate(meshes):
        p, nrm = sample(m, n, seed=100 + k)
        pcs.append(ObjectPointCloud(p, nrm, k))
        tms.append(TriMesh(m.vertices, m.faces))
    return pcs, tms


def world_boxes(g, names=BOX_NAMES):
    """[(name, R_world_box, centre_world, half)] of a grasp's boxes."""
    T = g.T_world_grasp
    out = []
    for name, (Tb, h) in zip(names, GRIPPER.boxes(g.width, g.depth), strict=False):
        out.append((name, T[:3, :3], T[:3, :3] @ Tb[:3, 3] + T[:3, 3], h))
    return out


def count_inside(points: np.ndarray, R: np.ndarray, c: np.ndarray, h: np.ndarray, shrink: float = 0.0) -> int:
    local = (points - c) @ R
    return int(np.all(np.abs(local) <= h - shrink, axis=1).sum())


def box_min_z(R: np.ndarray, c: np.ndarray, h: np.ndarray) -> float:
    corners = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)]) * h
    return float((corners @ R.T + c)[:, 2].min())


def check_grasp_on_object(g, mesh: trimesh.Trimesh, dense_pts: np.ndarray, dense_nrm: np.ndarray) -> None:
    T = g.T_world_grasp
    R = T[:3, :3]
    # right-handed GraspNet frame: x approach, y closing, z = x cross y
    assert np.allclose(R.T @ R, np.eye(3), atol=1e-6) and np.linalg.det(R) == pytest.approx(1.0, abs=1e-6)
    assert np.allclose(np.cross(R[:, 0], R[:, 1]), R[:, 2], atol=1e-6)
    # width within the stroke and at least the object's true width between the pads along y
    assert GRIPPER.min_opening <= g.width <= GRIPPER.max_opening + 1e-9
    local = (dense_pts - T[:3, 3]) @ R
    slab = (local[:, 0] >= g.depth - GRIPPER.pad_length) & (local[:, 0] <= g.depth) & \
        (np.abs(local[:, 2]) <= GRIPPER.pad_width / 2)
    assert slab.sum() > 10, "the pads must cover part of the object"
    assert g.width >= np.ptp(local[slab, 1]) - 1e-4
    # antipodal: surface points on the closing line, one on each side, normals in the friction cone
    line = np.linalg.norm(local[:, [0, 2]], axis=1) < 0.002
    assert line.sum() >= 2
    pos, neg = line & (local[:, 1] > 0), line & (local[:, 1] < 0)
    assert pos.any() and neg.any()
    ip = np.flatnonzero(pos)[np.argmax(local[pos, 1])]
    ineg = np.flatnonzero(neg)[np.argmin(local[neg, 1])]
    assert dense_nrm[ip] @ R[:, 1] >= COS_CONE - 0.05
    assert dense_nrm[ineg] @ R[:, 1] <= -(COS_CONE - 0.05)
    # clear of the table, fingers (and palm, sweep) do not penetrate the object
    for name, Rb, c, h in world_boxes(g):
        assert box_min_z(Rb, c, h) >= -1e-6, name
        assert count_inside(dense_pts, Rb, c, h, shrink=0.0005) == 0, name


OBJECTS = {
    "cylinder": lambda: cylinder(0.55, 0.0),
    "box": lambda: box(0.55, 0.0),
    "ball": lambda: ball(0.55, 0.0),
}


@pytest.mark.parametrize("use_meshes", [False, True], ids=["points", "mesh-raycast"])
@pytest.mark.parametrize("name", sorted(OBJECTS))
def test_single_object_grasps_are_antipodal_and_collision_free(name, use_meshes):
    mesh = OBJECTS[name]()
    pcs, tms = clouds([mesh])
    grasps = plan_grasps(pcs, tms if use_meshes else None, table_height=0.0, rng=1)
    assert len(grasps) == 1 and 1 <= len(grasps[0]) <= GraspPlannerConfig().top_k
    scores = [g.score for g in grasps[0]]
    assert scores == sorted(scores, reverse=True)
    dense_pts, dense_nrm = sample(mesh, 30000, seed=7)
    for g in grasps[0]:
        assert g.object_id == 0
        check_grasp_on_object(g, mesh, dense_pts, dense_nrm)
    best = grasps[0][0]
    assert best.T_world_grasp[2, 0] < -0.7, "a free-standing object should be grasped from above"


def test_object_wider_than_stroke_gets_no_grasp():
    pcs, tms = clouds([box(0.55, 0.0, (0.12, 0.12, 0.12))])
    assert plan_grasps(pcs, rng=0) == [[]]
    assert plan_grasps(pcs, tms, rng=0) == [[]]


def test_neighbour_in_the_fingers_way_changes_the_grasp():
    cyl = cylinder(0.55, 0.0)
    pcs, _ = clouds([cyl])
    best = plan_grasps(pcs, rng=3)[0][0]
    # a tall post where the best grasp's right finger would be
    T = best.T_world_grasp
    finger_local = [best.depth - GRIPPER.finger_length / 2, best.width / 2 + GRIPPER.finger_thickness / 2, 0.0]
    finger_c = T[:3, :3] @ np.array(finger_local) + T[:3, 3]
    post = box(finger_c[0], finger_c[1], (0.014, 0.014, 0.20))
    axis_dist = np.linalg.norm(finger_c[:2] - [0.55, 0.0])
    assert axis_dist - 0.007 * np.sqrt(2) > 0.03, "the post must not overlap the cylinder"
    pcs2, _ = clouds([cyl, post])
    grasps = plan_grasps(pcs2, rng=3)
    assert grasps[0], "the cylinder still has collision-free grasps"
    new = grasps[0][0]
    moved = np.linalg.norm(new.T_world_grasp[:3, 3] - T[:3, 3]) > 0.005
    from torm.grasp.score import rotation_distance

    turned = rotation_distance(T[:3, :3], new.T_world_grasp[None, :3, :3])[0] > np.radians(10)
    assert moved or turned
    post_pts, _ = sample(post, 30000, seed=9)
    for g in grasps[0]:
        for name, Rb, c, h in world_boxes(g):
            assert count_inside(post_pts, Rb, c, h) == 0, name
    # the old best grasp really collides with the post
    assert sum(count_inside(post_pts, Rb, c, h) for _, Rb, c, h in world_boxes(best)) > 0


def test_batched_planning_handles_each_object_independently():
    meshes = [cylinder(0.40, -0.15), box(0.40, 0.15), ball(0.70, -0.15), box(0.70, 0.15, (0.12, 0.12, 0.12)),
              cylinder(0.55, 0.0, r=0.025, h=0.08)]
    pcs, tms = clouds(meshes)
    planner = AntipodalGraspPlanner(rng=5)
    assert isinstance(planner, GraspPlanner)
    grasps = planner.plan(pcs, tms, table_height=0.0)
    assert len(grasps) == 5
    assert grasps[3] == []  # 12 cm box: wider than the stroke
    for k in (0, 1, 2, 4):
        assert grasps[k], f"object {k} should be graspable"
        lo, hi = meshes[k].bounds
        for g in grasps[k]:
            assert g.object_id == k
            assert np.all(g.T_world_grasp[:3, 3] >= lo - 1e-6) and np.all(g.T_world_grasp[:3, 3] <= hi + 1e-6)
        # same object alone: equally good best grasp (far neighbours do not matter)
        alone = plan_grasps([ObjectPointCloud(pcs[k].points_nx3, pcs[k].normals_nx3, k)], [tms[k]], rng=5)[0]
        assert alone and abs(alone[0].score - grasps[k][0].score) < 0.05
    assert planner.last_stats["grasps"] == [len(g) for g in grasps]


def test_planning_is_deterministic_for_a_seed():
    pcs, _ = clouds([cylinder(0.5, 0.0), ball(0.65, 0.1)])
    a = grasps_to_graspnet([g for gs in plan_grasps(pcs, rng=11) for g in gs])
    b = grasps_to_graspnet([g for gs in plan_grasps(pcs, rng=11) for g in gs])
    assert np.array_equal(a, b)


def test_table_height_is_respected():
    mesh = box(0.55, 0.0)
    mesh.apply_translation([0, 0, 0.3])
    pcs, _ = clouds([mesh])
    for g in plan_grasps(pcs, table_height=0.3, rng=0)[0]:
        for name, Rb, c, h in world_boxes(g):
            assert box_min_z(Rb, c, h) >= 0.3 - 1e-6, name


def test_graspnet_export_round_trip(tmp_path):
    pcs, _ = clouds([ball(0.55, 0.0), box(0.7, 0.1)])
    grasps = [g for gs in plan_grasps(pcs, rng=2) for g in gs]
    arr = grasps_to_graspnet(grasps)
    assert arr.shape == (len(grasps), 17)
    g0 = grasps[0]
    assert arr[0, 0] == g0.score and arr[0, 1] == g0.width and arr[0, 2] == g0.height and arr[0, 3] == g0.depth
    assert np.array_equal(arr[0, 4:13], g0.T_world_grasp[:3, :3].reshape(-1))
    assert np.array_equal(arr[0, 13:16], g0.T_world_grasp[:3, 3]) and arr[0, 16] == g0.object_id
    back = load_graspnet(save_graspnet(tmp_path / "grasps.npy", grasps))
    for a, b in zip(grasps, back, strict=True):
        assert np.allclose(a.T_world_grasp, b.T_world_grasp) and a.width == b.width and a.object_id == b.object_id
    with pytest.raises(GraspError):
        save_graspnet(tmp_path / "grasps.txt", grasps)
    assert grasps_to_graspnet([]).shape == (0, 17)


def test_gripper_geometry_boxes_and_config():
    g = GripperGeometry.from_mapping({"max_opening": 0.085, "pad_length": 0.0375, "pad_width": 0.022})
    assert g == GripperGeometry()
    with pytest.raises(ConfigError, match="unknown key"):
        GripperGeometry.from_mapping({"stroke": 0.085})
    with pytest.raises(ConfigError):
        GripperGeometry(palm_width=-0.05)
    with pytest.raises(ConfigError):
        GripperGeometry(min_opening=0.09)
    boxes = g.boxes(0.06, depth=0.02)
    assert len(boxes) == len(BOX_NAMES) == 6 and len(g.boxes(0.06, include_sweep=False)) == 3
    (Tl, hl), (Tr, hr), (Tp, hp) = boxes[:3]
    # inner finger faces at +-width/2, fingertips at x = depth, palm behind the fingers
    assert Tl[1, 3] + hl[1] == pytest.approx(-0.03) and Tr[1, 3] - hr[1] == pytest.approx(0.03)
    assert Tl[0, 3] + hl[0] == pytest.approx(0.02) and hl[2] == pytest.approx(g.pad_width / 2)
    assert Tp[0, 3] + hp[0] == pytest.approx(0.02 - g.finger_length)
    # sweeps contain their boxes and reach back by the approach distance
    for i, j in ((0, 3), (1, 4), (2, 5)):
        (Ti, hi), (Tj, hj) = boxes[i], boxes[j]
        assert np.all(Tj[:3, 3] - hj <= Ti[:3, 3] - hi + 1e-12) and np.all(Tj[:3, 3] + hj >= Ti[:3, 3] + hi - 1e-12)
        assert (Ti[0, 3] - hi[0]) - (Tj[0, 3] - hj[0]) == pytest.approx(g.approach_distance)


def test_planner_config_loads_from_a_mapping_with_overrides():
    from torm.config import from_dict

    cfg = from_dict(GraspPlannerConfig, {"top_k": 3, "depths": [0.01, 0.02]}, overrides=["friction_coef=0.3"])
    assert cfg.top_k == 3 and cfg.depths == (0.01, 0.02) and cfg.friction_coef == 0.3
    with pytest.raises(ConfigError, match="unknown key"):
        from_dict(GraspPlannerConfig, {"topk": 3})


def test_invalid_inputs_raise_clear_errors():
    with pytest.raises(ConfigError):
        GraspPlannerConfig(n_samples=0)
    with pytest.raises(ConfigError):
        GraspPlannerConfig(depths=())
    with pytest.raises(ConfigError, match="finger_length"):
        AntipodalGraspPlanner(config=GraspPlannerConfig(depths=(0.2,)))
    a, _ = clouds([ball(0.5, 0.0)], n=100)
    b, _ = clouds([ball(0.6, 0.0)], n=120)
    with pytest.raises(GraspError, match="point counts"):
        plan_grasps(a + b)
    assert plan_grasps([]) == []


def test_flat_object_is_grasped_with_the_fingertips_above_the_table():
    puck = cylinder(0.55, 0.0, r=0.03, h=0.015)
    pcs, tms = clouds([puck])
    grasps = plan_grasps(pcs, tms, rng=4)[0]
    assert grasps, "a 15 mm puck is graspable from above with the fingertips"
    for g in grasps:
        assert g.depth <= 0.0075 - GraspPlannerConfig().table_clearance + 1e-9
        for name, Rb, c, h in world_boxes(g):
            assert box_min_z(Rb, c, h) >= GraspPlannerConfig().table_clearance - 1e-6, name


@pytest.mark.parametrize("use_meshes", [False, True], ids=["points", "mesh-raycast"])
def test_friction_cone_decides_triangular_prism(use_meshes):
    # equilateral prism: opposite contacts lie on faces 120 deg apart, 30 deg off any closing axis
    prism = trimesh.creation.cylinder(radius=0.03, height=0.10, sections=3)
    prism.apply_translation([0.55, 0.0, 0.05])
    pcs, tms = clouds([prism])
    meshes = tms if use_meshes else None
    assert plan_grasps(pcs, meshes, config=GraspPlannerConfig(friction_coef=0.5), rng=0) == [[]]  # atan 26.6 deg
    grasps = plan_grasps(pcs, meshes, config=GraspPlannerConfig(friction_coef=0.7), rng=0)[0]  # atan 35 deg
    assert grasps
    for g in grasps:
        y = g.T_world_grasp[:3, 1]
        assert abs(y[2]) < 0.05  # closing axis horizontal, between two side faces


def test_gripper_geometry_from_the_robot_config_schema():
    section = {"approach_axis": "z", "closing_axis": "y", "pad_size": [0.022, 0.006, 0.0375],
               "finger_size": [0.022, 0.012, 0.06625], "finger_center_approach": -0.014375,
               "palm_size": [0.075, 0.09, 0.095], "palm_center_approach": -0.095, "max_opening": 0.085,
               "finger_depth": 0.06625, "tip_approach": 0.01875}
    g = GripperGeometry.from_robot_config(section)
    assert g == GripperGeometry()  # the defaults are the simulated 2F-85
    with pytest.raises(ConfigError, match="unknown key"):
        GripperGeometry.from_robot_config({**section, "colour": "grey"})
    with pytest.raises(ConfigError, match="palm"):
        GripperGeometry.from_robot_config({**section, "palm_center_approach": -0.02})
    robot_yaml = Path(__file__).resolve().parents[1] / "sim" / "robots" / "inovo_2f85" / "robot.yaml"
    if robot_yaml.is_file():  # the simulated robot's own config (read as data; torm never imports sim/)
        geometry = yaml.safe_load(robot_yaml.read_text())["gripper"]["geometry"]
        assert GripperGeometry.from_robot_config(geometry) == GripperGeometry()


@pytest.mark.parametrize("use_meshes", [False, True], ids=["points", "mesh-raycast"])
def test_hollow_cup_is_grasped_across_its_walls_only_with_far_contacts(use_meshes):
    cup = trimesh.creation.annulus(r_min=0.031, r_max=0.035, height=0.08, sections=64)  # 4 mm walls, open ends
    cup.apply_translation([0.55, 0.0, 0.04])
    pcs, tms = clouds([cup], n=4096)
    meshes = tms if use_meshes else None
    dense_pts, dense_nrm = sample(cup, 40000, seed=8)
    across = plan_grasps(pcs, meshes, config=GraspPlannerConfig(top_k=20), rng=0)[0]
    assert any(g.width > 0.07 for g in across), "some grasp spans the whole cup (outer wall to outer wall)"
    for g in across:  # rim pinches and across-the-cup grasps alike keep the fingers out of the walls
        for name, Rb, c, h in world_boxes(g):
            assert count_inside(dense_pts, Rb, c, h, shrink=0.0005) == 0, name
    if use_meshes:  # exact rays always stop at the near wall's inner face (a sparse cloud can miss it)
        near_only = plan_grasps(pcs, meshes, config=GraspPlannerConfig(top_k=20, far_contacts=False), rng=0)[0]
        assert near_only and all(g.width < 0.03 for g in near_only), "without far contacts only walls are pinched"


def test_tall_cylinder_gets_side_grasps_at_several_heights():
    pcs, tms = clouds([cylinder(0.55, 0.0)])
    cfg = GraspPlannerConfig(top_k=40, w_approach=0.0, w_centre=0.0)  # rank by grasp quality alone
    grasps = plan_grasps(pcs, tms, config=cfg, rng=0)[0]
    side = [g for g in grasps if abs(g.T_world_grasp[2, 0]) < 0.2]  # approach within ~12 deg of horizontal
    heights = np.array([g.T_world_grasp[2, 3] for g in side])
    assert len(side) >= 3 and np.ptp(heights) > 0.03, heights
    # side grasps keep the palm (75 mm tall) above the table: centre at least palm_height / 2 up
    assert heights.min() >= GRIPPER.palm_height / 2 * (1 - 0.2) - 1e-6


@pytest.mark.parametrize("use_meshes", [True, False])
def test_frustum_faces_leaning_inwards_are_grasped_level(use_meshes):
    # Square frustum (base 60 mm, top 30 mm, 60 mm tall): opposite faces lean 14 deg towards each other.
    # A ray cast along -n1 meets the opposite face 11 mm lower; the bisector re-cast must find the level
    # contact so the pair passes the friction cone of mu = 0.5 (26.6 deg).
    b, t, h = 0.03, 0.015, 0.06
    corners = [[sx * b, sy * b, 0] for sx in (-1, 1) for sy in (-1, 1)] + [
        [sx * t, sy * t, h] for sx in (-1, 1) for sy in (-1, 1)]
    frustum = trimesh.convex.convex_hull(np.array(corners))
    frustum.apply_translation([0.55, 0.0, 0.0])
    pcs, tms = clouds([frustum])
    grasps = plan_grasps(pcs, tms if use_meshes else None, config=GraspPlannerConfig(friction_coef=0.5), rng=0)[0]
    assert grasps
    for g in grasps:
        assert abs(g.T_world_grasp[2, 1]) < 0.1  # a level closing axis between two opposite faces
        assert g.width <= 0.085
