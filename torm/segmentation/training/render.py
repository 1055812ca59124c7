"""Rendering a dataset scene: RGB + the simulator's instance masks of the same cameras.

``mujoco``  the MuJoCo rasteriser (glass = alpha blending), with the table colour / checker, glass tint and
            opacity, and the two lights randomised per scene (stand-in data; no refraction);
``pbr``     the physically based renderer of ``sim.render`` (refraction, Fresnel; its own randomised
            table textures and lights per layout seed). Needs the renderer of branch i10r.

Both return ``rgb_vxhxwx3`` uint8 and ``mask_vxhxw`` int32 (0 background, k = object k) for cameras
``T_world_cam`` (V, 4, 4) in OpenCV axes (world frame, m) with per-view intrinsics ``K`` (V, 3, 3) at the
given size.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from torm.errors import ConfigError

RENDERERS = ("mujoco", "pbr")


def _randomise_mujoco(model: Any, rng: np.random.Generator) -> None:
    """Table / glass / light appearance drawn from ``rng`` (in place on the compiled model)."""
    import mujoco

    def mat(name: str) -> int:
        return mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_MATERIAL, name)

    tex = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_TEXTURE, "table_tex")
    if tex >= 0:  # recolour the checker: two random colours, random contrast
        adr, w, h = model.tex_adr[tex], model.tex_width[tex], model.tex_height[tex]
        nc = model.tex_nchannel[tex]
        data = model.tex_data[adr:adr + w * h * nc].reshape(h, w, nc)
        c1 = rng.uniform(0.1, 0.9, 3)
        c2 = np.clip(c1 * rng.uniform(0.6, 1.4, 3), 0, 1)
        cell = int(rng.choice([16, 32, 64, 128, 512]))
        yy, xx = np.mgrid[0:h, 0:w]
        chk = ((yy // cell + xx // cell) % 2).astype(bool)
        img = np.where(chk[..., None], c1, c2) * 255
        img += rng.normal(0, rng.uniform(0, 12), img.shape)
        data[..., :3] = np.clip(img, 0, 255).astype(np.uint8)
    g = mat("glass_mat")
    if g >= 0:
        tint = rng.uniform(0.75, 1.0, 3)
        model.mat_rgba[g] = [*tint, rng.uniform(0.15, 0.45)]
        model.mat_reflectance[g] = rng.uniform(0.0, 0.3)
    c = mat("ceramic_mat")
    if c >= 0:
        model.mat_rgba[c, :3] = rng.uniform(0.5, 1.0, 3)
    for i in range(model.nlight):
        model.light_diffuse[i] = rng.uniform(0.2, 0.7) * np.ones(3)
        d = np.array([rng.uniform(-0.6, 0.6), rng.uniform(-0.6, 0.6), -1.0])
        model.light_dir[i] = d / np.linalg.norm(d)
    model.vis.headlight.ambient[:] = rng.uniform(0.15, 0.4)
    model.vis.headlight.diffuse[:] = rng.uniform(0.2, 0.5)


def render_mujoco(world: Any, T_world_cam_vx4x4: np.ndarray, K_vx3x3: np.ndarray, width: int, height: int,
                  rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """MuJoCo RGB + instance masks of ``world`` at the given cameras, with randomised appearance."""
    from sim.camera_rig import CameraRigConfig, SimCameraRig

    _randomise_mujoco(world.model, rng)
    cfg = CameraRigConfig(n_views=len(T_world_cam_vx4x4), width=width, height=height, channels=("rgb", "mask"))
    rgbs, masks = [], []
    with SimCameraRig.from_world(world, cfg) as rig:
        for T, K_i in zip(T_world_cam_vx4x4, K_vx3x3, strict=True):
            out = rig.render_arrays(T, K_i, ("rgb", "mask"))
            rgbs.append(out["rgb"])
            masks.append(out["mask"])
    return np.stack(rgbs), np.stack(masks).astype(np.int32)


def render_pbr(world: Any, T_world_cam_vx4x4: np.ndarray, K_vx3x3: np.ndarray, width: int, height: int,
               rng: np.random.Generator, spp: int = 16, threads: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """Physically based RGB (``sim.render``'s Mitsuba renderer, its default settings but ``spp``; table texture and
    lights randomised from the world's layout seed) + MuJoCo's instance masks of the same cameras (the masks the
    pipeline's captures carry). No render cache: dataset shards are the cache."""
    try:
        from sim.render import PbrSettings, RenderCamera, make_renderer
    except ImportError as exc:
        raise ConfigError("renderer 'pbr' needs the physically based renderer in sim/render (branch i10r); "
                          f"it is not available here ({exc}); use renderer 'mujoco'") from exc
    from sim.camera_rig import CameraRigConfig, SimCameraRig

    del rng  # the PBR scene is randomised from world.seed by the renderer itself
    cams = [RenderCamera(K, T, width, height) for T, K in zip(T_world_cam_vx4x4, K_vx3x3, strict=True)]
    r = make_renderer("pbr", world, PbrSettings(spp=spp, cache=False, threads=threads))
    try:
        rgb = np.stack([v.rgb for v in r.render(cams, rgb=True, instance=False)])
    finally:
        r.close()
    cfg = CameraRigConfig(n_views=len(cams), width=width, height=height, channels=("mask",))
    with SimCameraRig.from_world(world, cfg) as rig:
        masks = np.stack([rig.render_arrays(T, K, ("mask",))["mask"] for T, K in
                          zip(T_world_cam_vx4x4, K_vx3x3, strict=True)])
    return rgb, masks.astype(np.int32)


def render_scene(renderer: str, world: Any, T_world_cam_vx4x4: np.ndarray, K_vx3x3: np.ndarray, width: int,
                 height: int, rng: np.random.Generator, spp: int = 16) -> tuple[np.ndarray, np.ndarray]:
    """Dispatch to :func:`render_mujoco` or :func:`render_pbr`."""
    if renderer == "mujoco":
        return render_mujoco(world, T_world_cam_vx4x4, K_vx3x3, width, height, rng)
    if renderer == "pbr":
        return render_pbr(world, T_world_cam_vx4x4, K_vx3x3, width, height, rng, spp)
    raise ConfigError(f"unknown renderer {renderer!r}; valid choices: {', '.join(RENDERERS)}")
