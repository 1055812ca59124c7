"""Robotiq 2F-85 driver against an in-memory Modbus RTU gripper that parses frames, checks CRCs and moves."""

from __future__ import annotations

import struct

import numpy as np
import pytest

from torm.errors import HardwareError
from torm.hardware.modbus import ModbusError, ModbusRTUClient, check_crc, crc16, with_crc
from torm.hardware.robotiq import (
    ACTION_REGISTER,
    STATUS_REGISTER,
    GripperCalibration,
    RobotiqGripper,
    force_to_byte,
    speed_to_byte,
)


class FakeRobotiq:
    """A 2F-85 on an RS-485 line: a byte transport (``write``/``read``) that answers FC04/FC16 for slave 9.

    Finger position ``po`` moves towards the request by ``1 + rSP // 32`` counts per status read, between
    the mechanical endpoints ``open_end``/``closed_end``; an object blocks closing at ``object_at``.
    """

    def __init__(self, slave: int = 9, open_end: int = 3, closed_end: int = 230, object_at: int | None = None,
                 silent: bool = False) -> None:
        self.slave, self.open_end, self.closed_end, self.object_at = slave, open_end, closed_end, object_at
        self.silent = silent
        self.action = [0, 0, 0, 0, 0, 0]  # bytes written at 0x03E8
        self.writes: list[list[int]] = []  # register triplets written
        self.po = 120
        self.sta = 0
        self.obj = 0
        self.act_reads = 0
        self.out = b""
        self.bad_crc_frames = 0

    # transport interface
    def reset_input_buffer(self) -> None:
        self.out = b""

    def read(self, n: int) -> bytes:
        chunk, self.out = self.out[:n], self.out[n:]
        return chunk

    def write(self, frame: bytes) -> int:
        if self.silent:
            return len(frame)
        if not check_crc(frame):
            self.bad_crc_frames += 1
            return len(frame)
        slave, fc = frame[0], frame[1]
        if slave != self.slave:
            return len(frame)
        if fc == 0x10:
            addr, n, nbytes = struct.unpack(">HHB", frame[2:7])
            data = frame[7:7 + nbytes]
            if addr != ACTION_REGISTER or n != 3 or nbytes != 6:
                self.out = with_crc(bytes([slave, 0x90, 2]))
                return len(frame)
            self.writes.append(list(struct.unpack(">3H", data)))
            prev_act = self.action[0] & 1
            self.action = list(data)
            if not (self.action[0] & 1):
                self.sta, self.obj = 0, 0
            elif not prev_act:
                self.sta, self.act_reads = 1, 0
            if self.action[0] & 0x08:
                self.obj = 0  # a new go-to starts moving
            self.out = with_crc(frame[:6])
        elif fc == 0x04:
            addr, n = struct.unpack(">HH", frame[2:6])
            if addr != STATUS_REGISTER or n != 3:
                self.out = with_crc(bytes([slave, 0x84, 2]))
                return len(frame)
            self._step()
            status = (self.action[0] & 1) | (self.action[0] & 0x08) | (self.sta << 4) | (self.obj << 6)
            body = bytes([status, 0, 0, self.action[3], self.po, 12])
            self.out = with_crc(bytes([slave, 0x04, 6]) + body)
        else:
            self.out = with_crc(bytes([slave, fc | 0x80, 1]))
        return len(frame)

    def _step(self) -> None:
        if self.sta == 1:
            self.act_reads += 1
            if self.act_reads >= 3:
                self.sta, self.po = 3, self.open_end
            return
        if self.sta != 3 or not (self.action[0] & 0x08) or self.obj != 0:
            return
        target = int(np.clip(self.action[3], self.open_end, self.closed_end))
        step = 1 + self.action[4] // 32
        if self.po < target:
            nxt = min(target, self.po + step)
            if self.object_at is not None and self.po < self.object_at <= nxt:
                self.po, self.obj = self.object_at, 2
                return
            self.po = nxt
        elif self.po > target:
            self.po = max(target, self.po - step)
        if self.po == target:
            # reached the request, or stopped at a mechanical endpoint beyond which the request lies
            self.obj = 3


def _gripper(fake: FakeRobotiq, cal: GripperCalibration | None = None) -> RobotiqGripper:
    return RobotiqGripper(ModbusRTUClient(fake, slave=9, port_label="fake"), cal, poll_s=0.0, move_timeout_s=2.0,
                          activate_timeout_s=2.0)


def test_crc16_matches_the_modbus_reference():
    # standard example: read holding registers, slave 1, addr 0, count 1 -> CRC bytes 84 0A
    assert with_crc(bytes.fromhex("010300000001"))[-2:] == bytes.fromhex("840A")
    assert crc16(b"123456789") == 0x4B37  # CRC-16/MODBUS check value


def test_activation_writes_reset_then_rACT():
    fake = FakeRobotiq()
    g = _gripper(fake)
    g.activate()
    assert fake.writes[0] == [0, 0, 0]  # rACT = 0 (reset)
    assert fake.writes[1][0] >> 8 == 0x01  # byte 0: rACT bit 0 set, rGTO clear
    assert fake.sta == 3 and fake.bad_crc_frames == 0


def test_move_writes_position_speed_force_and_reports_width():
    fake = FakeRobotiq()
    g = _gripper(fake)
    g.activate()
    st = g.move(0.085 / 2, speed_mps=0.15, force_n=235.0)
    regs = fake.writes[-1]
    b = struct.pack(">3H", *regs)
    assert b[0] == 0x09  # rACT | rGTO
    expected_rpr = GripperCalibration().width_to_count(0.0425)
    assert b[3] == expected_rpr == 116  # rPR: halfway between 3 and 230 counts
    assert b[4] == 255 and b[5] == 255  # rSP (150 mm/s), rFR (235 N)
    assert fake.po == expected_rpr and not st.object_detected
    assert st.width == pytest.approx(0.0425, abs=0.085 / 227)
    assert speed_to_byte(0.02) == 0 and speed_to_byte(0.085) == 128 and force_to_byte(127.5) == 128


def test_object_detection_when_closing_on_an_object():
    fake = FakeRobotiq(object_at=150)
    g = _gripper(fake)
    g.activate()
    st = g.move(0.0, speed_mps=0.05, force_n=40.0)
    assert fake.writes[-1][1] & 0xFF == 255  # width 0 -> rPR 255 (close fully)
    assert fake.writes[-1][2] == (59 << 8) | 24  # byte 4 rSP (50 mm/s), byte 5 rFR (40 N)
    assert st.object_detected and fake.po == 150
    assert st.width == pytest.approx(0.085 * (230 - 150) / 227, abs=1e-9)
    assert g.state().object_detected
    st = g.move(0.085)
    assert not st.object_detected and fake.po == 3


def test_width_calibration_measures_the_endpoints(tmp_path):
    fake = FakeRobotiq(open_end=12, closed_end=205)
    g = _gripper(fake)
    g.activate()
    cal = g.calibrate()
    assert (cal.open_count, cal.closed_count) == (12, 205)
    path = tmp_path / "cal.yaml"
    cal.save(path)
    loaded = GripperCalibration.load(path)
    assert loaded == cal
    g2 = _gripper(fake, loaded)
    st = g2.move(0.02)
    assert st.width == pytest.approx(0.02, abs=0.085 / 193)
    # the uncalibrated default map would be off by several millimetres on this unit
    assert abs(GripperCalibration().count_to_width(fake.po) - 0.02) > 0.005


def test_modbus_timeout_raises_hardware_error_with_hints():
    g = _gripper(FakeRobotiq(silent=True))
    with pytest.raises(HardwareError, match="cable.*power.*slave id 9.*115200"):
        g.state()


def test_wrong_slave_id_times_out_and_exception_responses_raise():
    fake = FakeRobotiq(slave=9)
    client = ModbusRTUClient(fake, slave=10, port_label="fake")
    with pytest.raises(ModbusError, match="timeout"):
        client.read_input_registers(STATUS_REGISTER, 3)
    with pytest.raises(ModbusError, match="exception 2"):
        ModbusRTUClient(fake, slave=9).read_input_registers(0x1234, 3)
