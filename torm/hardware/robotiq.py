"""Robotiq 2F-85 over Modbus RTU (implements :class:`torm.backend.protocol.Gripper`).

Registers (HARDWARE.md): the robot output (action request) block is written with FC16 at 0x03E8 as
3 registers = 6 bytes: byte 0 = ``rACT`` (bit 0) | ``rGTO`` (bit 3) | ``rATR`` (bit 4), bytes 1-2
reserved, byte 3 = ``rPR`` position request (0 open .. 255 closed), byte 4 = ``rSP`` speed, byte 5 =
``rFR`` force. The status block is read with FC04 at 0x07D0 as 3 registers: byte 0 = ``gACT`` (bit 0)
| ``gGTO`` (bit 3) | ``gSTA`` (bits 4-5; 3 = activation complete) | ``gOBJ`` (bits 6-7: 0 moving,
1 contact while opening, 2 contact while closing, 3 at the requested position), byte 1 reserved,
byte 2 = ``gFLT``, byte 3 = ``gPR`` (echo of ``rPR``), byte 4 = ``gPO`` (finger position count),
byte 5 = ``gCU`` (current, about 10 x value mA).

Width: each unit maps counts to the pad gap differently (the real endpoints after activation are about
3 and 230 counts). :class:`GripperCalibration` stores the measured open/closed counts and widths (a
linear map between them); :meth:`RobotiqGripper.calibrate` measures them by closing fully (nothing
between the fingers!) and opening fully. Speed 20-150 mm/s and force 20-235 N map linearly to 0..255.

Arming: exactly like the arm, an unarmed gripper (``armed=False``, the default) writes no action
register at all (activation, moves and calibration all move the fingers): it raises
``HardwareError("not armed: ...")`` and records a ``refused`` command. Reading the status is allowed.
"""

from __future__ import annotations

import logging
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import yaml

from torm.backend.protocol import GripperState
from torm.config import parse_yaml
from torm.errors import ConfigError, HardwareError
from torm.hardware.modbus import ModbusRTUClient

log = logging.getLogger(__name__)

ACTION_REGISTER = 0x03E8
STATUS_REGISTER = 0x07D0
SPEED_RANGE_MPS = (0.020, 0.150)
FORCE_RANGE_N = (20.0, 235.0)

FAULTS = {
    0x05: "action delayed: activation (re-activation) must complete first",
    0x07: "the activation bit must be set before an action",
    0x08: "maximum operating temperature exceeded; let the gripper cool down",
    0x09: "no communication for at least 1 s",
    0x0A: "under minimum operating voltage; check the 24 V supply",
    0x0B: "automatic release in progress",
    0x0C: "internal fault; contact support",
    0x0D: "activation fault; check nothing blocks the fingers",
    0x0E: "overcurrent triggered",
    0x0F: "automatic release completed",
}
MAJOR_FAULT_MIN = 0x08


@dataclass(frozen=True)
class RobotiqStatus:
    """Decoded status block (see the module docstring)."""

    gACT: int  # noqa: N815 (Robotiq manual names)
    gGTO: int  # noqa: N815 (Robotiq manual names)
    gSTA: int  # noqa: N815 (Robotiq manual names)
    gOBJ: int  # noqa: N815 (Robotiq manual names)
    gFLT: int  # noqa: N815 (Robotiq manual names)
    gPR: int  # noqa: N815 (Robotiq manual names)
    gPO: int  # noqa: N815 (Robotiq manual names)
    gCU: int  # noqa: N815 (Robotiq manual names)

    @classmethod
    def from_registers(cls, regs: list[int]) -> RobotiqStatus:
        b = [(regs[0] >> 8) & 0xFF, regs[0] & 0xFF, (regs[1] >> 8) & 0xFF, regs[1] & 0xFF,
             (regs[2] >> 8) & 0xFF, regs[2] & 0xFF]
        s = b[0]
        return cls(gACT=s & 1, gGTO=(s >> 3) & 1, gSTA=(s >> 4) & 3, gOBJ=(s >> 6) & 3, gFLT=b[2] & 0x0F,
                   gPR=b[3], gPO=b[4], gCU=b[5])

    @property
    def object_detected(self) -> bool:
        """Fingers stopped on an object (contact while opening or closing)."""
        return self.gOBJ in (1, 2)


def action_registers(rACT: int, rGTO: int, rPR: int, rSP: int, rFR: int, rATR: int = 0) -> list[int]:
    """The 3 action-request registers for the given fields (bytes in the order of the module docstring)."""
    for name, v in (("rPR", rPR), ("rSP", rSP), ("rFR", rFR)):
        if not 0 <= v <= 255:
            raise HardwareError(f"{name} must be 0..255, got {v}")
    b0 = (rACT & 1) | ((rGTO & 1) << 3) | ((rATR & 1) << 4)
    return [b0 << 8, rPR & 0xFF, ((rSP & 0xFF) << 8) | (rFR & 0xFF)]


def speed_to_byte(speed_mps: float) -> int:
    """rSP for a finger speed (m/s): 20 mm/s -> 0 .. 150 mm/s -> 255 (clipped)."""
    lo, hi = SPEED_RANGE_MPS
    return int(round(np.clip((speed_mps - lo) / (hi - lo), 0.0, 1.0) * 255))


def force_to_byte(force_n: float) -> int:
    """rFR for a grip force (N): 20 N -> 0 .. 235 N -> 255 (clipped)."""
    lo, hi = FORCE_RANGE_N
    return int(round(np.clip((force_n - lo) / (hi - lo), 0.0, 1.0) * 255))


@dataclass(frozen=True)
class GripperCalibration:
    """Per-unit count <-> pad-gap map: gap ``open_width`` (m) at ``open_count``, ``closed_width`` at ``closed_count``.

    Linear between the two; counts grow as the fingers close.
    """

    open_count: int = 3
    closed_count: int = 230
    open_width: float = 0.085
    closed_width: float = 0.0

    def __post_init__(self) -> None:
        if not 0 <= self.open_count < self.closed_count <= 255:
            raise ConfigError(f"gripper calibration needs 0 <= open_count < closed_count <= 255, got "
                              f"{self.open_count}, {self.closed_count}; run the calibration again")
        if not 0 <= self.closed_width < self.open_width <= 0.2:
            raise ConfigError(f"gripper calibration needs 0 <= closed_width < open_width <= 0.2 m, got "
                              f"{self.closed_width}, {self.open_width}")

    def count_to_width(self, count: float) -> float:
        """Pad gap (m) at finger position ``count`` (clipped to the calibrated range)."""
        f = (count - self.open_count) / (self.closed_count - self.open_count)
        return float(self.open_width + np.clip(f, 0.0, 1.0) * (self.closed_width - self.open_width))

    def width_to_count(self, width_m: float) -> int:
        """Position request for a pad gap (m): 0 at/above ``open_width``, 255 at/below ``closed_width``."""
        if width_m >= self.open_width:
            return 0
        if width_m <= self.closed_width:
            return 255
        f = (self.open_width - width_m) / (self.open_width - self.closed_width)
        return int(round(self.open_count + f * (self.closed_count - self.open_count)))

    def save(self, path: str | Path) -> None:
        """Write the calibration as YAML."""
        Path(path).write_text(yaml.safe_dump({"robotiq_2f85_calibration": asdict(self)}, sort_keys=False))

    @classmethod
    def load(cls, path: str | Path) -> GripperCalibration:
        """Read a YAML written by :meth:`save` (ConfigError naming the file when malformed)."""
        p = Path(path)
        if not p.is_file():
            raise ConfigError(f"gripper calibration file {p} does not exist; run RobotiqGripper.calibrate() first")
        data = parse_yaml(p.read_text()) or {}
        body = data.get("robotiq_2f85_calibration")
        if not isinstance(body, dict):
            raise ConfigError(f"{p}: expected a 'robotiq_2f85_calibration' mapping")
        unknown = set(body) - {"open_count", "closed_count", "open_width", "closed_width"}
        if unknown:
            raise ConfigError(f"{p}: unknown keys {sorted(unknown)}")
        return cls(**body)


class RobotiqGripper:
    """The 2F-85 commanded by pad gap (m).

    Args:
        client: Modbus RTU master for the gripper's slave id.
        calibration: count <-> width map (defaults: 3 / 230 counts for 85 / 0 mm).
        poll_s: status polling period (s).
        move_timeout_s: longest wait for a move to finish (s).
        activate_timeout_s: longest wait for the activation to complete (s).
        command_log: optional callable ``(kind, payload)`` recording every command (the JSONL log).
        armed: allow writes of the action register (anything that moves the fingers); False refuses them.
    """

    def __init__(self, client: ModbusRTUClient, calibration: GripperCalibration | None = None,
                 poll_s: float = 0.02, move_timeout_s: float = 5.0, activate_timeout_s: float = 10.0,
                 command_log=None, armed: bool = False) -> None:
        self.client = client
        self.armed = bool(armed)
        self.calibration = calibration or GripperCalibration()
        self.poll_s = poll_s
        self.move_timeout_s = move_timeout_s
        self.activate_timeout_s = activate_timeout_s
        self.max_width = float(self.calibration.open_width)
        self.force_range_n = FORCE_RANGE_N  # a force command is clipped to this (N)
        self._log = command_log
        self._warned_force = False
        self._last = (0, 0, 0)  # rPR, rSP, rFR

    def _record(self, kind: str, **payload) -> None:
        if self._log is not None:
            self._log(kind, payload)

    def status(self) -> RobotiqStatus:
        """Read and decode the status block; HardwareError on a major fault."""
        st = RobotiqStatus.from_registers(self.client.read_input_registers(STATUS_REGISTER, 3))
        if st.gFLT >= MAJOR_FAULT_MIN:
            raise HardwareError(f"Robotiq fault {st.gFLT:#04x}: {FAULTS.get(st.gFLT, 'unknown fault')}; "
                                "re-activate the gripper (activate()) after fixing the cause")
        return st

    def _write(self, rACT: int, rGTO: int, rPR: int, rSP: int, rFR: int) -> None:
        regs = action_registers(rACT, rGTO, rPR, rSP, rFR)
        if not self.armed:  # the one place the action register is written: nothing moves unarmed
            self._record("refused", command="robotiq_write", reason="not armed", address=ACTION_REGISTER,
                         registers=regs)
            raise HardwareError("not armed: refusing to command the gripper (activation or a finger move); pass "
                                "--arm-robot (or armed: true in the hardware config) once the workspace is clear")
        self._record("robotiq_write", address=ACTION_REGISTER, registers=regs)
        self.client.write_registers(ACTION_REGISTER, regs)

    def activate(self) -> None:
        """Reset (rACT = 0) then activate (rACT = 1) and wait for gSTA = 3; the fingers open and close once."""
        self._write(0, 0, 0, 0, 0)
        self._write(1, 0, 0, 0, 0)
        t_end = time.monotonic() + self.activate_timeout_s
        while True:
            st = self.status()
            if st.gACT == 1 and st.gSTA == 3:
                log.info("Robotiq activated (position count %d)", st.gPO)
                return
            if time.monotonic() > t_end:
                raise HardwareError(f"Robotiq activation did not complete in {self.activate_timeout_s} s "
                                    f"(gACT {st.gACT}, gSTA {st.gSTA}, fault {st.gFLT:#04x}); check nothing "
                                    "blocks the fingers and the 24 V supply")
            time.sleep(self.poll_s)

    def move_count(self, rPR: int, rSP: int = 255, rFR: int = 150) -> RobotiqStatus:
        """Go to position request ``rPR`` (0..255) and wait until the fingers stop (gOBJ != 0) or time out."""
        self._write(1, 1, rPR, rSP, rFR)
        self._last = (rPR, rSP, rFR)
        t_end = time.monotonic() + self.move_timeout_s
        while True:
            st = self.status()
            if st.gACT != 1 or st.gSTA != 3:
                raise HardwareError(f"Robotiq is not activated (gACT {st.gACT}, gSTA {st.gSTA}); call activate()")
            if st.gPR == rPR and st.gOBJ != 0:
                return st
            if time.monotonic() > t_end:
                raise HardwareError(f"Robotiq did not settle within {self.move_timeout_s} s of a move to count "
                                    f"{rPR} (at {st.gPO}, gOBJ {st.gOBJ}); check for a jam")
            time.sleep(self.poll_s)

    def move(self, width_m: float, speed_mps: float = 0.1, force_n: float = 100.0) -> GripperState:
        """Go to pad gap ``width_m`` (m) at ``speed_mps`` (20-150 mm/s) with ``force_n`` (20-235 N); blocks."""
        if not (np.isfinite(width_m) and np.isfinite(speed_mps) and np.isfinite(force_n)):
            raise HardwareError(f"gripper move needs finite width/speed/force, got {width_m}, {speed_mps}, {force_n}")
        rPR = self.calibration.width_to_count(float(width_m))
        lo, hi = FORCE_RANGE_N
        if not lo <= force_n <= hi and not self._warned_force:
            self._warned_force = True
            log.warning("gripper: a force of %g N was asked for, outside the 2F-85's %g-%g N; %g N is commanded",
                        force_n, lo, hi, min(max(force_n, lo), hi))
        st = self.move_count(rPR, speed_to_byte(speed_mps), force_to_byte(force_n))
        state = self._to_state(st)
        log.debug("gripper to %.4f m (rPR %d): at %.4f m, gOBJ %d", width_m, rPR, state.width, st.gOBJ)
        return state

    def _to_state(self, st: RobotiqStatus) -> GripperState:
        return GripperState(width=self.calibration.count_to_width(st.gPO), command=int(st.gPR),
                            object_detected=st.object_detected)

    def state(self) -> GripperState:
        """Current pad gap (m), position request and whether an object stopped the fingers (gOBJ 1 or 2)."""
        return self._to_state(self.status())

    def calibrate(self, open_width: float = 0.085, closed_width: float = 0.0) -> GripperCalibration:
        """Close fully and open fully (nothing between the pads), record the counts, adopt and return the map."""
        closed = self.move_count(255, 64, 0)
        if closed.object_detected:
            raise HardwareError("calibration: the fingers stopped on an object while closing; remove it and retry")
        opened = self.move_count(0, 64, 0)
        cal = GripperCalibration(open_count=int(opened.gPO), closed_count=int(closed.gPO),
                                 open_width=open_width, closed_width=closed_width)
        log.info("Robotiq calibration: open %d counts, closed %d counts", cal.open_count, cal.closed_count)
        self.calibration = cal
        self.max_width = float(cal.open_width)
        return cal
