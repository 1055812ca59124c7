"""torm/TormPick-v0: gymnasium's checker, determinism, vector envs, bad actions, and a scripted pick on rw1 that
earns the success reward by the paper's 25 cm lift test."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

import torm
from torm.env.cameras import SCENE_FOVY_DEG, scene_pose
from torm.env.errors import InvalidActionError
from torm.env.pick_env import TormPickEnv
from torm.errors import TormError
from torm.execution.errors import PhysicsError

gym.register_envs(torm)  # `import torm` registered them; this documents the dependency (Gymnasium-Robotics style)


def test_registered_env_passes_the_gymnasium_checker():
    assert gym.spec("torm/TormPick-v0").max_episode_steps == 200
    assert gym.spec("torm/TormGraspSelect-v0").max_episode_steps == 1
    env = gym.make("torm/TormPick-v0", image_size=(64, 64), cameras=("overview", "wrist"), render_mode="rgb_array")
    try:
        check_env(env.unwrapped, skip_close_check=True)
        obs, info = env.reset(seed=3)
        assert set(obs) == {"joint_pos", "joint_vel", "tcp_pose", "gripper_width", "overview_rgb", "overview_depth",
                            "wrist_rgb", "wrist_depth"}
        assert obs["overview_rgb"].shape == (64, 64, 3) and obs["overview_rgb"].dtype == np.uint8
        assert obs["wrist_depth"].shape == (64, 64) and obs["wrist_depth"].dtype == np.float32
        # the overview camera sees the table (~0.5-1.5 m away) and the wrist camera looks down onto it
        assert 0.3 < float(np.median(obs["overview_depth"])) < 2.0
        assert 0.05 < float(np.median(obs["wrist_depth"])) < 0.6
        assert obs["overview_rgb"].std() > 5.0  # not a blank image
        frame = env.render()
        assert frame.shape == (240, 320, 3) and frame.dtype == np.uint8
        # home pose: TCP at (0.5, 0, 0.35) pointing down (180 deg about y: quaternion wxyz = (0, 0, +-1, 0))
        assert np.allclose(obs["tcp_pose"][:3], [0.5, 0.0, 0.35], atol=2e-3)
        assert abs(abs(obs["tcp_pose"][5]) - 1.0) < 1e-3
        assert info["layout_seed"] == 3
        assert env.action_space.shape == (7,)
        assert np.allclose(env.action_space.high, 1.0) and np.allclose(env.action_space.low, -1.0)
        assert np.allclose(env.unwrapped.action_scale, [0.02, 0.02, 0.02, 0.1, 0.1, 0.1, 1.0])
    finally:
        env.close()


def _rollout(env: TormPickEnv, seed: int, actions: np.ndarray) -> tuple[list[dict], list[float]]:
    obs, _ = env.reset(seed=seed)
    out, rewards = [obs], []
    for a in actions:
        obs, r, *_ = env.step(a)
        out.append(obs)
        rewards.append(r)
    return out, rewards


def test_same_seed_same_layout_and_rollout():
    rng = np.random.default_rng(7)
    lo = np.array([-0.02] * 3 + [-0.1] * 3 + [-1.0])
    actions = (rng.uniform(-1, 1, (8, 7)) * -lo).astype(np.float32)
    actions[:4, 2] = -0.02  # go down towards the table so the rollout does something
    kw = dict(cameras=("overview",), image_size=(32, 32), reward_shaping=True, privileged_state=True, action_mode="raw")
    a, b = TormPickEnv(**kw), TormPickEnv(**kw)
    try:
        obs_a, rew_a = _rollout(a, 11, actions)
        obs_b, rew_b = _rollout(b, 11, actions)
        obs_a2, rew_a2 = _rollout(a, 11, actions)  # the same env again, after stepping it
        assert rew_a == rew_b == rew_a2
        for x, y, z in zip(obs_a, obs_b, obs_a2, strict=True):
            for k in x:
                if k.endswith("_depth"):
                    # Mesa's software rasteriser can differ by float rounding (~1e-5 m) between GL contexts;
                    # physics and every other observation must be bit-identical.
                    assert np.allclose(x[k], y[k], atol=1e-4) and np.allclose(x[k], z[k], atol=1e-4), k
                else:
                    assert np.array_equal(x[k], y[k]) and np.array_equal(x[k], z[k]), k
        assert not np.array_equal(obs_a[0]["tcp_pose"], obs_a[-1]["tcp_pose"])  # the arm moved
        # another seed gives another layout
        other, _ = a.reset(seed=12)
        assert not np.allclose(other["object_pos"], obs_a[0]["object_pos"])
    finally:
        a.close()
        b.close()


def test_sync_vector_env_steps():
    envs = gym.vector.SyncVectorEnv([lambda: TormPickEnv(cameras=("overview",), image_size=(32, 32))
                                     for _ in range(2)])
    try:
        obs, info = envs.reset(seed=[0, 1])
        assert obs["overview_rgb"].shape == (2, 32, 32, 3) and obs["joint_pos"].shape == (2, 6)
        envs.action_space.seed(0)
        for _ in range(3):
            obs, rew, term, trunc, info = envs.step(envs.action_space.sample())
        assert rew.shape == (2,) and term.shape == (2,) and obs["tcp_pose"].shape == (2, 7)
        assert list(info["layout_seed"]) == [0, 1]
    finally:
        envs.close()


def test_out_of_bounds_actions_are_rejected_with_the_bounds():
    env = TormPickEnv(cameras=(), action_mode="raw", out_of_bounds="raise")
    env.reset(seed=0)
    try:
        with pytest.raises(InvalidActionError, match=r"outside \[-0.02, 0.02\].*low=\[") as exc:
            env.step(np.array([0.05, 0, 0, 0, 0, 0, 0], np.float32))
        assert isinstance(exc.value, (TormError, ValueError)) and "dx" in str(exc.value)
        with pytest.raises(InvalidActionError, match="grip"):
            env.step(np.array([0, 0, 0, 0, 0, 0, 1.5]))
        with pytest.raises(InvalidActionError, match="shape"):
            env.step(np.zeros(6))
        with pytest.raises(InvalidActionError, match="not finite"):
            env.step(np.array([np.nan, 0, 0, 0, 0, 0, 0]))
        obs, *_ = env.step(np.zeros(7, np.float64))  # float64 inside the bounds is fine
        assert np.isfinite(obs["tcp_pose"]).all()
    finally:
        env.close()


def test_normalised_actions_map_to_the_physical_limits_and_clip():
    env = TormPickEnv(cameras=())
    try:
        env.reset(seed=0)
        T0 = env._T_target.copy()
        _, _, _, _, info = env.step(np.array([1.0, -0.5, 0, 0, 0, 0, -1], np.float32))
        assert not info["action_clipped"]
        assert np.allclose(env._T_target[:3, 3] - T0[:3, 3], [0.02, -0.01, 0.0], atol=1e-9)  # max_pos_step 0.02 m
        T1 = env._T_target.copy()
        _, _, _, _, info = env.step(np.array([3.0, 0, 0, 0, 0, 0, -1], np.float32))  # clipped to +1
        assert info["action_clipped"]
        assert np.allclose(env._T_target[:3, 3] - T1[:3, 3], [0.02, 0.0, 0.0], atol=1e-9)
        T2 = env._T_target.copy()
        env.step(np.array([0, 0, 0, 0, 0, 1.0, -1], np.float32))  # yaw by max_rot_step = 0.1 rad
        R = env._T_target[:3, :3] @ T2[:3, :3].T
        assert np.isclose(np.arctan2(R[1, 0], R[0, 0]), 0.1, atol=1e-9)
        with pytest.raises(InvalidActionError, match="not finite"):
            env.step(np.array([np.inf, 0, 0, 0, 0, 0, 0]))
    finally:
        env.close()
    strict = TormPickEnv(cameras=(), out_of_bounds="raise")
    try:
        strict.reset(seed=0)
        with pytest.raises(InvalidActionError, match=r"outside \[-1, 1\].*normalised"):
            strict.step(np.array([1.5, 0, 0, 0, 0, 0, 0], np.float32))
    finally:
        strict.close()


def test_render_camera_shows_the_arm_and_the_workspace():
    """Every robot geom at the home pose and every workspace corner project inside the render image."""
    env = TormPickEnv(cameras=())
    try:
        env.reset(seed=0)
        m, d = env.world.model, env.world.data
        robot = d.geom_xpos[m.geom_group == 1]  # robot visual geoms (group 1), world frame (m)
    finally:
        env.close()
    assert len(robot) > 5
    T = scene_pose()
    H, W = 240, 320
    f = 0.5 * H / np.tan(np.radians(SCENE_FOVY_DEG) / 2)
    pts = np.array([[x, y, z] for x in (0.33, 0.77) for y in (-0.22, 0.22) for z in (0.0, 0.2)], float)
    pts = np.r_[robot, pts]
    p_cam = (np.linalg.inv(T) @ np.c_[pts, np.ones(len(pts))].T)[:3].T
    assert np.all(p_cam[:, 2] > 0.3)
    u = f * p_cam[:, 0] / p_cam[:, 2] + W / 2
    v = f * p_cam[:, 1] / p_cam[:, 2] + H / 2
    assert np.all((u > 0) & (u < W) & (v > 0) & (v < H)), np.c_[u, v]


def test_clipping_rejection_and_physics_error_flags(monkeypatch):
    env = TormPickEnv(cameras=(), action_mode="raw", tcp_box=((0.15, -0.5, 0.30), (2.0, 0.5, 0.7)))
    try:
        env.reset(seed=0)
        _, _, _, _, info = env.step(np.array([0, 0, -0.02, 0, 0, 0, -1], np.float32))  # 0.35 -> 0.33: inside
        assert not info["clipped"] and not info["rejected"]
        for _ in range(3):
            obs, _, _, _, info = env.step(np.array([0, 0, -0.02, 0, 0, 0, -1], np.float32))
        assert info["clipped"] and abs(obs["tcp_pose"][2] - 0.30) < 3e-3  # held at the box floor
        reached = []
        for _ in range(60):  # walk out along +x until the arm cannot follow
            obs, _, _, _, info = env.step(np.array([0.02, 0, 0, 0, 0, 0, -1], np.float32))
            reached.append(obs["tcp_pose"][0])
            if info["rejected"]:
                break
        assert info["rejected"] and info["rejected_reason"]
        x_stop = obs["tcp_pose"][0]
        obs, _, _, _, info = env.step(np.array([0.02, 0, 0, 0, 0, 0, -1], np.float32))
        assert info["rejected"] and abs(obs["tcp_pose"][0] - x_stop) < 2e-3  # the arm holds its last target

        def boom(seconds):
            raise PhysicsError("simulation state became NaN/inf (test)")

        monkeypatch.setattr(env.backend.clock, "sleep", boom)
        obs, r, term, trunc, info = env.step(np.zeros(7, np.float32))
        assert term and not trunc and r == 0.0 and "NaN" in info["physics_error"]
        assert env.observation_space.contains(obs)
    finally:
        env.close()


def test_truncation_at_max_episode_steps():
    env = TormPickEnv(cameras=(), max_episode_steps=3)
    try:
        env.reset(seed=0)
        flags = [env.step(np.zeros(7, np.float32))[2:4] for _ in range(3)]
        assert flags == [(False, False), (False, False), (False, True)]
    finally:
        env.close()


def _scripted_pick(env: TormPickEnv, seed: int) -> tuple[list[float], list[dict], int]:
    """Above the object, descend to 60 % of its height (10 cm glass cylinder), close, lift (then move sideways)."""
    obs, _ = env.reset(seed=seed)
    obj = obs["object_pos"].copy()  # bounding-box centre of the cylinder (5 cm above the table)
    rewards, infos, phase, closing, n = [], [], 0, 0, 0

    def towards(target, grip):
        d = np.clip(np.asarray(target) - obs["tcp_pose"][:3], -0.02, 0.02)
        return np.array([*d, 0, 0, 0, grip], np.float32)

    while n < 120:
        p = obs["tcp_pose"][:3]
        if phase == 0:
            a = towards([obj[0], obj[1], 0.15], -1.0)
            phase += np.linalg.norm(p - [obj[0], obj[1], 0.15]) < 0.003
        elif phase == 1:
            a = towards([obj[0], obj[1], obj[2] + 0.01], -1.0)
            phase += np.linalg.norm(p - [obj[0], obj[1], obj[2] + 0.01]) < 0.003
        elif phase == 2:
            a, closing = towards(p, 1.0), closing + 1
            phase += closing >= 6
        elif phase == 3:
            a = towards(p + [0, 0, 0.02], 1.0)
            phase += p[2] > 0.33
        else:
            a = towards(p + [0, 0.02, 0], 1.0)
        obs, r, term, trunc, info = env.step(a)
        n += 1
        rewards.append(r)
        infos.append(info)
        if term or trunc:
            break
    return rewards, infos, n


def test_scripted_pick_earns_the_success_reward_on_rw1():
    env = TormPickEnv(scenario="rw1", cameras=(), privileged_state=True, reward_shaping=True, action_mode="raw")
    try:
        rewards, infos, n = _scripted_pick(env, seed=0)
        last = infos[-1]
        assert last["is_success"] and last["held"] and last["pad_contacts"] == 2
        assert last["lift_m"] >= 0.24 and rewards[-1] > 1.0  # sparse 1.0 + shaping
        assert not any(i["is_success"] for i in infos[:-1])
        # shaping: while held, the reward grows with the lift height
        held = [(i["lift_m"], r) for i, r in zip(infos, rewards, strict=True) if i["held"] and not i["is_success"]]
        assert len(held) >= 5
        lifts, rs = np.array(held).T
        assert np.all(np.diff(lifts[lifts > 0.01]) > 0) and np.all(np.diff(rs[lifts > 0.01]) > 0)
        # without shaping the reward is sparse: 0 until the success step
        env2 = TormPickEnv(scenario="rw1", cameras=(), privileged_state=True, action_mode="raw")
        rewards2, infos2, _ = _scripted_pick(env2, seed=0)
        env2.close()
        assert rewards2[-1] == 1.0 and set(rewards2[:-1]) == {0.0} and infos2[-1]["is_success"]
        # stage two: lift then translate 20 cm
        env3 = TormPickEnv(scenario="rw1", cameras=(), privileged_state=True, success="lift_translate",
                           action_mode="raw")
        rewards3, infos3, _ = _scripted_pick(env3, seed=0)
        env3.close()
        assert infos3[-1]["is_success"] and infos3[-1]["translation_m"] >= 0.18 and rewards3[-1] == 1.0
        assert any(i["lifted"] and not i["is_success"] for i in infos3)  # lifted first, success later
    finally:
        env.close()
