"""Rendering a dataset scene: RGB + the simulator's instance masks of the same cameras.

``mujoco``  the MuJoCo rasteriser (glass = alpha blending), with the table colour / checker, glass tint and
            opacity, and the two lights randomised per scene (stand-in data; no refraction);
``pbr``     the physically based renderer of ``sim.render`` (refraction, Fresnel; its own randomised
            table textures and lights per layout seed). Needs the renderer of branch i10r.

``pbr_scalar`` the same renderer on Mitsuba's ``scalar_rgb`` variant (plain ``path`` integrator: speckled glass
            interiors): the look of machines without libLLVM, so that no one renderer's look is learned.

Both return ``rgb_vxhxwx3`` uint8 and ``mask_vxhxw`` int32 (0 background, k = object k) for cameras
``T_world_cam`` (V, 4, 4) in OpenCV axes (world frame, m) with per-view intrinsics ``K`` (V, 3, 3) at the
given size. A :class:`SceneLook` adds (PBR only) opaque distractors and room surfaces
(:mod:`~torm.segmentation.training.clutter`) and rescales the room and panel light; with clutter the masks
come from the renderer's exact first-hit id pass, so distractors occlude the glass behind them.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from torm.errors import ConfigError

RENDERERS = ("mujoco", "pbr")
#: renderers a dataset shard can be drawn with (``DataRecipe.renderer_weights``)
SHARD_RENDERERS = ("mujoco", "pbr", "pbr_scalar")


@dataclass(frozen=True)
class SceneLook:
    """What a PBR scene adds to the world: ``n_distractors`` opaque look-alikes, ``room`` surfaces, light scales
    (``env_scale`` room light, ``area_scale`` ceiling panels; 1 = as drawn from the layout seed) and the seed of
    the clutter draw."""

    n_distractors: int = 0
    room: bool = False
    env_scale: float = 1.0
    area_scale: float = 1.0
    clutter_seed: int = 0
    reference: bool = False  # the empty-workspace pass: independent render noise, some distractors removed
    drop_distractors: float = 0.0  # reference pass: probability that a distractor is not there
    mix: str = "v4"  # distractor kinds and materials (training/clutter.py MIXES)
    object_kinds: tuple[str, ...] = ()  # distractor kinds labelled as opaque objects (ids after the world's)

    @classmethod
    def draw(cls, recipe: Any, rng: np.random.Generator) -> SceneLook:
        """Draw a look from a :class:`~torm.segmentation.training.dataset.DataRecipe`'s v4 fractions."""
        lo, hi = recipe.distractors_per_scene
        n = int(rng.integers(lo, hi + 1)) if rng.random() < recipe.distractor_fraction else 0
        room = bool(rng.random() < recipe.room_fraction)
        env, area = 1.0, 1.0
        if rng.random() < recipe.lighting_fraction:  # dim room + strong panel, bright room + no panel, ...
            env, area = float(np.exp(rng.uniform(np.log(0.2), np.log(2.0)))), float(rng.choice([0.0, 0.3, 1.0, 4.0]))
        return cls(n, room, env, area, int(rng.integers(0, 2**31 - 1)), mix=recipe.distractor_mix,
                   object_kinds=tuple(getattr(recipe, "object_distractors", ())))

    @property
    def plain(self) -> bool:
        return self.n_distractors == 0 and not self.room and self.env_scale == 1.0 and self.area_scale == 1.0


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
    from sim.cameras.rig import CameraRigConfig, SimCameraRig

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
               rng: np.random.Generator, spp: int = 16, threads: int = 1, look: SceneLook | None = None,
               variant: str = "auto") -> tuple[np.ndarray, np.ndarray, dict[str, Any]]:
    """Physically based RGB (``sim.render``'s Mitsuba renderer, its default settings but ``spp`` and ``variant``;
    table texture and lights randomised from the world's layout seed) + instance masks of the same cameras: MuJoCo's
    (the masks the pipeline's captures carry) for a plain look, the renderer's id pass when ``look`` adds clutter.
    No render cache: dataset shards are the cache. Returns (rgb, mask, what the look drew)."""
    try:
        from sim.cameras.renderers import make_renderer
        from sim.render import PbrSettings, RenderCamera
    except ImportError as exc:
        raise ConfigError("renderer 'pbr' needs the physically based renderer in sim/render (branch i10r); "
                          f"it is not available here ({exc}); use renderer 'mujoco'") from exc
    from sim.cameras.rig import CameraRigConfig, SimCameraRig

    del rng  # the PBR scene is randomised from world.seed by the renderer itself
    look = look or SceneLook()
    cams = [RenderCamera(K, T, width, height) for T, K in zip(T_world_cam_vx4x4, K_vx3x3, strict=True)]
    r = make_renderer("pbr", world, PbrSettings(spp=spp, cache=False, threads=threads, variant=variant))
    info: dict[str, Any] = {"variant": variant}
    try:
        extra, extra_ids = None, None
        if look.n_distractors or look.room:
            import mitsuba as mi

            from sim.cameras.reference_pass import HIDDEN_GROUP
            from sim.render.cache import cache_root
            from sim.render.scene import RENDERED_GROUPS, describe_world
            from torm.segmentation.training.clutter import clutter_entries

            # hidden objects (a reference pass) still shape the clutter: the same draw as the scene's
            desc = describe_world(world, centre=r.centre, groups=(*RENDERED_GROUPS, HIDDEN_GROUP))
            extra, drawn = clutter_entries(desc, np.random.default_rng(look.clutter_seed), look.n_distractors,
                                           look.room, mi, cache_root() / "meshes", look.mix)
            if look.reference and look.drop_distractors > 0:
                drop = np.random.default_rng([look.clutter_seed, 7])
                for k in [k for k in extra if k.startswith("distractor_")]:
                    if drop.random() < look.drop_distractors:
                        del extra[k]
            info.update(drawn)
            if look.object_kinds and not look.reference:  # labelled distractors: ids after the world's objects
                labelled = [k for k, d in zip(_distractor_keys(extra), drawn["distractors"], strict=True)
                            if d["kind"] in look.object_kinds]
                extra_ids = {k: len(world.objects) + 1 + j for j, k in enumerate(labelled)}
                info["object_distractors"] = labelled
        if not look.plain:
            info.update(env_scale=look.env_scale, area_scale=look.area_scale)
        views = r.render(cams, rgb=True, instance=extra is not None and not look.reference, extra_emitters=extra,
                         env_scale=look.env_scale, area_scale=look.area_scale, noise_seed=int(look.reference),
                         extra_instances=extra_ids)
        rgb = np.stack([v.rgb for v in views])
        if look.reference:  # no masks of an empty workspace
            return rgb, np.zeros(rgb.shape[:3], np.int32), info
        if extra is not None:
            return rgb, np.stack([v.instance for v in views]).astype(np.int32), info
    finally:
        r.close()
    cfg = CameraRigConfig(n_views=len(cams), width=width, height=height, channels=("mask",))
    with SimCameraRig.from_world(world, cfg) as rig:
        masks = np.stack([rig.render_arrays(T, K, ("mask",))["mask"] for T, K in
                          zip(T_world_cam_vx4x4, K_vx3x3, strict=True)])
    return rgb, masks.astype(np.int32), info


def _distractor_keys(entries: dict[str, Any]) -> list[str]:
    """The ``distractor_<i>`` keys of clutter entries in draw order (one per drawn distractor)."""
    return sorted((k for k in entries if k.startswith("distractor_")), key=lambda k: int(k.rsplit("_", 1)[1]))


def render_scene(renderer: str, world: Any, T_world_cam_vx4x4: np.ndarray, K_vx3x3: np.ndarray, width: int,
                 height: int, rng: np.random.Generator, spp: int = 16, look: SceneLook | None = None
                 ) -> tuple[np.ndarray, np.ndarray, dict[str, Any]]:
    """Dispatch to :func:`render_mujoco` or :func:`render_pbr` (``pbr``: the machine's default variant,
    ``pbr_scalar``: ``scalar_rgb``); returns (rgb, mask, what the look drew)."""
    if renderer == "mujoco":
        rgb, mask = render_mujoco(world, T_world_cam_vx4x4, K_vx3x3, width, height, rng)
        return rgb, mask, {}
    if renderer in ("pbr", "pbr_scalar"):
        return render_pbr(world, T_world_cam_vx4x4, K_vx3x3, width, height, rng, spp, look=look,
                          variant="scalar_rgb" if renderer == "pbr_scalar" else "auto")
    raise ConfigError(f"unknown renderer {renderer!r}; valid choices: {', '.join(SHARD_RENDERERS)}")
