"""The realism profile of the simulated world: sourced parameter ranges, drawn per trial into a frozen record.

``world.realism`` names a profile (:data:`PROFILES`):

- ``ideal``: nominal physics and exact sensing, i.e. the world as built without this module (pads mu 1.0,
  objects 0.5 on a 0.6 table, the pick's requested grip force, library masses, exact cameras, exact tracking).
  Its record holds no values, so nothing is changed and results are those of the world without realism.
- ``measured``: every parameter of :class:`MeasuredRanges` drawn uniformly from a range whose source is
  named in :data:`SOURCES` (the table in ``sim/REALISM.md`` mirrors them).
- ``stress``: **not realism**: every parameter at the worst end of its sourced range pushed ``world.stress`` times
  further (:meth:`MeasuredRanges.stressed`; 1 = the worst sourced value). For margin sweeps
  (``benchmarks/stress.py``): how far beyond the sources a factor can go before picks fail. No value of this
  profile has a source, and none is a default.

Parameters come in factor groups (:data:`FACTORS`); ``world.factors`` may restrict the draws to some groups,
the others staying ideal (the fidelity report's sensitivity table runs each group alone). Each group draws
from its own random stream seeded by ``(trial seed, group)``, so a group's values do not depend on which
other groups are active: the sensitivity runs and the full ``measured`` run see the same values.

Who reads the record (:class:`RealismRecord`):

- :func:`apply_physics` (the world builder): pad and object friction, object masses (before settling);
- :func:`perturb_capture` (the simulated backend's capture): the camera poses and intrinsics *reported* with
  each view; the images are rendered with the true cameras;
- :class:`ExecutionErrors` (the simulated backend's stepping): controller latency and joint tracking error
  of the position-controlled arm joints;
- the trial (:mod:`torm.pipeline`): the requested pad force replaces ``pick.grip_force``.

Units: m, rad, s, N, kg; camera poses ``T_world_cam`` in OpenCV axes.
"""

from __future__ import annotations

import dataclasses
import math
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
from scipy.spatial.transform import Rotation

from torm.errors import ConfigError, UnknownNameError

if TYPE_CHECKING:
    import mujoco

    from torm.types import Capture

#: Realism profiles (``world.realism``); mirrors ``torm.pipeline.REALISM_PROFILES``.
PROFILES: tuple[str, ...] = ("ideal", "measured", "stress")
#: Factor groups of a profile (``world.factors``); mirrors ``torm.pipeline.REALISM_FACTORS``.
FACTORS: tuple[str, ...] = ("contact", "grip_force", "objects", "calibration", "execution")

#: Nominal width (px) the principal-point error is stated at (the D455 colour stream, 1280 x 720).
NOMINAL_WIDTH_PX = 1280
#: Horizontal reach of the Inovo medium preset to the flange (m, HARDWARE.md): turns the arm's position
#: repeatability into a joint-angle error.
ARM_REACH_M = 1.083
#: Lever (m) that turns the flange's position repeatability into an orientation jitter of a wrist camera
#: (about the flange-to-camera distance of a wrist-mounted D455).
CAMERA_LEVER_M = 0.1

#: Where every range comes from (keys of :attr:`Range.source`). ``sim/REALISM.md`` shows the same table.
SOURCES: dict[str, str] = {
    "pad_friction": (
        "Robotiq Hand-E manual: silicone fingertips rated at static mu 0.3 (on lubricated steel; the payload "
        "rule W = 2 F mu / 2.4 uses it); fingertip on wet glass 0.53-0.78 (REALISM.md). The upper end excludes "
        "clean, dry, tacky silicone (about 1.0, the ideal profile); MuJoCo Menagerie's 2F-85 uses 0.7."),
    "pad_torsion": (
        "computed: torsional coefficient = mu x lever; lever = L/4 = 9.4 mm for a uniform line contact along "
        "the 37.5 mm pad (HARDWARE.md) down to 3.6 mm = 3 pi a / 16 for a Hertz patch of radius a = 6.1 mm "
        "(30 mm glass ball on a silicone pad, E about 1.5 MPa, 20 N)."),
    "object_friction": "glass on glass sliding 0.4, glass on metal 0.5-0.7 (REALISM.md); table = same value.",
    "grip_force": (
        "Robotiq 2F-85: 20-235 N over the force register 0-255 (HARDWARE.md); fragile parts: start at "
        "20-30 % force (Telekinesis Robotiq 2F-85 guide) -> 20 N (0 %) to 85 N (30 %, linear map). The paper "
        "states no force setting."),
    "wall_tolerance": (
        "DURAN borosilicate tubing wall tolerances +-4-5 % (e.g. 1.5 +- 0.08 mm, 1.2 +- 0.05 mm; DWK DURAN "
        "tubing table): mass of thin-walled glassware +-5 %. Solid objects keep their library mass."),
    "hand_eye": (
        "translation 0.28 mm (flange-based hand-eye calibration of cobots with an industrial 3D scanner, "
        "arXiv 2407.16041) to 1.5 mm (RealSense eye-in-hand, lixiny/Handeye-Calibration-ROS issue 2); rotation "
        "0.01-0.25 deg: camera ray-angle repeatability of careful vs standard intrinsic calibration "
        "(Skip Robotics, 'Repeatability of intrinsic calibration'), 0.25 deg also the flange-based bound."),
    "repeatability": (
        "ISO 9283 position repeatability of cobots: UR5e +-0.03 mm, Franka +-0.1 mm (datasheets); the Inovo's "
        "is not published. Per view: N(0, (r/3)^2) per axis; orientation r/3 over a 0.1 m lever."),
    "intrinsics": (
        "computed from Skip Robotics' 0.25 deg ray-angle variation of standard calibration tools on a 90 deg "
        "lens: focal scale +-0.87 % (0.25 deg at the 45 deg image edge), principal point +-2.7 px "
        "(0.25 deg x 623 px focal length at 1280 px)."),
    "latency": (
        "ROS 1 service round trip 10 ms direct, 40 ms through rosbridge (RobotWebTools/rosbridge_suite issue "
        "868); the Inovo is driven through rosbridge (HARDWARE.md)."),
    "tape_measure": (
        "a lab measures the table height and places a fixture with a steel tape: EU Measuring Instruments "
        "Directive 2004/22/EC, Annex MI-008, class II maximum permissible error +-(0.3 + 0.2 L) mm (L in m, rounded "
        "up: +-0.5 mm up to 1 m) plus half of the 1 mm graduation read by eye (+-0.5 mm): +-1 mm per length; "
        "a fixture's yaw from two such lengths 0.1 m apart: +-atan(2 x 1 mm / 100 mm) = +-1.15 deg."),
    "joint_tracking": (
        "repeatability r (see 'repeatability') as a per-motion static joint error: N(0, (r / 3 / 1.083 m)^2) "
        "rad per joint (1.083 m = Inovo medium reach, HARDWARE.md)."),
}


@dataclass(frozen=True)
class Range:
    """A uniform range ``[lo, hi]`` in ``unit``, with the key of its source in :data:`SOURCES`."""

    lo: float
    hi: float
    unit: str
    source: str

    def __post_init__(self) -> None:
        if not (math.isfinite(self.lo) and math.isfinite(self.hi) and self.lo <= self.hi):
            raise ConfigError(f"Range needs finite lo <= hi, got [{self.lo}, {self.hi}] {self.unit}")
        if self.source not in SOURCES:
            raise UnknownNameError("realism source", self.source, SOURCES)

    def draw(self, rng: np.random.Generator) -> float:
        """One uniform draw (``lo`` when the range is a point)."""
        return float(rng.uniform(self.lo, self.hi)) if self.hi > self.lo else float(self.lo)

    def contains(self, value: float, tol: float = 1e-12) -> bool:
        return self.lo - tol <= value <= self.hi + tol


@dataclass(frozen=True)
class MeasuredRanges:
    """The ``measured`` profile: one sourced range per parameter (see :data:`SOURCES`)."""

    pad_friction: Range = Range(0.30, 0.78, "", "pad_friction")
    pad_torsion_lever: Range = Range(0.0036, 0.0094, "m", "pad_torsion")
    object_friction: Range = Range(0.40, 0.70, "", "object_friction")
    grip_force: Range = Range(20.0, 85.0, "N", "grip_force")
    hollow_mass_scale: Range = Range(0.95, 1.05, "", "wall_tolerance")
    hand_eye_translation: Range = Range(0.28e-3, 1.5e-3, "m", "hand_eye")
    hand_eye_rotation: Range = Range(math.radians(0.01), math.radians(0.25), "rad", "hand_eye")
    arm_repeatability: Range = Range(0.03e-3, 0.1e-3, "m", "repeatability")
    focal_error: Range = Range(-0.0087, 0.0087, "", "intrinsics")
    principal_point_error: Range = Range(-2.7, 2.7, "px at 1280 px", "intrinsics")
    latency: Range = Range(0.010, 0.040, "s", "latency")
    table_height_error: Range = Range(-1.0e-3, 1.0e-3, "m", "tape_measure")
    fixture_position_error: Range = Range(-1.0e-3, 1.0e-3, "m", "tape_measure")
    fixture_yaw_error: Range = Range(-math.atan(2e-3 / 0.1), math.atan(2e-3 / 0.1), "rad", "tape_measure")

    def table(self) -> list[dict[str, Any]]:
        """One row per parameter: name, lo, hi, unit, factor, source text (for docs and reports)."""
        factor_of = {"pad_friction": "contact", "pad_torsion_lever": "contact", "object_friction": "contact",
                     "grip_force": "grip_force", "hollow_mass_scale": "objects",
                     "hand_eye_translation": "calibration", "hand_eye_rotation": "calibration",
                     "arm_repeatability": "calibration, execution", "focal_error": "calibration",
                     "principal_point_error": "calibration", "latency": "execution",
                     "table_height_error": "calibration", "fixture_position_error": "calibration",
                     "fixture_yaw_error": "calibration"}
        out = []
        for f in dataclasses.fields(self):
            r: Range = getattr(self, f.name)
            out.append({"parameter": f.name, "lo": r.lo, "hi": r.hi, "unit": r.unit, "factor": factor_of[f.name],
                        "source": SOURCES[r.source]})
        return out


    def stressed(self, k: float) -> MeasuredRanges:
        """Every range collapsed to its worst end pushed ``k`` (>= 1) times further (:data:`WORSE`): a value that
        is worse when lower is divided by ``k`` (pad friction 0.30 -> 0.15 at k = 2), one worse when higher has its
        deviation multiplied by ``k`` (hand-eye 1.5 mm -> 3 mm; mass scale 1.05 -> 1.10; focal error +0.87 % ->
        +1.74 %, the sign fixed to +). ``k = 1`` is the worst end of each sourced range."""
        if not (math.isfinite(k) and k >= 1):
            raise ConfigError(f"stress multiplier must be a finite number >= 1 (1 = the worst sourced value), got {k}")
        out = {}
        for f in dataclasses.fields(self):
            r: Range = getattr(self, f.name)
            if WORSE[f.name] == "lower":
                v = r.lo / k
            elif WORSE[f.name] == "magnitude":  # a signed error: its larger end, k times (the sign kept +)
                v = max(abs(r.lo), abs(r.hi)) * k
            elif f.name == "hollow_mass_scale":
                v = 1.0 + (r.hi - 1.0) * k
            else:
                v = r.hi * k
            out[f.name] = Range(v, v, r.unit, r.source)
        return MeasuredRanges(**out)


#: Which direction makes each parameter of :class:`MeasuredRanges` harder for a pick (stress sweeps).
WORSE: dict[str, str] = {
    "pad_friction": "lower", "pad_torsion_lever": "lower", "object_friction": "lower", "grip_force": "lower",
    "hollow_mass_scale": "higher", "hand_eye_translation": "higher", "hand_eye_rotation": "higher",
    "arm_repeatability": "higher", "focal_error": "higher", "principal_point_error": "higher", "latency": "higher",
    "table_height_error": "magnitude", "fixture_position_error": "magnitude", "fixture_yaw_error": "magnitude",
}

MEASURED = MeasuredRanges()


@dataclass(frozen=True)
class RealismRecord:
    """The realism values of one trial; ``None`` = leave the ideal (as-built) value. Units m, rad, s, N.

    Attributes:
        profile, seed, factors: what produced the record (``factors``: the groups that were drawn).
        stress: the stress multiplier (profile ``stress`` only).
        pad_friction: sliding mu of the gripper pads (the pads have contact priority, so it governs pad contacts).
        pad_torsional: torsional friction coefficient of the pads (m).
        object_friction: sliding mu of the objects' collision geoms and of the table top.
        grip_force_n: requested pad force (N) passed to the pick as ``pick.grip_force``.
        object_mass_scale: per instance (index k-1) multiplier of the library mass and inertia.
        hand_eye_rotvec, hand_eye_translation: the hand-eye calibration error, one per trial, as a transform in
            the camera frame: ``T_world_cam_reported = T_world_cam_true @ T_err`` (rad, m).
        arm_repeatability_m: position repeatability r (m): per-view pose jitter and per-motion joint error.
        focal_scale: reported fx, fy = true x this.
        principal_point_offset_px: reported (cx, cy) offset in px at :data:`NOMINAL_WIDTH_PX` (scaled with the width).
        latency_s: controller latency of the arm's joint targets (s).
        joint_error_std_rad: std of the per-motion static joint tracking error (rad).
        table_height_error_m: declared table height minus the true one (m): the lab's tape measurement.
        fixture_error: declared fixture pose minus the true one, (dx, dy, dyaw) in the world (m, m, rad).
    """

    profile: str = "ideal"
    seed: int = 0
    factors: tuple[str, ...] = ()
    stress: float | None = None
    pad_friction: float | None = None
    pad_torsional: float | None = None
    object_friction: float | None = None
    grip_force_n: float | None = None
    object_mass_scale: tuple[float, ...] | None = None
    hand_eye_rotvec: tuple[float, float, float] | None = None
    hand_eye_translation: tuple[float, float, float] | None = None
    arm_repeatability_m: float | None = None
    focal_scale: float | None = None
    principal_point_offset_px: tuple[float, float] | None = None
    latency_s: float | None = None
    joint_error_std_rad: float | None = None
    table_height_error_m: float | None = None
    fixture_error: tuple[float, float, float] | None = None

    def __post_init__(self) -> None:
        if self.profile not in PROFILES:
            raise UnknownNameError("world.realism", self.profile, PROFILES)
        for f in self.factors:
            if f not in FACTORS:
                raise UnknownNameError("world.factors entry", f, FACTORS)
        for name in ("pad_friction", "pad_torsional", "object_friction", "grip_force_n", "arm_repeatability_m",
                     "latency_s", "joint_error_std_rad"):
            v = getattr(self, name)
            if v is not None and not (math.isfinite(v) and v >= 0):
                raise ConfigError(f"RealismRecord.{name} must be a finite number >= 0, got {v}")
        if self.focal_scale is not None and not self.focal_scale > 0:
            raise ConfigError(f"RealismRecord.focal_scale must be > 0, got {self.focal_scale}")

    @property
    def is_ideal(self) -> bool:
        """True when the record changes nothing."""
        return all(getattr(self, f.name) is None for f in dataclasses.fields(self)
                   if f.name not in ("profile", "seed", "factors", "stress"))

    @property
    def T_cam_err(self) -> np.ndarray:
        """(4, 4) hand-eye error in the camera frame (identity when not drawn)."""
        T = np.eye(4)
        if self.hand_eye_rotvec is not None:
            T[:3, :3] = Rotation.from_rotvec(self.hand_eye_rotvec).as_matrix()
        if self.hand_eye_translation is not None:
            T[:3, 3] = self.hand_eye_translation
        return T

    def as_dict(self) -> dict[str, Any]:
        """JSON-ready values (tuples as lists), plus the hand-eye error magnitudes in mm and deg."""
        d = {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}
        for k, v in d.items():
            if isinstance(v, tuple):
                d[k] = list(v)
        if self.hand_eye_rotvec is not None:
            d["hand_eye_rotation_deg"] = math.degrees(float(np.linalg.norm(self.hand_eye_rotvec)))
        if self.hand_eye_translation is not None:
            d["hand_eye_translation_mm"] = 1e3 * float(np.linalg.norm(self.hand_eye_translation))
        return d


def _stream(seed: int, *key: int) -> np.random.Generator:
    """An independent generator for (trial seed, key...); 0x7EA1 separates it from the layout seed's stream."""
    return np.random.default_rng(np.random.SeedSequence([int(seed) & 0xFFFFFFFF, 0x7EA1, *key]))


def _unit_vector(rng: np.random.Generator) -> np.ndarray:
    v = rng.normal(size=3)
    return v / max(float(np.linalg.norm(v)), 1e-12)


def sample_realism(profile: str, seed: int, hollow: Sequence[bool] = (), factors: Sequence[str] = (),
                   ranges: MeasuredRanges = MEASURED, stress: float = 1.0) -> RealismRecord:
    """Draw the realism record of one trial.

    Args:
        profile: ``ideal`` (returns an empty record) or ``measured``.
        seed: the trial seed.
        hollow: per scenario object (instance order), whether it is thin-walled glassware (mass tolerance).
        factors: the factor groups to draw (empty: all of :data:`FACTORS`); the others stay ideal.
        ranges: the ranges of the ``measured`` profile.
        stress: profile ``stress`` only: the multiplier of :meth:`MeasuredRanges.stressed` (>= 1).
    """
    if profile not in PROFILES:
        raise UnknownNameError("world.realism", profile, PROFILES)
    for f in factors:
        if f not in FACTORS:
            raise UnknownNameError("world.factors entry", f, FACTORS)
    if profile == "ideal":
        return RealismRecord(profile="ideal", seed=int(seed))
    active = tuple(f for f in FACTORS if not factors or f in factors)
    r = ranges.stressed(stress) if profile == "stress" else ranges
    kw: dict[str, Any] = {"stress": float(stress)} if profile == "stress" else {}
    if "contact" in active:
        g = _stream(seed, FACTORS.index("contact"))
        mu = r.pad_friction.draw(g)
        kw.update(pad_friction=mu, pad_torsional=mu * r.pad_torsion_lever.draw(g),
                  object_friction=r.object_friction.draw(g))
    if "grip_force" in active:
        kw["grip_force_n"] = r.grip_force.draw(_stream(seed, FACTORS.index("grip_force")))
    if "objects" in active:
        g = _stream(seed, FACTORS.index("objects"))
        kw["object_mass_scale"] = tuple(r.hollow_mass_scale.draw(g) if h else 1.0 for h in hollow)
    # The arm's repeatability feeds both the view jitter (calibration) and the joint error (execution): one draw.
    rep = r.arm_repeatability.draw(_stream(seed, 99))
    if "calibration" in active:
        g = _stream(seed, FACTORS.index("calibration"))
        kw.update(hand_eye_rotvec=tuple(float(x) for x in _unit_vector(g) * r.hand_eye_rotation.draw(g)),
                  hand_eye_translation=tuple(float(x) for x in _unit_vector(g) * r.hand_eye_translation.draw(g)),
                  arm_repeatability_m=rep, focal_scale=1.0 + r.focal_error.draw(g),
                  principal_point_offset_px=(r.principal_point_error.draw(g), r.principal_point_error.draw(g)))
        # the declared calibration's errors: their own stream, so the draws above are those of earlier versions
        gd = _stream(seed, FACTORS.index("calibration"), 1)
        kw.update(table_height_error_m=r.table_height_error.draw(gd),
                  fixture_error=(r.fixture_position_error.draw(gd), r.fixture_position_error.draw(gd),
                                 r.fixture_yaw_error.draw(gd)))
    if "execution" in active:
        g = _stream(seed, FACTORS.index("execution"))
        kw.update(latency_s=r.latency.draw(g), joint_error_std_rad=rep / 3.0 / ARM_REACH_M)
        kw.setdefault("arm_repeatability_m", rep)
    return RealismRecord(profile=profile, seed=int(seed), factors=active, **kw)


# ------------------------------------------------------------------------------------------------ physics

def sample_scenario_realism(profile: str, scenario: str, seed: int, factors: Sequence[str] = (),
                            stress: float = 1.0) -> RealismRecord:
    """:func:`sample_realism` for a scenario by name: its objects' hollowness comes from the object library."""
    from sim.scenes.objects import get_object
    from sim.scenes.scenario import get_scenario

    hollow = [get_object(n).hollow for n in get_scenario(scenario).objects]
    return sample_realism(profile, seed, hollow, factors, stress=stress)

def apply_physics(record: RealismRecord, model: mujoco.MjModel, object_body_ids: Sequence[int],
                  object_geom_ids: Sequence[int], pad_geom_ids: Sequence[int], table_geom_id: int | None) -> None:
    """Write the record's contact and mass values into a compiled model (before the world settles).

    Friction: the pads' sliding/torsional coefficients (the pads have contact priority, so they govern every pad
    contact); the objects' and the table top's sliding coefficient (MuJoCo takes the larger of two geoms of
    equal priority, so both get the drawn glass-on-surface value). Masses: body mass and inertia of object
    ``k`` scaled by ``object_mass_scale[k-1]`` (a uniform wall-thickness change scales both; the centre of mass
    stays). Nothing changes for ``None`` entries.
    """
    if record.pad_friction is not None:
        for g in pad_geom_ids:
            model.geom_friction[g, 0] = record.pad_friction
            if record.pad_torsional is not None:
                model.geom_friction[g, 1] = record.pad_torsional
    if record.object_friction is not None:
        for g in object_geom_ids:
            model.geom_friction[g, 0] = record.object_friction
        if table_geom_id is not None:
            model.geom_friction[table_geom_id, 0] = record.object_friction
    if record.object_mass_scale is not None:
        if len(record.object_mass_scale) != len(object_body_ids):
            raise ConfigError(f"realism record has {len(record.object_mass_scale)} object mass scales for "
                              f"{len(object_body_ids)} objects; sample it for this scenario")
        for b, s in zip(object_body_ids, record.object_mass_scale, strict=True):
            model.body_mass[b] *= s
            model.body_inertia[b] *= s


# ------------------------------------------------------------------------------------------------ cameras
def perturb_capture(record: RealismRecord, capture: Capture, capture_index: int = 0
                    ) -> tuple[Capture, dict[str, Any]]:
    """The capture as the pipeline receives it: same images, reported poses and intrinsics with the errors.

    ``T_world_cam_reported = T_world_cam_true @ T_cam_err @ J_i`` with the trial's hand-eye error ``T_cam_err``
    and a per-view jitter ``J_i`` (translation N(0, (r/3)^2) per axis, rotation N(0, (r/3 / 0.1 m)^2) per axis,
    r = arm repeatability, drawn from the stream of (seed, capture_index)); ``K`` with the focal scale and
    principal point offset. Returns the capture and a summary (RMS jitter in mm / deg).
    """
    calibration = (record.hand_eye_rotvec is not None or record.focal_scale is not None
                   or record.principal_point_offset_px is not None)
    if not calibration:
        return capture, {}
    rng = _stream(record.seed, 100 + int(capture_index))
    T_err = record.T_cam_err
    sig_t = (record.arm_repeatability_m or 0.0) / 3.0 if record.hand_eye_rotvec is not None else 0.0
    sig_r = sig_t / CAMERA_LEVER_M
    views, jit_t, jit_r = [], [], []
    for v in capture.views:
        J = np.eye(4)
        if sig_t > 0:
            rv = rng.normal(scale=sig_r, size=3)
            J[:3, :3] = Rotation.from_rotvec(rv).as_matrix()
            J[:3, 3] = rng.normal(scale=sig_t, size=3)
            jit_t.append(float(np.linalg.norm(J[:3, 3])))
            jit_r.append(float(np.linalg.norm(rv)))
        T = v.T_world_cam @ T_err @ J
        K = v.K.copy()
        if record.focal_scale is not None:
            K[0, 0] *= record.focal_scale
            K[1, 1] *= record.focal_scale
        if record.principal_point_offset_px is not None:
            s = v.width / NOMINAL_WIDTH_PX
            K[0, 2] += record.principal_point_offset_px[0] * s
            K[1, 2] += record.principal_point_offset_px[1] * s
        views.append(v.with_(T_world_cam=T, K=K))
    meta = dict(capture.metadata)
    meta["realism_calibration"] = {"reported_poses": "true pose x hand-eye error x per-view jitter",
                                   "capture_index": int(capture_index)}
    out = dataclasses.replace(capture, views=tuple(views), metadata=meta)
    summary = {"capture_index": int(capture_index), "views": len(views),
               "view_jitter_rms_mm": 1e3 * float(np.sqrt(np.mean(np.square(jit_t)))) if jit_t else 0.0,
               "view_jitter_rms_deg": math.degrees(float(np.sqrt(np.mean(np.square(jit_r))))) if jit_r else 0.0}
    return out, summary


# ------------------------------------------------------------------------------------------------ execution
class ExecutionErrors:
    """Controller latency and joint tracking error of position-controlled arm joints, applied at every physics tick.

    The arm writes the *commanded* joint targets into ``data.ctrl``; :meth:`step` swaps in what the servo actually
    tracks -- the command of ``latency`` ago plus the current motion's static joint error -- for the physics step
    and puts the command back afterwards, so everything that reads ``ctrl`` (the trajectory's start, safety
    checks, a TCP-tracking check comparing commanded and measured poses) sees the command. A new error is drawn
    per motion (:meth:`new_motion`) and blended in over that motion, so the arm never jumps.

    Args:
        record: the trial's realism record (``latency_s``, ``joint_error_std_rad``).
        actuator_ids: the arm's position actuators.
        control_dt: the period of :meth:`step` (s).
    """

    def __init__(self, record: RealismRecord, actuator_ids: Sequence[int], control_dt: float) -> None:
        self.act = np.asarray(actuator_ids, dtype=int)
        self.delay_ticks = int(round((record.latency_s or 0.0) / control_dt))
        self.std = float(record.joint_error_std_rad or 0.0)
        self._seed = record.seed
        self.latency_s = self.delay_ticks * control_dt
        self.reset()

    def reset(self) -> None:
        """Forget the command history and the current error and restart the error stream (after a world reset),
        so that the same commands after a reset meet the same errors (an env's same seed, same outcome)."""
        self.rng = _stream(self._seed, 200)
        self.n_motions = 0
        self.max_abs_error = 0.0
        n = len(self.act)
        self._fifo: deque[np.ndarray] = deque(maxlen=self.delay_ticks + 1)
        self._e_from = np.zeros(n)
        self._e_to = np.zeros(n)
        self._blend_ticks = 1
        self._tick = 0

    def _error(self) -> np.ndarray:
        s = min(1.0, self._tick / self._blend_ticks)
        return self._e_from + s * (self._e_to - self._e_from)

    def new_motion(self, duration_ticks: int) -> None:
        """Draw the next motion's static joint error, blended in over ``duration_ticks`` control ticks."""
        self._e_from = self._error()
        self._e_to = self.rng.normal(scale=self.std, size=len(self.act)) if self.std > 0 else np.zeros(len(self.act))
        self._blend_ticks = max(1, int(duration_ticks))
        self._tick = 0
        self.n_motions += 1
        if self.std > 0:
            self.max_abs_error = max(self.max_abs_error, float(np.max(np.abs(self._e_to))))

    def step(self, model: mujoco.MjModel, data: mujoco.MjData, nstep: int) -> None:
        """One control tick: step physics ``nstep`` times with the delayed, offset arm targets."""
        import mujoco

        cmd = data.ctrl[self.act].copy()
        if not self._fifo:
            self._fifo.extend([cmd] * (self.delay_ticks + 1))
        else:
            self._fifo.append(cmd)
        data.ctrl[self.act] = self._fifo[0] + self._error()
        try:
            mujoco.mj_step(model, data, nstep=nstep)
        finally:
            data.ctrl[self.act] = cmd
        self._tick += 1

    def summary(self) -> dict[str, Any]:
        return {"latency_s": self.latency_s, "joint_error_std_rad": self.std, "motions": self.n_motions,
                "max_abs_joint_error_rad": self.max_abs_error}


__all__ = ["ARM_REACH_M", "CAMERA_LEVER_M", "FACTORS", "MEASURED", "NOMINAL_WIDTH_PX", "PROFILES", "SOURCES",
           "ExecutionErrors", "MeasuredRanges", "Range", "RealismRecord", "apply_physics", "perturb_capture",
           "sample_realism", "sample_scenario_realism"]
