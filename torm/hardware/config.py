"""Hardware settings for ``--backend real``: one frozen config loaded from a YAML.

Example ``hardware.yaml`` (paths relative to the YAML's folder)::

    host: 192.168.1.10        # Inovo controller running rosbridge_server
    port: 9090
    armed: false              # or --arm-robot / TORM_ARM_ROBOT=1; nothing moves unless armed
    dry_run: false            # log planned motions, send nothing
    speed_scale: 0.25         # fraction of the joint speed/acceleration limits
    command_log: logs/hardware_commands.jsonl
    gripper: {device: /dev/ttyUSB0, calibration: robotiq_cal.yaml}   # or socket://host:port (RS-485 gateway)
    camera: {hand_eye: hand_eye.yaml}
    stream: {horizon_s: 0.3, period_s: 0.1}   # the arm stops by itself <= horizon + braking after the link dies

Where the config comes from (:func:`resolve_hardware_config`): the trial config's
``hardware_config`` field when it has one, else the environment variable ``TORM_HARDWARE_CONFIG``.
``armed`` is also switched on by a trial-config field ``arm_robot: true`` or ``TORM_ARM_ROBOT=1``.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from torm.config import check_finite, from_dict, load_yaml
from torm.errors import ConfigError
from torm.hardware.streaming import StreamSettings

ENV_CONFIG = "TORM_HARDWARE_CONFIG"
ENV_ARMED = "TORM_ARM_ROBOT"


@dataclass(frozen=True)
class GripperSettings:
    """Robotiq 2F-85 on Modbus RTU: serial device, slave id, baud rate, read timeout (s), calibration YAML."""

    device: str = "/dev/ttyUSB0"
    slave: int = 9
    baudrate: int = 115200
    timeout_s: float = 0.2
    calibration: str | None = None
    move_timeout_s: float = 5.0
    activate: bool = True

    def __post_init__(self) -> None:
        if not 1 <= self.slave <= 247:
            raise ConfigError(f"gripper.slave must be 1..247, got {self.slave}")
        if self.timeout_s <= 0 or self.move_timeout_s <= 0:
            raise ConfigError("gripper.timeout_s and gripper.move_timeout_s must be positive (s)")


@dataclass(frozen=True)
class CameraSettings:
    """RealSense D455 colour (+ aligned depth) stream and the hand-eye YAML giving T_flange_cam."""

    serial: str | None = None
    width: int = 1280
    height: int = 720
    fps: int = 30
    depth: bool = True
    hand_eye: str | None = None
    warmup_frames: int = 15
    timeout_ms: int = 5000

    def __post_init__(self) -> None:
        if self.width <= 0 or self.height <= 0 or self.fps <= 0:
            raise ConfigError("camera.width, camera.height and camera.fps must be positive")


@dataclass(frozen=True)
class RealCaptureSettings:
    """Wrist-camera capture poses: a Fibonacci band on the hemisphere around ``centre`` (m, deg, s)."""

    radius: float = 0.5
    centre: tuple[float, float, float] = (0.55, 0.0, 0.0)
    target_height: float = 0.0
    elevation_min_deg: float = 20.0
    elevation_max_deg: float = 80.0
    min_flange_height: float = 0.15
    settle_s: float = 0.3
    return_home: bool = True
    label: str = "real"
    table_height: float = 0.0
    table_height_error: float = 0.0
    workspace_bounds: tuple[tuple[float, float, float], tuple[float, float, float]] = (
        (0.33, -0.22, -0.005), (0.77, 0.22, 0.20))

    def __post_init__(self) -> None:
        if not self.radius > 0:
            raise ConfigError("capture.radius must be positive (m)")
        if not self.elevation_min_deg < self.elevation_max_deg:
            raise ConfigError("capture.elevation_min_deg must be below elevation_max_deg")
        b = np.asarray(self.workspace_bounds, float)
        if b.shape != (2, 3) or not np.all(b[1] > b[0]):
            raise ConfigError("capture.workspace_bounds must be [[xmin, ymin, zmin], [xmax, ymax, zmax]] (m)")


@dataclass(frozen=True)
class HardwareConfig:
    """Everything the real backend needs besides the robot config.

    Attributes:
        host, port: rosbridge websocket of the Inovo controller.
        armed: allow motion commands (enable, switch_controller, trajectories); False -> HardwareError.
        dry_run: log planned motions to the command log and send nothing that moves the robot.
        speed_scale: fraction of the joint velocity/acceleration limits the safety layer allows, (0, 1].
        watchdog_s: stop the arm when no /joint_states arrived for this long (s).
        connect_timeout_s: websocket handshake and first /joint_states timeout (s).
        result_timeout_s: slack after a trajectory's duration to wait for the action result (s).
        command_log: JSONL file every command is appended to (None: memory only).
        enable_on_start: when armed, call /robot/enable and switch to the trajectory controller on start.
        disable_on_fault: call /robot/disable (besides cancelling the goal) when the watchdog trips.
        disable_on_close: call /robot/disable (after cancelling every goal) when the backend closes, which
            a bench worker also does on SIGTERM.
        path_tolerance_rad, goal_tolerance_rad, goal_time_tolerance_s: sent with every trajectory goal; the
            controller aborts and holds when the tracking error exceeds them (0 = the controller's default).
        stream: how motions are streamed in chunks that end at rest (:class:`StreamSettings`); the arm stops
            on its own at most ``stream.horizon_s`` + the braking time after the last chunk arrived.
        switch_controller_arg: request field name of /robot/switch_controller (unpublished; check with
            ``rosservice args /robot/switch_controller``).
        workspace_min, workspace_max: TCP safety box (m) in the robot base frame.
        operator_confirm: ask the operator on stdin to confirm each placement.
        fixtures: static fixtures declared to the planner, each ``{name, pose: [x, y, z, yaw_deg], boxes:
            [[[cx, cy, cz], [hx, hy, hz]], ...] | mesh: file}`` (m, deg; :class:`torm.backend.calibration.
            FixtureDeclaration`); with ``capture.table_height`` (m) and ``capture.table_height_error`` (m, the
            measurement's stated error) they form the cell's declared calibration.
    """

    host: str = ""
    port: int = 9090
    armed: bool = False
    dry_run: bool = False
    speed_scale: float = 0.25
    watchdog_s: float = 0.5
    connect_timeout_s: float = 5.0
    result_timeout_s: float = 5.0
    command_log: str | None = "hardware_commands.jsonl"
    enable_on_start: bool = True
    disable_on_fault: bool = True
    disable_on_close: bool = True
    path_tolerance_rad: float = 0.1
    goal_tolerance_rad: float = 0.01
    goal_time_tolerance_s: float = 0.5
    joint_states_topic: str = "/joint_states"
    tcp_pose_topic: str = "/default_move_group/tcp_pose"
    action_ns: str = "/robot/joint_trajectory_controller/follow_joint_trajectory"
    enable_service: str = "/robot/enable"
    disable_service: str = "/robot/disable"
    switch_controller_service: str = "/robot/switch_controller"
    switch_controller_arg: str = "data"
    workspace_min: tuple[float, float, float] = (-0.2, -0.6, 0.0)
    workspace_max: tuple[float, float, float] = (1.0, 0.6, 1.0)
    operator_confirm: bool = False
    stream: StreamSettings = field(default_factory=StreamSettings)
    gripper: GripperSettings = field(default_factory=GripperSettings)
    camera: CameraSettings = field(default_factory=CameraSettings)
    capture: RealCaptureSettings = field(default_factory=RealCaptureSettings)
    fixtures: tuple[dict[str, Any], ...] = ()

    def __post_init__(self) -> None:
        check_finite(self, "hardware config")
        object.__setattr__(self, "fixtures", tuple(dict(f) for f in self.fixtures))
        self.calibration()  # a bad fixture declaration or table height fails here, before anything moves
        if not self.host:
            raise ConfigError("hardware config: 'host' (the Inovo controller's address running rosbridge) is empty")
        if not 0 < self.port < 65536:
            raise ConfigError(f"hardware config: port {self.port} must be 1..65535 (rosbridge default 9090)")
        if not 0.0 < self.speed_scale <= 1.0:
            raise ConfigError(f"hardware config: speed_scale must be in (0, 1], got {self.speed_scale}")
        peak = self.speed_scale * (1.05 + self.stream.brake_fraction)
        if peak > 1.0:
            raise ConfigError(
                f"hardware config: speed_scale {self.speed_scale} with stream.brake_fraction "
                f"{self.stream.brake_fraction} lets a braking tail accelerate at up to {peak:.2f} x the joint "
                "acceleration limits (speed_scale x (1.05 + brake_fraction)); lower speed_scale or brake_fraction "
                "so the product stays <= 1")
        if min(self.path_tolerance_rad, self.goal_tolerance_rad, self.goal_time_tolerance_s) < 0:
            raise ConfigError("hardware config: path_tolerance_rad, goal_tolerance_rad and goal_time_tolerance_s "
                              "must be >= 0 (0 = the controller's default)")
        for name in ("watchdog_s", "connect_timeout_s", "result_timeout_s"):
            if not getattr(self, name) > 0:
                raise ConfigError(f"hardware config: {name} must be positive (s)")
        if not np.all(np.asarray(self.workspace_max) > np.asarray(self.workspace_min)):
            raise ConfigError("hardware config: workspace_max must exceed workspace_min on every axis (m)")


    def calibration(self) -> Any:
        """The cell's declared :class:`torm.backend.calibration.Calibration` (table height, fixtures)."""
        from torm.backend.calibration import Calibration, FixtureDeclaration

        c = self.capture
        return Calibration(c.table_height, c.table_height_error, "hardware config",
                           tuple(FixtureDeclaration.from_dict(f) for f in self.fixtures))


def load_hardware_config(path: str | Path, overrides: tuple[str, ...] | list[str] = ()) -> HardwareConfig:
    """Load a :class:`HardwareConfig` YAML; relative file paths inside are resolved against its folder."""
    p = Path(path)
    if not p.is_file():
        raise ConfigError(f"hardware config {p} does not exist; pass --hardware-config FILE (or set {ENV_CONFIG})")
    data = load_yaml(p)

    def _abs(v: Any) -> Any:
        return str((p.parent / v).resolve()) if isinstance(v, str) and not Path(v).is_absolute() else v

    if "command_log" in data:
        data["command_log"] = _abs(data["command_log"])
    for fx in data.get("fixtures") or []:
        if isinstance(fx, dict) and "mesh" in fx:
            fx["mesh"] = _abs(fx["mesh"])
    for section, key in (("gripper", "calibration"), ("camera", "hand_eye")):
        if isinstance(data.get(section), dict) and key in data[section]:
            data[section][key] = _abs(data[section][key])
    return from_dict(HardwareConfig, data, overrides, where=str(p))


def _truthy(v: Any) -> bool:
    return str(v).strip().lower() in ("1", "true", "yes", "on")


def resolve_hardware_config(trial_config: Any = None) -> HardwareConfig:
    """The hardware config for a trial: ``trial_config.hardware_config`` or $TORM_HARDWARE_CONFIG, with ``armed``
    forced on by ``trial_config.arm_robot`` or $TORM_ARM_ROBOT=1."""
    path = getattr(trial_config, "hardware_config", None) or os.environ.get(ENV_CONFIG)
    if not path:
        raise ConfigError(f"--backend real needs a hardware config: pass --hardware-config FILE or set {ENV_CONFIG} "
                          "(see torm/hardware/config.py for the YAML fields)")
    cfg = load_hardware_config(path)
    if bool(getattr(trial_config, "arm_robot", False)) or _truthy(os.environ.get(ENV_ARMED, "")):
        cfg = replace(cfg, armed=True)
    return cfg
