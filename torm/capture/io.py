"""Read and write captures as folders in the nerfstudio ``transforms.json`` convention.

Layout written by :func:`save_capture`::

    DIR/transforms.json
    DIR/images/00000.png         RGB, 8-bit PNG (lossless)
    DIR/masks/00000.png          instance ids, 16-bit single-channel PNG (0 background, k = object k)
    DIR/depth/00000.npy          ideal z-depth, float32 metres (.npy: bit-exact; 0 or NaN = no reading)
    DIR/sensor_depth/00000.npy   sensor z-depth (sees through glass), float32 metres

``transforms.json`` holds ``camera_model`` ("PINHOLE"), ``fl_x, fl_y, cx, cy, w, h`` (pixels) and
``frames``: per frame ``file_path``, ``transform_matrix`` (camera-to-world, **OpenGL** axes: x
right, y up, z backwards, metres), optional ``mask_path``, ``depth_file_path``,
``sensor_depth_file_path`` and ``name``, and per-frame ``fl_x, fl_y, cx, cy`` where a view's
intrinsics differ from the top-level ones. Capture metadata sits at the top level: ``scenario``,
``seed``, ``object_ids``, ``object_names``, ``table_height`` (m; null or absent = no table plane),
``workspace_bounds`` ((2, 3) m; absent = the reconstruction computes a box from the cameras and masks),
``metadata`` (free JSON) and ``torm_version``. ``depth_unit_scale_factor`` is 1.0 (metres);
nerfstudio multiplies depth by its own ``depth_unit_scale_factor`` setting (default 1e-3), so set it
to 1.0 there when training with our depth. Note that nerfstudio treats ``mask_path`` as a binary
"pixels to use" mask, whereas ours holds instance ids (background 0).

:func:`load_capture` also reads third-party NeRF-style folders: ``transforms_train.json`` when
there is no ``transforms.json``; ``camera_angle_x`` (and ``camera_angle_y``, rad) instead of focal
lengths; ``file_path`` without an extension (``./train/r_0`` -> ``train/r_0.png``); RGBA images (the
RGB channels are kept as stored and, when the frame has no ``mask_path``, alpha > 0.5 becomes a
binary instance mask with id 1); binary 0/255 masks (when the file lists no ``object_ids``) become
instance 1; soft greyscale masks (coverage or alpha values at the edges, or more than
:data:`MAX_LABELS` grey levels in an 8-bit file; :func:`mask_kind`) are thresholded at 0.5 into
instance 1, with one log line; instance ids are taken only from integer-labelled masks, and a mask
with more than :data:`MAX_LABELS` ids is warned about; frames without masks; 16-bit PNG depth scaled by the file's
``depth_unit_scale_factor`` (default 1e-3, i.e. millimetres). A lens model with distortion (``camera_model``
OPENCV, OPENCV_FISHEYE, SIMPLE_RADIAL or RADIAL with ``k1``... at the top level or per frame) is undone when the
frame is loaded: images, masks and depth are resampled onto the pinhole camera with the same intrinsics
(:mod:`torm.capture.lens`), and ``metadata["undistorted"]`` says so; pixels left without a source are "no
evidence" (:func:`torm.capture.lens.no_evidence_masks`), which every segmenter's masks and the reconstruction
respect; an unknown model or lens coefficient is an error.
Inconsistent folders raise :class:`~torm.errors.CaptureError` naming the offending file.
"""

from __future__ import annotations

import json
import logging
import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import cv2
import numpy as np

import torm
from torm.errors import CaptureError
from torm.geometry import cv_to_gl, gl_to_cv
from torm.types import CameraView, Capture

log = logging.getLogger(__name__)

#: File names tried, in order, when a folder is given.
TRANSFORMS_NAMES: tuple[str, ...] = ("transforms.json", "transforms_train.json")
#: Extensions tried for a ``file_path`` that has none or does not exist as written.
IMAGE_EXTENSIONS: tuple[str, ...] = (".png", ".jpg", ".jpeg", ".PNG", ".JPG", ".JPEG")
#: Up to this many ids per mask an 8-bit mask may be an instance map; more is greyscale (or warned about).
MAX_LABELS = 48


def _json_default(o: Any) -> Any:
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"{type(o).__name__} is not JSON serialisable")


def _imwrite(path: Path, img: np.ndarray) -> None:
    ok = cv2.imwrite(str(path), img, [cv2.IMWRITE_PNG_COMPRESSION, 1])
    if not ok:
        raise CaptureError(f"could not write {path}; check that the folder is writable")


def _intrinsics(K: np.ndarray) -> dict[str, float]:
    return {"fl_x": float(K[0, 0]), "fl_y": float(K[1, 1]), "cx": float(K[0, 2]), "cy": float(K[1, 2])}


def save_capture(capture: Capture, folder: str | Path) -> Path:
    """Write ``capture`` to ``folder`` (created if needed); returns the path of ``transforms.json``.

    Lossless: :func:`load_capture` returns bit-identical images, masks and depth and the same
    poses and intrinsics. Raises CaptureError for masks outside 0..65535, skewed intrinsics or
    metadata that is not JSON-serialisable.
    """
    root = Path(folder)
    root.mkdir(parents=True, exist_ok=True)
    H, W = capture.image_size
    K0 = capture.views[0].K
    top = _intrinsics(K0)
    frames: list[dict[str, Any]] = []
    for i, v in enumerate(capture.views):
        if v.K[0, 1] != 0 or not np.array_equal(v.K[2], [0.0, 0.0, 1.0]) or v.K[1, 0] != 0:
            raise CaptureError(f"view {i} ({v.name!r}): transforms.json stores pinhole intrinsics without skew")
        stem = f"{i:05d}"
        frame: dict[str, Any] = {}
        if v.rgb is not None:
            (root / "images").mkdir(exist_ok=True)
            frame["file_path"] = f"images/{stem}.png"
            _imwrite(root / frame["file_path"], cv2.cvtColor(v.rgb, cv2.COLOR_RGB2BGR))
        if v.reference_rgb is not None:  # the empty workspace through the same camera (reference pass)
            (root / "reference").mkdir(exist_ok=True)
            frame["reference_file_path"] = f"reference/{stem}.png"
            _imwrite(root / frame["reference_file_path"], cv2.cvtColor(v.reference_rgb, cv2.COLOR_RGB2BGR))
        frame["transform_matrix"] = cv_to_gl(v.T_world_cam).tolist()
        if v.name:
            frame["name"] = v.name
        k = _intrinsics(v.K)
        if k != top:
            frame.update(k)
        if v.mask is not None:
            if v.mask.min() < 0 or v.mask.max() > 65535:
                raise CaptureError(f"view {i} ({v.name!r}): mask ids must be in 0..65535 to fit a 16-bit PNG")
            (root / "masks").mkdir(exist_ok=True)
            frame["mask_path"] = f"masks/{stem}.png"
            _imwrite(root / frame["mask_path"], v.mask.astype(np.uint16))
        for key, arr, sub in (
            ("depth_file_path", v.depth, "depth"),
            ("sensor_depth_file_path", v.sensor_depth, "sensor_depth"),
        ):
            if arr is not None:
                (root / sub).mkdir(exist_ok=True)
                frame[key] = f"{sub}/{stem}.npy"
                np.save(root / frame[key], np.ascontiguousarray(arr, dtype=np.float32), allow_pickle=False)
        frames.append(frame)
    doc: dict[str, Any] = {
        "camera_model": "PINHOLE",
        **top,
        "w": W,
        "h": H,
        "depth_unit_scale_factor": 1.0,
        "torm_version": torm.__version__,
        "scenario": capture.scenario,
        "seed": capture.seed,
        "object_ids": list(capture.object_ids),
        "object_names": list(capture.object_names),
        "table_height": capture.table_height,
        "workspace_bounds": None if capture.workspace_bounds is None else capture.workspace_bounds.tolist(),
        "metadata": capture.metadata,
        "frames": frames,
    }
    path = root / "transforms.json"
    try:
        text = json.dumps(doc, indent=2, default=_json_default, allow_nan=False)
    except (TypeError, ValueError) as exc:
        raise CaptureError(f"capture metadata is not JSON-serialisable ({exc}); keep it to numbers/strings") from exc
    path.write_text(text)
    return path


# --------------------------------------------------------------------------------------------- loading
def find_transforms(folder: str | Path) -> Path:
    """The transforms file in ``folder`` (transforms.json, else transforms_train.json) or the JSON path given."""
    p = Path(folder)
    if p.is_file():
        return p
    if not p.is_dir():
        raise CaptureError(f"capture folder {p} does not exist; give a folder that holds transforms.json")
    for name in TRANSFORMS_NAMES:
        if (p / name).is_file():
            return p / name
    raise CaptureError(f"{p} holds none of {', '.join(TRANSFORMS_NAMES)}; it is not a capture folder")


def _resolve_image(root: Path, rel: str, transforms: Path) -> Path:
    p = root / rel
    if p.is_file():
        return p
    for ext in IMAGE_EXTENSIONS:
        q = p.with_name(p.name + ext)
        if q.is_file():
            return q
    raise CaptureError(f"{transforms}: image file {p} is missing (also tried extensions {', '.join(IMAGE_EXTENSIONS)})")


def _read_image(path: Path) -> tuple[np.ndarray, np.ndarray | None]:
    """(H, W, 3) uint8 RGB and the (H, W) alpha mask (bool) when the image has an alpha channel."""
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise CaptureError(f"cannot read image {path}; it is not a PNG/JPEG file or it is corrupt")
    alpha = None
    if img.dtype == np.uint16:
        img8 = np.round(img.astype(np.float64) / 257.0).astype(np.uint8)
    elif img.dtype == np.uint8:
        img8 = img
    else:
        raise CaptureError(f"image {path} has pixel type {img.dtype}; use 8- or 16-bit images")
    if img.ndim == 2:
        rgb = np.repeat(img8[..., None], 3, axis=2)
    elif img.shape[2] == 4:
        rgb = cv2.cvtColor(img8[..., :3], cv2.COLOR_BGR2RGB)
        full = 65535 if img.dtype == np.uint16 else 255
        alpha = img[..., 3].astype(np.float64) > 0.5 * full
    elif img.shape[2] == 3:
        rgb = cv2.cvtColor(img8, cv2.COLOR_BGR2RGB)
    else:
        raise CaptureError(f"image {path} has {img.shape[2]} channels; expected 1, 3 or 4")
    return np.ascontiguousarray(rgb), alpha


def _read_mask(path: Path, transforms: Path) -> tuple[np.ndarray, int]:
    """(H, W) int32 mask values and the file's full-scale value (255 or 65535)."""
    if not path.is_file():
        raise CaptureError(f"{transforms}: mask file {path} is missing")
    m = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if m is None:
        raise CaptureError(f"cannot read mask {path}; expected a single-channel 8- or 16-bit PNG")
    if m.ndim == 3:
        if not (np.all(m == m[..., :1])):
            raise CaptureError(f"mask {path} has differing colour channels; store instance ids in one channel")
        m = m[..., 0]
    return m.astype(np.int32), (65535 if m.dtype == np.uint16 else 255)


def mask_kind(mask_hxw: np.ndarray, full: int) -> str:
    """``"binary"`` (0 and one value), ``"soft"`` (greyscale coverage/alpha) or ``"labels"`` (instance ids).

    Soft: an 8-bit mask with more than :data:`MAX_LABELS` grey levels, or one whose values other than 0 and
    its most common one sit almost only (> 60 %) on region edges (pixels that differ from a 4-neighbour),
    as antialiased or matted masks do; an instance map's ids fill regions.
    """
    vals, counts = np.unique(mask_hxw, return_counts=True)
    nz, nzc = vals[vals > 0], counts[vals > 0]
    if len(nz) <= 1:
        return "binary"
    if full == 255 and len(nz) > MAX_LABELS:
        return "soft"
    main = nz[np.argmax(nzc)]
    m = mask_hxw
    edge = np.zeros(m.shape, bool)
    edge[1:] |= m[1:] != m[:-1]
    edge[:-1] |= m[:-1] != m[1:]
    edge[:, 1:] |= m[:, 1:] != m[:, :-1]
    edge[:, :-1] |= m[:, :-1] != m[:, 1:]
    other = (m > 0) & (m != main)
    return "soft" if edge[other].mean() > 0.6 else "labels"


def _read_depth(path: Path, scale: float, transforms: Path) -> np.ndarray:
    if not path.is_file():
        raise CaptureError(f"{transforms}: depth file {path} is missing")
    if path.suffix == ".npy":
        try:
            d = np.load(path, allow_pickle=False)
        except (ValueError, OSError) as exc:
            raise CaptureError(f"cannot read depth {path} ({exc})") from exc
        if d.ndim == 3 and d.shape[2] == 1:
            d = d[..., 0]
        if d.ndim != 2:
            raise CaptureError(f"depth {path} has shape {d.shape}; expected (H, W) float32 metres")
        return d.astype(np.float32, copy=False)
    d = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if d is None or d.ndim != 2:
        raise CaptureError(f"cannot read depth {path}; expected a .npy (metres) or a 16-bit single-channel PNG")
    return (d.astype(np.float64) * scale).astype(np.float32)


def _num(doc: dict[str, Any], frame: dict[str, Any], key: str) -> float | None:
    v = frame.get(key, doc.get(key))
    return None if v is None else float(v)


def _frame_K(doc: dict[str, Any], frame: dict[str, Any], w: int, h: int, where: str) -> np.ndarray:
    fx, fy = _num(doc, frame, "fl_x"), _num(doc, frame, "fl_y")
    ax, ay = _num(doc, frame, "camera_angle_x"), _num(doc, frame, "camera_angle_y")
    if fx is None and ax is not None:
        fx = 0.5 * w / math.tan(0.5 * ax)
    if fy is None and ay is not None:
        fy = 0.5 * h / math.tan(0.5 * ay)
    if fx is None and fy is None:
        raise CaptureError(f"{where}: no focal length; give fl_x/fl_y or camera_angle_x")
    fx = fy if fx is None else fx
    fy = fx if fy is None else fy
    cx = _num(doc, frame, "cx")
    cy = _num(doc, frame, "cy")
    cx = w / 2.0 if cx is None else cx
    cy = h / 2.0 if cy is None else cy
    K = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
    if not np.all(np.isfinite(K)) or fx <= 0 or fy <= 0:
        raise CaptureError(f"{where}: intrinsics must be finite with positive focal lengths, got {K.tolist()}")
    return K


def _frame_pose(frame: dict[str, Any], where: str) -> np.ndarray:
    if "transform_matrix" not in frame:
        raise CaptureError(f"{where}: missing transform_matrix (camera-to-world, OpenGL axes)")
    try:
        T = np.array(frame["transform_matrix"], dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise CaptureError(f"{where}: transform_matrix is not a numeric matrix ({exc})") from exc
    if T.shape == (3, 4):
        T = np.vstack([T, [0.0, 0.0, 0.0, 1.0]])
    if T.shape != (4, 4):
        raise CaptureError(f"{where}: transform_matrix has shape {T.shape}; expected 4x4")
    if not np.all(np.isfinite(T)):
        raise CaptureError(f"{where}: transform_matrix contains NaN or inf")
    return gl_to_cv(T)


def load_capture(folder: str | Path, views: Sequence[int] | None = None) -> Capture:
    """Load a capture folder written by :func:`save_capture` or a NeRF-style dataset (see the module docstring).

    ``views`` selects frames by index (in that order); only their files are read.
    """
    tpath = find_transforms(folder)
    root = tpath.parent
    try:
        doc = json.loads(tpath.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise CaptureError(f"{tpath}: cannot parse JSON ({exc})") from exc
    if not isinstance(doc, dict) or not isinstance(doc.get("frames"), list) or not doc["frames"]:
        raise CaptureError(f"{tpath}: needs a non-empty 'frames' list")
    frames_all: list[dict[str, Any]] = doc["frames"]
    indices = list(range(len(frames_all))) if views is None else [int(i) for i in views]
    bad = [i for i in indices if not 0 <= i < len(frames_all)]
    if bad or not indices:
        raise CaptureError(f"{tpath}: view indices {bad or indices} out of range; it has {len(frames_all)} frames")
    from torm.capture.lens import Lens, undistort

    undistorted: dict[str, Any] = {}
    maps_cache: dict[Any, Any] = {}
    depth_scale = float(doc.get("depth_unit_scale_factor", 1e-3))

    object_ids = tuple(int(i) for i in doc.get("object_ids") or ())
    object_names = tuple(str(n) for n in doc.get("object_names") or ())
    if object_names and len(object_names) != len(object_ids):
        raise CaptureError(
            f"{tpath}: object_names has {len(object_names)} entries but object_ids has {len(object_ids)}; "
            "give one name per id"
        )

    out: list[CameraView] = []
    hw: tuple[int, int] | None = None
    alpha_used = False
    soft_frames: list[int] = []
    many_ids: list[tuple[int, int]] = []
    for i in indices:
        frame = frames_all[i]
        where = f"{tpath} frame {i}"
        if not isinstance(frame, dict):
            raise CaptureError(f"{where}: a frame must be a JSON object")
        rgb = alpha = mask = None
        label = str(frame.get("name", ""))
        if frame.get("file_path"):
            ipath = _resolve_image(root, str(frame["file_path"]), tpath)
            rgb, alpha = _read_image(ipath)
            label = label or ipath.stem
            size_src = ipath
        elif not frame.get("mask_path"):
            raise CaptureError(f"{where}: has neither file_path nor mask_path")
        if frame.get("mask_path"):
            mpath = root / str(frame["mask_path"])
            mask, full = _read_mask(mpath, tpath)
            label = label or mpath.stem
            if rgb is not None and mask.shape != rgb.shape[:2]:
                raise CaptureError(
                    f"mask {mpath} is {mask.shape[1]}x{mask.shape[0]} but image {size_src} is "
                    f"{rgb.shape[1]}x{rgb.shape[0]}; masks must match their images"
                )
            if rgb is None:
                size_src = mpath
            if object_ids:
                extra = sorted(set(np.unique(mask).tolist()) - {0, *object_ids})
                if extra:
                    raise CaptureError(f"mask {mpath} holds ids {extra} that are not in object_ids {list(object_ids)}")
            else:
                kind = mask_kind(mask, full)
                if kind == "soft":  # greyscale coverage / alpha: foreground where it is at least half
                    mask = (mask >= 0.5 * full).astype(np.int32)
                    soft_frames.append(i)
                elif kind == "binary" and mask.max() in (255, 65535):
                    mask = (mask > 0).astype(np.int32)  # a binary 0/255 foreground mask (nerfstudio style): object 1
                else:
                    n_ids = int(np.count_nonzero(np.bincount(mask.ravel())[1:]))
                    if n_ids > MAX_LABELS:
                        many_ids.append((i, n_ids))
        elif alpha is not None:
            mask = alpha.astype(np.int32)
            alpha_used = True
        img_hw = (rgb if rgb is not None else mask).shape[:2]
        w_decl, h_decl = _num(doc, frame, "w"), _num(doc, frame, "h")
        if (w_decl is not None and int(w_decl) != img_hw[1]) or (h_decl is not None and int(h_decl) != img_hw[0]):
            raise CaptureError(
                f"{size_src} is {img_hw[1]}x{img_hw[0]} but {tpath} declares w={w_decl} h={h_decl}; "
                "fix w/h or resize the image"
            )
        if hw is not None and img_hw != hw:
            raise CaptureError(f"{size_src} is {img_hw[1]}x{img_hw[0]} but earlier frames are {hw[1]}x{hw[0]}")
        hw = img_hw
        depths: dict[str, np.ndarray | None] = {"depth": None, "sensor_depth": None}
        for key, name in (("depth_file_path", "depth"), ("sensor_depth_file_path", "sensor_depth")):
            if frame.get(key):
                dpath = root / str(frame[key])
                d = _read_depth(dpath, depth_scale, tpath)
                if d.shape != img_hw:
                    raise CaptureError(
                        f"depth {dpath} is {d.shape[1]}x{d.shape[0]} but image {size_src} is {img_hw[1]}x{img_hw[0]}"
                    )
                depths[name] = d
        ref = None
        if frame.get("reference_file_path"):
            ref, _ = _read_image(_resolve_image(root, str(frame["reference_file_path"]), tpath))
            if ref.shape[:2] != img_hw:
                raise CaptureError(f"{where}: reference image {frame['reference_file_path']} is {ref.shape[1]}x"
                                   f"{ref.shape[0]} but the frame is {img_hw[1]}x{img_hw[0]}; record the reference "
                                   "pass with the same camera settings")
        K = _frame_K(doc, frame, img_hw[1], img_hw[0], where)
        try:
            lens = Lens.from_json(doc, frame)
        except CaptureError as exc:
            raise CaptureError(f"{where}: {exc}") from exc
        if not lens.is_pinhole:  # resample everything onto the pinhole camera with the same K
            key = (lens, K.tobytes(), img_hw)
            if key not in maps_cache:
                maps_cache[key] = lens.undistort_maps(K, img_hw[1], img_hw[0])
            mp = maps_cache[key]
            rgb = undistort(rgb, mp) if rgb is not None else None
            ref = undistort(ref, mp) if ref is not None else None
            mask = undistort(mask, mp, nearest=True) if mask is not None else None
            depths = {k: undistort(d, mp, nearest=True) if d is not None else None for k, d in depths.items()}
            undistorted.setdefault(json.dumps(lens.to_json(), sort_keys=True), []).append((i, label))
        T = _frame_pose(frame, where)
        try:
            out.append(CameraView(K=K, T_world_cam=T, rgb=rgb, mask=mask, name=label, reference_rgb=ref, **depths))
        except CaptureError as exc:
            raise CaptureError(f"{where}: {exc}") from exc

    if soft_frames:
        log.info("%s: %d of %d masks are soft (greyscale coverage or alpha, e.g. frame %d); thresholded at 0.5 into "
                 "one object (id 1)", tpath, len(soft_frames), len(indices), soft_frames[0])
    if many_ids:
        log.warning("%s: %d mask(s) hold more than %d instance ids (frame %d: %d); if these are greyscale values, "
                    "not ids, store binary or soft 8-bit masks", tpath, len(many_ids), MAX_LABELS, *many_ids[0])
    if not object_ids and alpha_used:
        object_ids, object_names = (1,), ("object",)
    elif not object_ids and any(v.mask is not None for v in out):
        object_ids = tuple(sorted({int(k) for v in out if v.mask is not None for k in np.unique(v.mask) if k > 0}))
    bounds = doc.get("workspace_bounds")
    table = doc.get("table_height")
    seed = doc.get("seed")
    meta = dict(doc.get("metadata") or {})
    if undistorted:
        # the view names let no_evidence_masks find each view's lens again (after subset, segmentation, a reload)
        meta["undistorted"] = [{**json.loads(k), "frames": [i for i, _ in v], "names": [n for _, n in v]}
                               for k, v in undistorted.items()]
        log.info("%s: lens distortion undone on %d frame(s) (%s)", tpath, sum(len(v) for v in undistorted.values()),
                 "; ".join(k for k in undistorted))
    try:
        return Capture(
            views=tuple(out),
            scenario=str(doc.get("scenario") or root.name),
            seed=None if seed is None else int(seed),
            object_ids=object_ids,
            object_names=object_names,
            table_height=None if table is None else float(table),
            workspace_bounds=None if bounds is None else np.asarray(bounds, dtype=np.float64),
            metadata=meta,
        )
    except CaptureError as exc:
        raise CaptureError(f"{tpath}: {exc}") from exc
