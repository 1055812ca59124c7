"""Blender Cycles (PyPI ``bpy``) vs the Mitsuba renderer: time per 640x360 view at equal noise.

Why: the issue allows Blender's ``bpy`` + Cycles instead of Mitsuba 3 if it is measured faster at equal quality.
``bpy`` is not a torm dependency (a 374 MB wheel that pins its own numpy), so this runs in three steps:

1. ``python benchmarks/render_cycles.py export DIR`` (torm's venv): the same rw3 scene as ``benchmarks/render.py``
   (geometry at the settled poses, table texture, environment map, area lights, one camera) as ``DIR/scene.npz``
   + ``DIR/scene.json``.
2. ``BPY_PYTHON benchmarks/render_cycles.py cycles DIR`` (a venv with ``pip install bpy==5.0.1``): Cycles on the
   CPU, 2 threads, persistent data, max 8 bounces, glass BSDF IOR from the scene, emissive panels with the same
   radiance; for 1, 2 and 4 spp with and without its bundled OpenImageDenoise, the warm wall time of one render
   (image write included) and the RMSE (8-bit levels, tone-mapped with the reference's auto-exposure gain)
   against Cycles' own 32-spp reference (a first measurement put 1 spp at ~4 s per view: more spp cannot make
   it faster). Writes ``DIR/cycles.json``.
3. ``python benchmarks/render_cycles.py report DIR`` (torm's venv): the same protocol for Mitsuba (chosen
   integrator and sampler, nlmeans denoise) against its own 256-spp reference, and the time each needs for a
   given RMSE: ``benchmarks/results/render_cycles.{json,md}``.

Equal quality here means equal noise (RMSE against each renderer's own converged image), not identical light
transport (Cycles runs its default caustics; the environment map orientation is not matched). About 5 minutes
on 2 cores under the lock.
"""

from __future__ import annotations

import json
import os
import sys
import time
from pathlib import Path

import numpy as np

QUICK = os.environ.get("TORM_RENDER_CYCLES_QUICK") == "1"  # smoke run of the plumbing
SPPS = (4,) if QUICK else (4, 16, 64)  # the ldsampler's sample counts (square powers of two, >= 4)
SPPS_CYCLES = (1, 2) if QUICK else (1, 2, 4)  # Cycles' time per view already exceeds the target at 1 spp
REF_SPP_CYCLES = 8 if QUICK else 32
REF_SPP_MITSUBA = 8 if QUICK else 256
VIEW = 25  # of the rig's 50-view layout


def _srgb8(lin: np.ndarray, gain: float) -> np.ndarray:
    c = np.clip(lin * gain, 0.0, 1.0)
    return np.round(255 * np.where(c <= 0.0031308, 12.92 * c, 1.055 * np.power(c, 1 / 2.4) - 0.055))


def _gain(lin: np.ndarray) -> float:
    lum = np.maximum(lin[..., :3] @ np.array([0.2126, 0.7152, 0.0722]), 0.0)
    return 0.18 / float(np.exp(np.mean(np.log(lum + 1e-4))))


def _rmse(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.sqrt(np.mean((a - b) ** 2)))


# ------------------------------------------------------------------------------------------- export (torm)
def export(folder: Path) -> None:
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
    os.environ.setdefault("MUJOCO_GL", "egl")
    import trimesh

    from sim.cameras.rig import CameraRigConfig
    from sim.render.lighting import sample_lighting
    from sim.render.scene import describe_world
    from sim.render.textures import table_texture
    from sim.world import build_world

    world = build_world("rw3", 0, robot=None)
    desc = describe_world(world)
    light = sample_lighting(desc.layout_seed, desc.centre)
    cfg = CameraRigConfig(n_views=50, scale=0.5)
    arrays: dict[str, np.ndarray] = {"env": light.env_hxwx3, "K": cfg.K(), "T_world_cam": cfg.poses()[VIEW]}
    meta: dict = {"width": cfg.image_width, "height": cfg.image_height, "env_rotation_deg": light.env_rotation_deg,
                  "geoms": [], "area_lights": []}
    for i, g in enumerate(desc.geoms):
        entry = {"name": g.name, "kind": g.kind, "material": g.material, "rgb": list(g.rgb), "ior": g.ior,
                 "size": g.size.tolist(), "T": g.T_world_geom.tolist()}
        if g.kind == "mesh":
            tm = trimesh.graph.smooth_shade(trimesh.Trimesh(*g.mesh, process=False), angle=np.radians(30),
                                            facet_minarea=None)
            arrays[f"v{i}"], arrays[f"f{i}"] = np.asarray(tm.vertices), np.asarray(tm.faces)
            entry["mesh"] = i
        if g.material == "table":
            arrays["table_tex"] = table_texture(desc.layout_seed, (2 * g.size[0], 2 * g.size[1])).image_hxwx3
        meta["geoms"].append(entry)
    for a in light.area_lights:
        meta["area_lights"].append({"T": a.T_world_light().tolist(), "radiance": np.asarray(a.radiance).tolist()})
    folder.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(folder / "scene.npz", **arrays)
    (folder / "scene.json").write_text(json.dumps(meta))


# ------------------------------------------------------------------------------------------- cycles (bpy)
def cycles(folder: Path) -> None:
    import bpy

    z = np.load(folder / "scene.npz")
    meta = json.loads((folder / "scene.json").read_text())
    bpy.ops.wm.read_factory_settings(use_empty=True)
    scene = bpy.context.scene

    def material(name: str, kind: str, rgb=None, ior=1.5, image=None, strength=None):
        m = bpy.data.materials.new(name)
        m.use_nodes = True
        nt = m.node_tree
        nt.nodes.clear()
        out = nt.nodes.new("ShaderNodeOutputMaterial")
        if kind == "glass":
            sh = nt.nodes.new("ShaderNodeBsdfGlass")
            sh.inputs["IOR"].default_value = ior
            sh.inputs["Roughness"].default_value = 0.0
        elif kind == "emission":
            sh = nt.nodes.new("ShaderNodeEmission")
            sh.inputs["Color"].default_value = (*rgb, 1.0)
            sh.inputs["Strength"].default_value = strength
        else:
            sh = nt.nodes.new("ShaderNodeBsdfDiffuse")
            if image is not None:
                tex = nt.nodes.new("ShaderNodeTexImage")
                tex.image = image
                nt.links.new(tex.outputs["Color"], sh.inputs["Color"])
            else:
                sh.inputs["Color"].default_value = (*rgb, 1.0)
        nt.links.new(sh.outputs[0], out.inputs["Surface"])
        return m

    def float_image(name: str, arr: np.ndarray):
        h, w = arr.shape[:2]
        img = bpy.data.images.new(name, w, h, float_buffer=True, alpha=True)
        rgba = np.concatenate([arr[::-1], np.ones((h, w, 1), np.float32)], axis=2)  # Blender rows run bottom-up
        img.pixels.foreach_set(rgba.astype(np.float32).ravel())
        img.colorspace_settings.name = "Non-Color"
        return img

    def add_mesh(name: str, verts, faces, T, mat, smooth: bool):
        me = bpy.data.meshes.new(name)
        me.from_pydata([tuple(v) for v in np.asarray(verts, float)], [], [tuple(int(i) for i in f) for f in faces])
        me.update()
        for p in me.polygons:
            p.use_smooth = smooth
        ob = bpy.data.objects.new(name, me)
        ob.matrix_world = [list(r) for r in np.asarray(T)]
        me.materials.append(mat)
        scene.collection.objects.link(ob)

    cube_v = np.array([[x, y, zz] for x in (-1, 1) for y in (-1, 1) for zz in (-1, 1)], float)
    cube_f = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
    quad_v = np.array([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0]], float)
    for g in meta["geoms"]:
        T, size = np.asarray(g["T"]), np.asarray(g["size"])
        if g["material"] == "glass":
            mat = material(g["name"], "glass", ior=g["ior"])
        elif g["material"] == "table":
            mat = material(g["name"], "diffuse", image=float_image("table_tex", z["table_tex"]))
        else:
            mat = material(g["name"], "diffuse", rgb=g["rgb"])
        if g["kind"] == "mesh":
            add_mesh(g["name"], z[f"v{g['mesh']}"], z[f"f{g['mesh']}"], T, mat, True)
        elif g["kind"] == "box" and g["material"] == "table":
            S = np.diag([size[0], size[1], 1.0, 1.0])
            S[2, 3] = size[2]
            add_mesh("table_top", quad_v, [(0, 1, 2, 3)], T @ S, mat, False)
            body = material("table_body", "diffuse", rgb=list(z["table_tex"].reshape(-1, 3).mean(0) * 0.6))
            S2 = np.diag([*size, 1.0])
            S2[2, 3] = -1e-4
            add_mesh("table_body", cube_v, cube_f, T @ S2, body, False)
        elif g["kind"] == "box":
            add_mesh(g["name"], cube_v, cube_f, T @ np.diag([*size, 1.0]), mat, False)
        elif g["kind"] == "plane":
            hx, hy = (size[0] or 10.0), (size[1] or 10.0)
            add_mesh(g["name"], quad_v, [(0, 1, 2, 3)], T @ np.diag([hx, hy, 1.0, 1.0]), mat, False)
    for i, a in enumerate(meta["area_lights"]):
        rad = np.asarray(a["radiance"])
        s = float(rad.max())
        add_mesh(f"panel{i}", quad_v, [(0, 1, 2, 3)], np.asarray(a["T"]),
                 material(f"panel{i}", "emission", rgb=list(rad / s), strength=s), False)
    world = bpy.data.worlds.new("env")
    world.use_nodes = True
    nt = world.node_tree
    nt.nodes.clear()
    env = nt.nodes.new("ShaderNodeTexEnvironment")
    env.image = float_image("env", z["env"])
    bg = nt.nodes.new("ShaderNodeBackground")
    out = nt.nodes.new("ShaderNodeOutputWorld")
    nt.links.new(env.outputs["Color"], bg.inputs["Color"])
    nt.links.new(bg.outputs["Background"], out.inputs["Surface"])
    scene.world = world
    # camera: Blender cameras look along -z with +y up
    W, H, K = meta["width"], meta["height"], z["K"]
    cam_data = bpy.data.cameras.new("cam")
    cam_data.sensor_fit = "HORIZONTAL"
    cam_data.angle = 2 * np.arctan(W / (2 * K[0, 0]))
    cam_data.clip_start = 0.005
    cam = bpy.data.objects.new("cam", cam_data)
    cam.matrix_world = [list(r) for r in z["T_world_cam"] @ np.diag([1.0, -1.0, -1.0, 1.0])]
    scene.collection.objects.link(cam)
    scene.camera = cam
    r = scene.render
    r.engine = "CYCLES"
    r.resolution_x, r.resolution_y, r.resolution_percentage = W, H, 100
    r.threads_mode, r.threads = "FIXED", 2
    r.use_persistent_data = True
    r.image_settings.file_format = "OPEN_EXR"
    scene.view_settings.view_transform = "Standard"
    c = scene.cycles
    c.device = "CPU"
    c.max_bounces = c.transmission_bounces = c.glossy_bounces = 8
    c.use_adaptive_sampling = False
    c.seed = 1
    path = str(folder / "cycles.exr")

    def render(spp: int, denoise: bool) -> tuple[np.ndarray, float]:
        c.samples = spp
        c.use_denoising = denoise
        if denoise:
            c.denoiser = "OPENIMAGEDENOISE"
        t = time.perf_counter()
        r.filepath = path
        bpy.ops.render.render(write_still=True)
        dt = time.perf_counter() - t
        img = bpy.data.images.load(path, check_existing=False)
        arr = np.array(img.pixels[:], dtype=np.float32).reshape(H, W, 4)[::-1, :, :3]
        bpy.data.images.remove(img)
        return arr, dt

    render(1, False)  # warm-up: scene sync and BVH (kept by persistent data)
    ref, ref_s = render(REF_SPP_CYCLES, False)
    g = _gain(ref)
    R = _srgb8(ref, g)
    rows = []
    for spp in SPPS_CYCLES:
        for dn in (False, True):
            img, dt = render(spp, dn)
            rows.append({"spp": spp, "denoise": "oidn" if dn else "none", "s_per_view": dt,
                         "rmse": _rmse(_srgb8(img, g), R)})
            print(rows[-1], flush=True)
    doc = {"renderer": f"blender {bpy.app.version_string} cycles cpu", "threads": 2, "ref_spp": REF_SPP_CYCLES,
           "ref_s": ref_s, "rows": rows, "load_avg": list(os.getloadavg()),
           "date_utc": time.strftime("%Y-%m-%dT%H:%M:%S", time.gmtime())}
    (folder / "cycles.json").write_text(json.dumps(doc, indent=1))


# ------------------------------------------------------------------------------------------- report (torm)
def report(folder: Path) -> None:
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    import _common as bc

    bc.setup(2)
    from sim.cameras.rig import CameraRigConfig
    from sim.render import MitsubaRenderer, PbrSettings, RenderCamera
    from sim.render.mitsuba_renderer import denoise, render_linear, tone_map
    from sim.world import build_world

    cyc = json.loads((folder / "cycles.json").read_text())
    ctx = bc.context({"folder": str(folder)})
    world = build_world("rw3", 0, robot=None)
    cfg = CameraRigConfig(n_views=50, scale=0.5)
    cam = RenderCamera(cfg.K(), cfg.poses()[VIEW], cfg.image_width, cfg.image_height)
    base = PbrSettings(spp=REF_SPP_MITSUBA, denoise="none", cache=False, threads=2)
    r = MitsubaRenderer(world, base)
    mi_scene, _ = r.scene()
    ref = render_linear(mi_scene, cam, base, 7)
    g = _gain(ref)
    R = _srgb8(ref, g)
    rows = []
    for spp in SPPS:
        s = PbrSettings(spp=spp, cache=False, threads=2)
        render_linear(mi_scene, cam, s, 0)  # warm-up (kernel compile)
        t = time.perf_counter()
        lin = render_linear(mi_scene, cam, s, 1)
        t_r = time.perf_counter() - t
        for dn, strength in (("none", 0.0), ("nlmeans", s.denoise_strength)):
            t = time.perf_counter()
            img = denoise(tone_map(lin, g), dn, strength)
            rows.append({"spp": spp, "denoise": dn, "s_per_view": t_r + time.perf_counter() - t,
                         "rmse": _rmse(img.astype(float), R)})
    doc = {"context": ctx, "mitsuba": {"renderer": r.describe(), "ref_spp": REF_SPP_MITSUBA, "rows": rows},
           "cycles": cyc, "view": VIEW}
    write_report(doc)


def write_report(doc: dict) -> None:
    """``render_cycles.{json,md}`` from a report document (fastest time per view reaching 8, 5, 3 levels RMSE)."""
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    import _common as bc

    ctx, cyc, rows = doc["context"], doc["cycles"], doc["mitsuba"]["rows"]
    for target in (8.0, 5.0, 3.0):
        doc[f"time_for_rmse_{target:g}"] = {
            name: min((x["s_per_view"] for x in rs if x["rmse"] <= target), default=None)
            for name, rs in (("mitsuba", rows), ("cycles", cyc["rows"]))}
    bc.write_json(bc.RESULTS / "render_cycles.json", doc)
    md = [f"# Cycles vs Mitsuba, rw3 view {VIEW}, 640x360, 2 threads\n\n", bc.context_md(ctx),
          f"- Mitsuba: `{doc['mitsuba']['renderer']}` (spp varied), reference {doc['mitsuba']['ref_spp']} spp; "
          f"Cycles: `{cyc['renderer']}`, "
          f"reference {cyc['ref_spp']} spp, measured {cyc['date_utc']} (load {cyc['load_avg'][0]:.2f}).\n"
          "- RMSE in 8-bit levels against each renderer's own reference (equal noise, not identical transport).\n\n"]
    md.append(bc.md_table(["renderer", "spp", "denoise", "s/view", "RMSE"],
                          [["mitsuba", x["spp"], x["denoise"], x["s_per_view"], x["rmse"]] for x in rows]
                          + [["cycles", x["spp"], x["denoise"], x["s_per_view"], x["rmse"]] for x in cyc["rows"]], 2))
    md.append("\nFastest time per view reaching an RMSE:\n\n")
    md.append(bc.md_table(["RMSE <=", "mitsuba s", "cycles s"],
                          [[k.split("_")[-1], v["mitsuba"], v["cycles"]] for k, v in doc.items()
                           if k.startswith("time_for_rmse")], 2))
    (bc.RESULTS / "render_cycles.md").write_text("".join(md))


if __name__ == "__main__":
    cmd, folder = sys.argv[1], Path(sys.argv[2])
    {"export": export, "cycles": cycles, "report": report}[cmd](folder)
