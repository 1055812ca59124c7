"""Test double: an in-memory Robotiq 2F-85 on an RS-485 line, and a loopback TCP server that puts it behind ``socket://``.

:class:`FakeRobotiq` parses Modbus RTU frames, checks CRCs, answers FC04/FC16 for its slave id and moves
its fingers; :class:`FakeRobotiqServer` serves it on 127.0.0.1 so a backend opens it with
``gripper.device: socket://127.0.0.1:PORT`` (pyserial's ``serial_for_url``), like an RS-485-to-Ethernet
gateway.
"""

from __future__ import annotations

import contextlib
import socket
import struct
import threading

import numpy as np

from torm.hardware.modbus import check_crc, with_crc
from torm.hardware.robotiq import ACTION_REGISTER, STATUS_REGISTER


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

    def finger_writes(self) -> list[list[int]]:
        """Action-register writes that can move the fingers (rACT or rGTO set)."""
        return [w for w in self.writes if (w[0] >> 8) & 0x09]


class FakeRobotiqServer:
    """Serves ``fake`` on 127.0.0.1 (ephemeral port) as raw RTU-over-TCP; ``url`` is ``socket://127.0.0.1:PORT``."""

    def __init__(self, fake: FakeRobotiq) -> None:
        self.fake = fake
        self._sock = socket.create_server(("127.0.0.1", 0))
        self.url = f"socket://127.0.0.1:{self._sock.getsockname()[1]}"
        self._stop = False
        threading.Thread(target=self._serve, daemon=True).start()

    def _serve(self) -> None:
        while not self._stop:
            try:
                conn, _ = self._sock.accept()
            except OSError:
                return
            threading.Thread(target=self._client, args=(conn,), daemon=True).start()

    def _client(self, conn: socket.socket) -> None:
        buf = b""
        with conn:
            while not self._stop:
                try:
                    data = conn.recv(4096)
                except OSError:
                    return
                if not data:
                    return
                buf += data
                while len(buf) >= 8:
                    need = 9 + buf[6] if buf[1] == 0x10 and len(buf) >= 7 else 8
                    if len(buf) < need:
                        break
                    frame, buf = buf[:need], buf[need:]
                    self.fake.write(frame)
                    out, self.fake.out = self.fake.out, b""
                    if out:
                        with contextlib.suppress(OSError):
                            conn.sendall(out)

    def close(self) -> None:
        self._stop = True
        with contextlib.suppress(OSError):
            self._sock.close()
