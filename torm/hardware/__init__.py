"""Real hardware behind ``--backend real``: Inovo arm (rosbridge), Robotiq 2F-85 (Modbus RTU), RealSense D455.

Optional extra: ``pip install 'torm[hardware]'``. Importing this package needs only numpy/mujoco/opencv;
``websockets``, ``pyserial`` and ``pyrealsense2`` are imported when a device is opened, and their absence
raises :class:`~torm.errors.HardwareError` with the install hint.
"""

from torm.hardware.backend import RealBackend, WallClock, make_real_backend, operator_prompt
from torm.hardware.config import HardwareConfig, load_hardware_config, resolve_hardware_config

__all__ = ["HardwareConfig", "RealBackend", "WallClock", "load_hardware_config", "make_real_backend",
           "operator_prompt", "resolve_hardware_config"]
