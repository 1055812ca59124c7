"""A minimal Modbus RTU master (function codes 04 and 16) over a byte transport.

Why our own framing instead of pymodbus' client: the Robotiq 2F-85 needs only two requests
(FC16 "write multiple registers" and FC04 "read input registers"), and a ~100-line master over a
two-method transport (``write(bytes)``, ``read(n) -> bytes``) is tested byte for byte against an
in-memory fake gripper without serial ports, ptys or an event loop. A :class:`serial.Serial`
(pyserial) is such a transport; :func:`open_serial` opens one with the 2F-85's settings.

Frame layout (all multi-byte fields big-endian except the CRC, which is sent low byte first):

- FC04 request ``[slave, 0x04, addr_hi, addr_lo, n_hi, n_lo, crc_lo, crc_hi]``;
  response ``[slave, 0x04, 2n, data (2n bytes), crc_lo, crc_hi]``.
- FC16 request ``[slave, 0x10, addr_hi, addr_lo, n_hi, n_lo, 2n, data (2n bytes), crc_lo, crc_hi]``;
  response ``[slave, 0x10, addr_hi, addr_lo, n_hi, n_lo, crc_lo, crc_hi]``.
- Exception response ``[slave, fc | 0x80, code, crc_lo, crc_hi]``.
"""

from __future__ import annotations

import logging
import struct
import threading
from typing import Protocol

from torm.errors import HardwareError

log = logging.getLogger(__name__)

FC_READ_INPUT_REGISTERS = 0x04
FC_WRITE_MULTIPLE_REGISTERS = 0x10

_EXCEPTIONS = {1: "illegal function", 2: "illegal data address", 3: "illegal data value", 4: "slave device failure",
               6: "slave device busy"}


class ModbusError(HardwareError):
    """No valid Modbus answer: timeout, bad CRC, wrong slave/function, or an exception response."""


class ByteTransport(Protocol):
    """A half-duplex byte link (pyserial ``Serial`` satisfies it)."""

    def write(self, data: bytes) -> int | None: ...

    def read(self, size: int) -> bytes:
        """Up to ``size`` bytes; fewer when the read timeout expires."""
        ...

    def reset_input_buffer(self) -> None: ...


def crc16(data: bytes) -> int:
    """CRC-16/MODBUS (poly 0xA001 reflected, init 0xFFFF) of ``data``."""
    crc = 0xFFFF
    for b in data:
        crc ^= b
        for _ in range(8):
            crc = (crc >> 1) ^ 0xA001 if crc & 1 else crc >> 1
    return crc


def with_crc(frame: bytes) -> bytes:
    """``frame`` followed by its CRC (low byte first)."""
    return frame + struct.pack("<H", crc16(frame))


def check_crc(frame: bytes) -> bool:
    """Whether the last two bytes of ``frame`` are the CRC of the rest."""
    return len(frame) >= 3 and struct.unpack("<H", frame[-2:])[0] == crc16(frame[:-2])


def bytes_to_registers(data: bytes) -> list[int]:
    """Big-endian 16-bit registers from an even number of bytes."""
    if len(data) % 2:
        raise ValueError("register data must have an even number of bytes")
    return list(struct.unpack(f">{len(data) // 2}H", data))


def registers_to_bytes(regs: list[int]) -> bytes:
    """Big-endian bytes of 16-bit registers."""
    return struct.pack(f">{len(regs)}H", *regs)


class ModbusRTUClient:
    """Modbus RTU master for one slave on a :class:`ByteTransport`.

    Args:
        transport: the byte link (serial port, or a fake in tests).
        slave: slave id (2F-85: 9).
        port_label: used in error messages (e.g. ``/dev/ttyUSB0 @ 115200``).
        retries: extra attempts after a timeout or corrupt frame.
    """

    def __init__(self, transport: ByteTransport, slave: int = 9, port_label: str = "serial port",
                 retries: int = 1) -> None:
        if not 1 <= slave <= 247:
            raise HardwareError(f"Modbus slave id must be in 1..247, got {slave}")
        self.transport = transport
        self.slave = slave
        self.port_label = port_label
        self.retries = retries
        self._lock = threading.Lock()

    def _hint(self) -> str:
        return (f"check the RS-485/USB cable, the gripper's 24 V power, slave id {self.slave} and 115200 baud "
                f"8N1 on {self.port_label}")

    def _transact(self, request: bytes, fc: int, n_response: int) -> bytes:
        frame = with_crc(request)
        last = ""
        with self._lock:
            for _ in range(self.retries + 1):
                self.transport.reset_input_buffer()
                self.transport.write(frame)
                head = self.transport.read(2)
                if len(head) < 2:
                    last = "no answer (timeout)"
                    continue
                if head[1] == (fc | 0x80):
                    rest = self.transport.read(3)
                    resp = head + rest
                    if len(resp) == 5 and check_crc(resp):
                        code = resp[2]
                        raise ModbusError(f"Modbus exception {code} ({_EXCEPTIONS.get(code, 'unknown')}) for "
                                          f"function {fc:#04x} from slave {self.slave}; {self._hint()}")
                    last = "corrupt exception frame"
                    continue
                resp = head + self.transport.read(n_response - 2)
                if len(resp) < n_response:
                    last = f"short answer ({len(resp)} of {n_response} bytes, timeout)"
                    continue
                if not check_crc(resp):
                    last = "CRC mismatch"
                    continue
                if resp[0] != self.slave or resp[1] != fc:
                    last = f"answer from slave {resp[0]} function {resp[1]:#04x}"
                    continue
                return resp
        raise ModbusError(f"Modbus function {fc:#04x} to slave {self.slave} failed: {last}; {self._hint()}")

    def read_input_registers(self, address: int, count: int) -> list[int]:
        """FC04: ``count`` input registers starting at ``address``."""
        req = struct.pack(">BBHH", self.slave, FC_READ_INPUT_REGISTERS, address, count)
        resp = self._transact(req, FC_READ_INPUT_REGISTERS, 5 + 2 * count)
        if resp[2] != 2 * count:
            raise ModbusError(f"FC04 answer has byte count {resp[2]}, expected {2 * count}; {self._hint()}")
        return bytes_to_registers(resp[3:-2])

    def write_registers(self, address: int, values: list[int]) -> None:
        """FC16: write ``values`` (16-bit each) starting at ``address``."""
        data = registers_to_bytes(values)
        req = struct.pack(">BBHHB", self.slave, FC_WRITE_MULTIPLE_REGISTERS, address, len(values), len(data)) + data
        resp = self._transact(req, FC_WRITE_MULTIPLE_REGISTERS, 8)
        addr, n = struct.unpack(">HH", resp[2:6])
        if addr != address or n != len(values):
            raise ModbusError(f"FC16 echo ({addr:#06x}, {n}) does not match the request ({address:#06x}, "
                              f"{len(values)}); {self._hint()}")


def open_serial(device: str, baudrate: int = 115200, timeout_s: float = 0.2) -> ByteTransport:
    """Open ``device`` as 8N1 at ``baudrate`` with a read timeout (s); HardwareError if absent.

    ``device`` is a serial port (``/dev/ttyUSB0``) or any pyserial URL (``socket://host:port`` for an
    RS-485-to-Ethernet gateway passing raw RTU frames, ``rfc2217://host:port``).
    """
    try:
        import serial
    except ImportError as exc:
        raise HardwareError("pyserial is not installed; pip install 'torm[hardware]'") from exc
    try:
        return serial.serial_for_url(device, baudrate=baudrate, bytesize=8, parity="N", stopbits=1, timeout=timeout_s)
    except (serial.SerialException, OSError, ValueError) as exc:
        raise HardwareError(f"cannot open serial port {device}: {exc}; check the USB/RS-485 adapter is plugged in, "
                            "the device path (ls /dev/ttyUSB*) and that your user is in the 'dialout' group") from exc
