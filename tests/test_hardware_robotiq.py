"""Robotiq 2F-85 driver against an in-memory Modbus RTU gripper that parses frames, checks CRCs and moves
(torm/testing/fake_robotiq.py)."""

from __future__ import annotations

import struct

import pytest

from torm.errors import HardwareError
from torm.hardware.modbus import ModbusError, ModbusRTUClient, crc16, with_crc
from torm.hardware.robotiq import (
    STATUS_REGISTER,
    GripperCalibration,
    RobotiqGripper,
    force_to_byte,
    speed_to_byte,
)
from torm.testing.fake_robotiq import FakeRobotiq, FakeRobotiqServer


def _gripper(fake: FakeRobotiq, cal: GripperCalibration | None = None, armed: bool = True) -> RobotiqGripper:
    return RobotiqGripper(ModbusRTUClient(fake, slave=9, port_label="fake"), cal, poll_s=0.0, move_timeout_s=2.0,
                          activate_timeout_s=2.0, armed=armed)


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


def test_unarmed_gripper_writes_nothing_that_moves_the_fingers():
    fake = FakeRobotiq()
    log = []
    g = RobotiqGripper(ModbusRTUClient(fake, slave=9), poll_s=0.0, command_log=lambda k, p: log.append(k))
    for action in (g.activate, lambda: g.move(0.02), g.calibrate):
        with pytest.raises(HardwareError, match="not armed"):
            action()
    assert fake.writes == [] and log == ["refused"] * 3
    assert g.state().width == pytest.approx(GripperCalibration().count_to_width(120))  # reading is fine


def test_unarmed_real_backend_activates_nothing_and_moves_no_finger(tmp_path):
    """make_real_backend with the gripper on a loopback Modbus server and the arm on the fake rosbridge."""
    from types import SimpleNamespace

    from sim.robots.config import load_robot_config
    from torm.hardware import make_real_backend
    from torm.testing.fake_rosbridge import FakeRosbridge, write_cell_yaml

    rcfg = load_robot_config("inovo_2f85")
    fake = FakeRobotiq()
    modbus, ros = FakeRobotiqServer(fake), FakeRosbridge(rcfg.arm.home_q, tuple(rcfg.arm.joints))
    hw = write_cell_yaml(tmp_path / "hw.yaml", ros.port, modbus.url, watchdog_s=None)
    try:
        backend = make_real_backend(SimpleNamespace(robot="inovo_2f85", hardware_config=str(hw), arm_robot=False))
        try:
            with pytest.raises(HardwareError, match="not armed"):
                backend.gripper.move(0.02)
            assert backend.gripper.state().width > 0  # the status is read over the link
        finally:
            backend.close()
        assert fake.writes == [] and ros.msgs("call_service") == [] and ros.goals() == []
        # armed, the same backend activates the gripper on start and moves its fingers
        backend = make_real_backend(SimpleNamespace(robot="inovo_2f85", hardware_config=str(hw), arm_robot=True))
        try:
            backend.gripper.move(0.04)
        finally:
            backend.close()
        assert fake.writes[:2] == [[0, 0, 0], [0x0100, 0, 0]] and fake.finger_writes()
    finally:
        modbus.close()
        ros.close()
