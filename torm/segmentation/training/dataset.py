"""Randomised multi-object scenes with ground-truth instance masks, written as resumable shards.

A :class:`DataRecipe` fixes everything: object pools, objects per scene, spacing, camera ranges, image size,
renderer and seeds. Shard ``i`` of split ``s`` is a pure function of (recipe, s, i), so a killed generation
resumes by skipping the shards already on disk (each is written to a temporary file and renamed).

Scenes are physically placed: :func:`sim.world.build_world` samples a layout (``spacing`` moderate or dense),
lets the objects settle and rejects layouts that tip, slide or interpenetrate. Object sets:

``train`` / ``val``   per object, a library shape outside :data:`~.shapes.HELD_OUT_SHAPES` (``library_fraction``)
                      or one of the procedural shapes; random camera poses on a band around the workspace
                      (radius ``radius_range`` m, elevation ``elevation_deg`` above the table, azimuth uniform,
                      look-at point jittered by ``target_jitter`` m) and ``views_per_scene`` views per scene,
                      each rendered as a ``width`` x ``height`` window of the full 640x360 camera around the
                      objects (:meth:`DataRecipe.crop_K`: objects keep the pipeline's pixel size);
``train_library``     optional extra training scenes drawn like ``train`` but with library shapes only (the lab
                      glassware and cups the benchmarks use); used for training together with ``train``;
``val_rig``           optional validation split shaped like deployment: library shapes only and the rig's full frames
                      (as ``test_layouts``, own seeds); what a training run or a post-processing search may select on
                      instead of ``val`` (random windows, half procedural shapes);
``test_layouts``      library shapes seen in training only, new layouts (seeds disjoint from train/val), the
                      capture rig's own Fibonacci layout (``test_views`` full 640x360 views, radius 0.5 m, 20-80 deg);
``test_shapes``       every scene holds at least one held-out shape (plus seen library shapes), same cameras;
``train_fixtures``    optional: library shapes standing in the lab suite's opaque fixtures, windows like ``train``; half
                      the scenes a ``tube_rack`` with 1-5 test tubes (and 0-3 objects on the table beside it), half a
                      ``tray`` holding some of its objects; used for training together with ``train``;
``test_fixtures``     optional: the same draw in the rig's full frames, own seeds (a held-out measure).

Test tubes: a free ``test_tube_*`` never settles upright (it rolls onto its side, a ~28 deg tilt the placement
rejects), so in every split but the fixture splits a scene drawing one is redrawn and holds no tube. The fixture
splits are where tubes, racks and trays (which the lab suite uses) enter the data; every other split is unchanged
by them.

Shard ``i`` of a split does not depend on the shard counts (``shards``), so a recipe that only asks for more shards
(or new splits) reuses the shards already rendered under the same folder.

A shard (``<root>/<split>/shard_00000.npz``) holds ``rgb`` (N, H, W, 3) uint8, ``mask`` (N, H, W) uint8
(0 background, k = object k), ``T_world_cam`` (N, 4, 4), ``K`` (N, 3, 3), ``scene`` (N,) index of the view's scene in
``meta`` and ``meta`` (JSON: per scene the seed, object names, materials, spacing).
"""

from __future__ import annotations

import dataclasses
import json
import logging
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from torm.errors import ConfigError, SceneError
from torm.geometry import look_at_cv

log = logging.getLogger(__name__)

SPLITS = ("train", "train_library", "train_fixtures", "val", "val_rig", "test_layouts", "test_shapes", "test_fixtures")
#: splits rendered as the rig's full frames (the others: windows of random cameras)
RIG_SPLITS = ("val_rig", "test_layouts", "test_shapes", "test_fixtures")
#: splits whose scenes hold library shapes only
LIBRARY_SPLITS = ("train_library", "val_rig", "test_layouts", "train_fixtures", "test_fixtures")
#: splits whose scenes stand objects in a fixture (a tube rack or a tray)
FIXTURE_SPLITS = ("train_fixtures", "test_fixtures")
#: extra training splits appended to ``train`` when the recipe renders them
EXTRA_TRAIN_SPLITS = ("train_library", "train_fixtures")
_SPLIT_SALT = {"train": 1, "val": 2, "test_layouts": 3, "test_shapes": 4, "train_library": 5, "val_rig": 6,
               "train_fixtures": 7, "test_fixtures": 8}
#: the tube rack's slots (``sim.scenes.fixtures``)
RACK_SLOTS = 5


@dataclass(frozen=True)
class DataRecipe:
    """How the dataset is generated (m, deg, px). Stored beside the shipped model as its data recipe."""

    renderer: str = "mujoco"
    spp: int = 16
    full_width: int = 640
    full_height: int = 360
    hfov_deg: float = 91.5
    width: int = 320
    height: int = 192
    crop_jitter_px: float = 60.0
    n_procedural: int = 60
    procedural_seed: int = 0
    library_fraction: float = 0.5
    objects_per_scene: tuple[int, int] = (1, 6)
    dense_fraction: float = 0.4
    views_per_scene: int = 4
    radius_range: tuple[float, float] = (0.38, 0.65)
    elevation_deg: tuple[float, float] = (15.0, 80.0)
    target_jitter: float = 0.06
    scenes_per_shard: int = 8
    shards: dict[str, int] = dataclasses.field(
        default_factory=lambda: {"train": 60, "val": 4, "test_layouts": 3, "test_shapes": 3})
    test_views: int = 12
    seed: int = 0
    # segmenter v4 (transfer to real photos); the defaults reproduce the v3 data exactly
    distractor_fraction: float = 0.0  # share of PBR scenes with opaque look-alikes (training/clutter.py)
    distractors_per_scene: tuple[int, int] = (1, 6)
    room_fraction: float = 0.0  # share of PBR scenes with a textured floor and walls
    lighting_fraction: float = 0.0  # share of PBR scenes with the room / panel light scaled (dim, key, back-lit)
    label_opaque: bool = True  # False: opaque objects are background in the masks (only glass is labelled)
    renderer_weights: dict[str, float] = dataclasses.field(default_factory=dict)  # per-shard renderer draw
    distractor_mix: str = "v4"  # kinds and materials of the look-alikes (training/clutter.py MIXES; v5: "print")
    # distractor kinds labelled as opaque objects (instances of the opaque class) instead of background: things
    # standing on the table that a prompt for opaque objects should find (segmenter v7: every kind but ``book``)
    object_distractors: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        from torm.segmentation.training.render import RENDERERS, SHARD_RENDERERS

        if self.renderer not in RENDERERS:
            raise ConfigError(f"data.renderer {self.renderer!r}; valid choices: {', '.join(RENDERERS)}")
        bad_r = sorted(set(self.renderer_weights) - set(SHARD_RENDERERS))
        if bad_r or any(float(w) < 0 for w in self.renderer_weights.values()) or (
                self.renderer_weights and sum(self.renderer_weights.values()) <= 0):
            raise ConfigError(f"data.renderer_weights {dict(self.renderer_weights)}: keys among "
                              f"{', '.join(SHARD_RENDERERS)}, weights >= 0 with a positive sum")
        if not all(0 <= f <= 1 for f in (self.distractor_fraction, self.room_fraction, self.lighting_fraction)):
            raise ConfigError("data.distractor_fraction, data.room_fraction and data.lighting_fraction must be in "
                              "[0, 1]")
        from torm.segmentation.training.clutter import MIXES

        if self.distractor_mix not in MIXES:
            raise ConfigError(f"data.distractor_mix {self.distractor_mix!r}; valid choices: {', '.join(MIXES)}")
        from torm.segmentation.training.clutter import KINDS

        bad_k = sorted(set(self.object_distractors) - set(KINDS))
        if bad_k:
            raise ConfigError(f"data.object_distractors: unknown kind(s) {bad_k}; valid choices: {', '.join(KINDS)}")
        if self.object_distractors and not self.label_opaque:
            raise ConfigError("data.object_distractors labels distractors as opaque objects; it needs "
                              "data.label_opaque: true")
        dlo, dhi = self.distractors_per_scene
        if not 0 <= dlo <= dhi <= 20:
            raise ConfigError("data.distractors_per_scene must be (lo, hi) with 0 <= lo <= hi <= 20")
        lo, hi = self.objects_per_scene
        if not 1 <= lo <= hi <= 10:
            raise ConfigError("data.objects_per_scene must be (lo, hi) with 1 <= lo <= hi <= 10")
        if (min(self.width, self.height) < 16 or self.width > self.full_width or self.height > self.full_height
                or self.views_per_scene < 1 or self.test_views < 2):
            raise ConfigError("data: need 16 px <= width <= full_width, 16 px <= height <= full_height, "
                              "views_per_scene >= 1, test_views >= 2")
        if not (0 <= self.library_fraction <= 1 and 0 <= self.dense_fraction <= 1):
            raise ConfigError("data.library_fraction and data.dense_fraction must be in [0, 1]")
        bad = sorted(set(self.shards) - set(SPLITS))
        if bad:
            raise ConfigError(f"data.shards: unknown split(s) {bad}; valid: {', '.join(SPLITS)}")

    def K(self) -> np.ndarray:
        """(3, 3) intrinsics of the full ``full_width`` x ``full_height`` camera (the rig's 91.5 deg HFOV)."""
        f = 0.5 * self.full_width / np.tan(np.deg2rad(self.hfov_deg) / 2)
        return np.array([[f, 0, self.full_width / 2], [0, f, self.full_height / 2], [0, 0, 1.0]])

    def crop_K(self, T_world_cam: np.ndarray, points_world_nx3: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """(3, 3) intrinsics of a ``width`` x ``height`` window of the full camera around the projected points.

        The same focal length as the full camera with a shifted principal point: rendering it is exactly
        cropping the full-resolution image (objects keep their pixel size) at a fraction of the cost. The
        window centre is the points' mean projection plus N(0, ``crop_jitter_px``), kept inside the full frame.
        """
        K = self.K()
        p = (np.asarray(points_world_nx3) - T_world_cam[:3, 3]) @ T_world_cam[:3, :3]
        p = p[p[:, 2] > 1e-3]
        uv = p[:, :2] / p[:, 2:3] * K[0, 0] + K[:2, 2] if len(p) else K[:2, 2][None]
        c = uv.mean(axis=0) + rng.normal(0, self.crop_jitter_px, 2)
        x0 = float(np.clip(round(c[0] - self.width / 2), 0, max(self.full_width - self.width, 0)))
        y0 = float(np.clip(round(c[1] - self.height / 2), 0, max(self.full_height - self.height, 0)))
        out = K.copy()
        out[0, 2] -= x0
        out[1, 2] -= y0
        return out

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)


def stored_recipe(d: dict[str, Any]) -> dict[str, Any]:
    """A recipe dict as stored (JSON types), with the fields it lacks at their defaults: a folder or model card written
    before a field existed was made with its default."""
    return json.loads(json.dumps({**DataRecipe().to_dict(), **d}))


def random_poses(n: int, recipe: DataRecipe, rng: np.random.Generator) -> np.ndarray:
    """(n, 4, 4) OpenCV camera-to-world poses on the recipe's band, looking at the jittered workspace centre."""
    out = np.empty((n, 4, 4))
    centre = np.array([0.55, 0.0, 0.0])
    for i in range(n):
        r = rng.uniform(*recipe.radius_range)
        el = np.deg2rad(rng.uniform(*recipe.elevation_deg))
        az = rng.uniform(0, 2 * np.pi)
        target = centre + np.array([*rng.normal(0, recipe.target_jitter, 2), rng.uniform(0.0, 0.05)])
        eye = target + r * np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
        out[i] = look_at_cv(eye, target)
    return out


def rig_poses(n: int) -> np.ndarray:
    """The capture rig's default Fibonacci layout (radius 0.5 m, 20-80 deg): neighbouring views are close."""
    from sim.cameras.rig import CameraRigConfig

    return CameraRigConfig(n_views=n).poses()


def _pools(recipe: DataRecipe) -> tuple[list[str], list[str], list[str]]:
    from torm.segmentation.training.shapes import HELD_OUT_SHAPES, register_procedural, train_library_objects

    proc = register_procedural(recipe.n_procedural, recipe.procedural_seed)
    return list(train_library_objects()), proc, list(HELD_OUT_SHAPES)


def sample_objects(split: str, recipe: DataRecipe, rng: np.random.Generator) -> tuple[str, ...]:
    """Object names of one scene of ``split`` (see the module docstring)."""
    lib, proc, held = _pools(recipe)
    n = int(rng.integers(recipe.objects_per_scene[0], recipe.objects_per_scene[1] + 1))
    if split in ("train", "val"):
        return tuple(str(rng.choice(lib)) if rng.random() < recipe.library_fraction else str(rng.choice(proc))
                     for _ in range(n))
    if split in LIBRARY_SPLITS:
        return tuple(str(rng.choice(lib)) for _ in range(n))
    k = int(rng.integers(1, min(n, 3) + 1))
    objs = [str(rng.choice(held)) for _ in range(k)] + [str(rng.choice(lib)) for _ in range(n - k)]
    rng.shuffle(objs)
    return tuple(objs)


def sample_fixture_scene(recipe: DataRecipe, rng: np.random.Generator) -> tuple[tuple[str, ...], str, int]:
    """(objects, fixture, how many of the first objects stand in it) of one fixture-split scene: with probability
    1/2 a ``tube_rack`` holding 1-5 test tubes with 0-3 other library objects on the table, else a ``tray`` holding
    1..n of its n library objects (no tubes; n drawn from ``objects_per_scene``)."""
    lib, _, _ = _pools(recipe)
    tubes = [o for o in lib if o.startswith("test_tube")]
    others = [o for o in lib if not o.startswith("test_tube")]
    if tubes and rng.random() < 0.5:
        n_t = int(rng.integers(1, RACK_SLOTS + 1))
        n_rest = int(rng.integers(0, 4))
        objs = [str(rng.choice(tubes)) for _ in range(n_t)] + [str(rng.choice(others)) for _ in range(n_rest)]
        return tuple(objs), "tube_rack", n_t
    n = int(rng.integers(recipe.objects_per_scene[0], recipe.objects_per_scene[1] + 1))
    objs = [str(rng.choice(others)) for _ in range(n)]
    return tuple(objs), "tray", int(rng.integers(1, n + 1))


def scene_seed(recipe: DataRecipe, split: str, shard: int, j: int) -> int:
    return int(recipe.seed * 10_000_000 + _SPLIT_SALT[split] * 1_000_000 + shard * 1000 + j)


def shard_renderer(recipe: DataRecipe, split: str, shard: int) -> str:
    """The renderer of shard ``shard`` of ``split``: ``recipe.renderer``, or a draw from ``renderer_weights`` seeded
    by (recipe seed, split, shard) (one renderer per shard: Mitsuba's variant is fixed per process)."""
    if not recipe.renderer_weights:
        return recipe.renderer
    names = sorted(recipe.renderer_weights)
    w = np.array([float(recipe.renderer_weights[n]) for n in names])
    rng = np.random.default_rng([recipe.seed, _SPLIT_SALT[split], shard, 0x5EED])
    return str(rng.choice(names, p=w / w.sum()))


def shard_path(root: Path, split: str, shard: int) -> Path:
    """Where shard ``shard`` of ``split`` lives under ``root``."""
    return Path(root) / split / f"shard_{shard:05d}.npz"


def _build_scene(recipe: DataRecipe, split: str, shard: int, j: int) -> tuple[int, np.random.Generator, Any, tuple,
                                                                              str, str | None]:
    """(seed, rng after the draws, world or None, objects, spacing, fixture) of scene ``j`` of a shard: a pure
    function of its arguments (the reference pass rebuilds the same scene)."""
    from sim.scenes.scenario import Scenario
    from sim.world import build_world

    seed = scene_seed(recipe, split, shard, j)
    rng = np.random.default_rng(seed)
    world, objs, spacing, fixture = None, (), "moderate", None
    for _attempt in range(5):
        fixture, n_fix = None, 0
        if split in FIXTURE_SPLITS:
            objs, fixture, n_fix = sample_fixture_scene(recipe, rng)
        else:
            objs = sample_objects(split, recipe, rng)
        spacing = "dense" if rng.random() < recipe.dense_fraction else "moderate"
        try:
            world = build_world(Scenario(name=f"{split}_{shard}_{j}", objects=objs, spacing=spacing,
                                         fixture=fixture, fixture_objects=n_fix), seed, robot=None)
            break
        except SceneError as exc:
            log.info("scene %d/%d/%d rejected (%s); drawing another object set", shard, j, _attempt, exc)
    return seed, rng, world, tuple(objs), spacing, fixture


def _cameras(recipe: DataRecipe, split: str, world: Any, rng: np.random.Generator
             ) -> tuple[np.ndarray, np.ndarray, int, int]:
    """(T_world_cam (V, 4, 4), K (V, 3, 3), width, height) of a scene's views."""
    if split in RIG_SPLITS:  # full frames of the rig layout
        Ts = rig_poses(recipe.test_views)
        return Ts, np.repeat(recipe.K()[None], len(Ts), axis=0), recipe.full_width, recipe.full_height
    Ts = random_poses(recipe.views_per_scene, recipe, rng)  # crops around the objects of random cameras
    centres = np.array([world.object_pose(o.instance_id)[:3, 3] for o in world.objects])
    K_v = np.stack([recipe.crop_K(T, centres, rng) for T in Ts])
    return Ts, K_v, recipe.width, recipe.height


def _scenes(recipe: DataRecipe, split: str, shard: int) -> Any:
    """Every scene of a shard that builds, as (seed, rng, world, objects, spacing, fixture, T_world_cam, K, width,
    height, look): the draws in the order the shard and its reference pass both make them."""
    from torm.segmentation.training.render import SceneLook

    renderer = shard_renderer(recipe, split, shard)
    for j in range(recipe.scenes_per_shard):
        seed, rng, world, objs, spacing, fixture = _build_scene(recipe, split, shard, j)
        if world is None:
            continue
        Ts, K_v, w, h = _cameras(recipe, split, world, rng)
        look = SceneLook.draw(recipe, rng) if renderer != "mujoco" else SceneLook()
        yield seed, rng, world, objs, spacing, fixture, Ts, K_v, w, h, look


def generate_shard(recipe: DataRecipe, split: str, shard: int, root: Path) -> Path:
    """Render shard ``shard`` of ``split`` into ``root`` unless it exists; returns its path."""
    from torm.segmentation.training.render import render_scene

    path = shard_path(root, split, shard)
    if path.exists():
        return path
    path.parent.mkdir(parents=True, exist_ok=True)
    renderer = shard_renderer(recipe, split, shard)
    rgbs, masks, poses, Ks, scene_idx, meta = [], [], [], [], [], []
    for seed, rng, world, objs, spacing, fixture, Ts, K_v, w, h, look in _scenes(recipe, split, shard):
        rgb, mask, look_info = render_scene(renderer, world, Ts, K_v, w, h, rng, recipe.spp, look)
        if not recipe.label_opaque:  # only glass is labelled: opaque objects become background
            for o in world.objects:
                if not o.transparent:
                    mask[mask == o.instance_id] = 0
        rgbs.append(rgb)
        masks.append(mask.astype(np.uint8))
        poses.append(Ts)
        Ks.append(K_v)
        scene_idx += [len(meta)] * len(Ts)
        meta.append({"seed": seed, "objects": list(objs), "spacing": spacing, "fixture": fixture,
                     "materials": ["glass" if o.transparent else "opaque" for o in world.objects]
                     + ["opaque"] * len(look_info.get("object_distractors", [])),
                     "renderer": renderer, **look_info})
    tmp = path.with_suffix(".tmp.npz")
    np.savez_compressed(tmp, rgb=np.concatenate(rgbs), mask=np.concatenate(masks), T_world_cam=np.concatenate(poses),
                        K=np.concatenate(Ks), scene=np.asarray(scene_idx, np.int32),
                        meta=np.asarray(json.dumps({"recipe": recipe.to_dict(), "scenes": meta})))
    os.replace(tmp, path)
    return path


def transparent_maps(mask_nxhxw: np.ndarray, scene_n: np.ndarray, meta: list[dict[str, Any]]) -> np.ndarray:
    """(N, H, W) uint8: 1 on the pixels of transparent objects, 0 elsewhere (opaque objects and background), from
    instance masks (value k = the scene's object k) and each scene's ``materials`` (``glass`` / ``opaque``, object
    order): the target of the class head (segmenter v6). Needs data rendered with ``label_opaque`` true, or every
    labelled object is glass."""
    out = np.zeros(mask_nxhxw.shape, np.uint8)
    for i, (m, sc) in enumerate(zip(mask_nxhxw, scene_n, strict=True)):
        mats = meta[int(sc)].get("materials")
        if mats is None:
            raise SceneError(f"scene {int(sc)} of the data has no 'materials' entry; re-render it with this version")
        glass = np.zeros(max(int(m.max()), len(mats)) + 1, np.uint8)
        glass[1:len(mats) + 1] = [1 if x == "glass" else 0 for x in mats]
        out[i] = glass[m]
    return out


def reference_path(root: Path, split: str, shard: int) -> Path:
    """Where the reference pass of a shard lives: ``<split>/shard_00000.ref.npz`` beside it."""
    return shard_path(root, split, shard).with_suffix(".ref.npz")


def generate_reference_shard(recipe: DataRecipe, split: str, shard: int, root: Path,
                             drop_distractors: float = 0.3) -> Path:
    """The empty-workspace reference pass of an existing shard: the same scenes rebuilt from their seeds, the same
    cameras, renderer and look, the objects hidden, independent render noise; each distractor is also removed with
    probability ``drop_distractors`` (things that arrive with the objects). Writes ``reference_rgb`` (N, H, W, 3)
    uint8 to :func:`reference_path`; raises when a rebuilt scene's cameras differ from the shard's."""
    from sim.cameras.reference_pass import objects_hidden
    from torm.segmentation.training.render import render_scene

    path = reference_path(root, split, shard)
    if path.exists():
        return path
    src = shard_path(root, split, shard)
    if not src.exists():
        raise ConfigError(f"{src} does not exist; render the shard before its reference pass")
    z = np.load(src)
    renderer = shard_renderer(recipe, split, shard)
    refs, poses = [], []
    for _seed, rng, world, _objs, _spacing, _fixture, Ts, K_v, w, h, look in _scenes(recipe, split, shard):
        look = dataclasses.replace(look, reference=True, drop_distractors=drop_distractors)
        with objects_hidden(world):
            rgb, _mask, _info = render_scene(renderer, world, Ts, K_v, w, h, rng, recipe.spp, look)
        refs.append(rgb)
        poses.append(Ts)
    T = np.concatenate(poses)
    if T.shape != z["T_world_cam"].shape or not np.allclose(T, z["T_world_cam"], atol=1e-9):
        raise ConfigError(f"{src}: the rebuilt scenes' cameras differ from the shard's (another code version or "
                          "recipe?); re-render the shard")
    tmp = path.with_suffix(".tmp.npz")
    np.savez_compressed(tmp, reference_rgb=np.concatenate(refs))
    os.replace(tmp, path)
    return path


def _render_job(args: tuple) -> str:
    """One shard (or, with a fifth element True, its reference pass) in a worker process (single-threaded renders;
    one process per core)."""
    os.environ.setdefault("MUJOCO_GL", "egl")
    recipe, split, shard, root = args[:4]
    if len(args) > 4 and args[4]:
        return str(generate_reference_shard(recipe, split, shard, Path(root)))
    return str(generate_shard(recipe, split, shard, Path(root)))


def generate(recipe: DataRecipe, root: Path, splits: tuple[str, ...] = SPLITS, progress: bool = True,
             workers: int = 1, references: bool = False) -> list[Path]:
    """Render every missing shard of ``splits`` (resumable; existing shards are kept).

    ``workers`` > 1 renders shards in that many spawned processes (one core each). Shard contents depend only on
    the recipe and the shard index (:func:`scene_seed`), so the dataset is the same for any ``workers``.
    ``references``: then render each shard's missing reference pass (:func:`generate_reference_shard`).
    """

    if workers < 1:
        raise ConfigError(f"generate: workers = {workers} must be >= 1")
    root = Path(root)
    root.mkdir(parents=True, exist_ok=True)
    rec_path = root / "recipe.json"
    mine = json.loads(json.dumps(recipe.to_dict()))  # tuples as lists, as stored
    if rec_path.exists():  # shard contents do not depend on the shard counts: compare everything else
        theirs = stored_recipe(json.loads(rec_path.read_text()))
        if {k: v for k, v in theirs.items() if k != "shards"} != {k: v for k, v in mine.items() if k != "shards"}:
            raise ConfigError(f"{root} holds shards of another data recipe ({rec_path}); use another folder or "
                              "delete it")
        old = theirs.get("shards", {})
        mine["shards"] = {s: max(int(old.get(s, 0)), int(mine["shards"].get(s, 0))) for s in {*old, *mine["shards"]}}
    rec_path.write_text(json.dumps(mine, indent=2, sort_keys=True))
    jobs = [(s, i) for s in splits for i in range(recipe.shards.get(s, 0))]
    _run_jobs(recipe, root, [(s, i) for s, i in jobs if not shard_path(root, s, i).exists()], workers, False,
              progress)
    if references:
        _run_jobs(recipe, root, [(s, i) for s, i in jobs if not reference_path(root, s, i).exists()], workers, True,
                  progress)
    return [shard_path(root, s, i) for s, i in jobs]


def _run_jobs(recipe: DataRecipe, root: Path, todo: list[tuple[str, int]], workers: int, reference: bool,
              progress: bool) -> None:
    from tqdm import tqdm

    desc = "render reference passes" if reference else "render shards"
    variants = {shard_renderer(recipe, s, i) for s, i in todo} & {"pbr", "pbr_scalar"}
    if (workers > 1 and len(todo) > 1) or len(variants) > 1:
        import multiprocessing as mp
        from concurrent.futures import ProcessPoolExecutor

        # a fresh process per shard when Mitsuba variants mix (the variant is fixed per process)
        per_child = {"max_tasks_per_child": 1} if len(variants) > 1 else {}
        with ProcessPoolExecutor(max(1, min(workers, len(todo))), mp_context=mp.get_context("spawn"),
                                 **per_child) as ex:
            done = ex.map(_render_job, [(recipe, s, i, str(root), reference) for s, i in todo])
            for _ in tqdm(done, total=len(todo), desc=desc, unit="shard", disable=not progress):
                pass
        return
    for s, i in tqdm(todo, desc=desc, unit="shard", disable=not progress):
        (generate_reference_shard if reference else generate_shard)(recipe, s, i, root)


def load_split(root: Path, split: str, references: bool = False) -> dict[str, Any]:
    """All shards of ``split`` concatenated: rgb, mask, T_world_cam, scene (global index), meta list; with
    ``references`` also ``reference`` (N, H, W, 3) uint8, the empty-workspace views (a named error when a shard's
    reference pass is missing)."""
    files = sorted((Path(root) / split).glob("shard_*.npz"))
    files = [f for f in files if not f.name.endswith((".tmp.npz", ".ref.npz"))]
    if not files:
        raise ConfigError(f"no shards of split {split!r} under {root}; generate them first (torm train-segmenter)")
    rgb, mask, T, Ks, scene, meta, refs = [], [], [], [], [], [], []
    offset = 0
    for f in files:
        z = np.load(f)
        if references:
            rp = f.with_suffix(".ref.npz")
            if not rp.exists():
                raise ConfigError(f"{f} has no reference pass ({rp.name}); render it (train.reference renders them)")
            refs.append(np.load(rp)["reference_rgb"])
        rgb.append(z["rgb"])
        mask.append(z["mask"])
        T.append(z["T_world_cam"])
        Ks.append(z["K"])
        m = json.loads(str(z["meta"]))["scenes"]
        scene.append(z["scene"] + offset)
        meta += [m[k] for k in range(len(m))]
        offset += len(m)
    return {"rgb": np.concatenate(rgb), "mask": np.concatenate(mask), "T_world_cam": np.concatenate(T),
            "scene": np.concatenate(scene), "meta": meta, "K": np.concatenate(Ks),
            **({"reference": np.concatenate(refs)} if references else {})}
