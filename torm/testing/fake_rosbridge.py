"""Test double: a rosbridge_server stand-in on loopback with a model of a ROS joint_trajectory_controller behind it.

Speaks the JSON rosbridge v2 protocol: answers ``call_service`` for /robot/enable, /robot/disable and
/robot/switch_controller, publishes /joint_states at 100 Hz to subscribers, takes FollowJointTrajectory
goals on the actionlib ``.../goal`` topic and cancels on ``.../cancel``.

The controller model (:class:`FakeController`, wall-clock time) follows what the ROS1
joint_trajectory_controller does with position-only points: a goal's points are reached at
``receipt time + time_from_start``, linearly interpolated, starting from where the arm is when the goal
arrives; a new goal replaces the running one (whose result is PREEMPTED); after its last point the
arm holds that point (the goal SUCCEEDED); a cancel holds the current position. The model runs on
whether or not anything talks to it, which is what a dropped link or a dead client means for a real
controller: :meth:`FakeRosbridge.freeze` stops the fake from answering (no messages in or out) and
the modelled arm carries on with the last goal it received.
"""

from __future__ import annotations

import contextlib
import json
import threading
import time
from pathlib import Path

import numpy as np
from websockets.sync.server import serve

ACTION = "/robot/joint_trajectory_controller/follow_joint_trajectory"


def _secs(d: dict) -> float:
    return d["secs"] + d["nsecs"] * 1e-9


class FakeController:
    """Piecewise-linear joint motion on wall time (``time.monotonic``); thread-safe."""

    def __init__(self, q0: np.ndarray) -> None:
        self.lock = threading.Lock()
        self.t = np.array([time.monotonic()])
        self.q = np.asarray(q0, float)[None].copy()
        self.active: str | None = None
        self.done: set[str] = set()

    def q_at(self, t: float) -> np.ndarray:
        with self.lock:
            return np.array([np.interp(t, self.t, self.q[:, j]) for j in range(self.q.shape[1])])

    def end_time(self) -> float:
        """When the current motion ends (the arm holds still from then on)."""
        with self.lock:
            return float(self.t[-1])

    def accept(self, goal: dict, t_recv: float) -> str | None:
        """Start ``goal`` from the current position; returns the goal id it replaced (if still running)."""
        pts = goal["goal"]["trajectory"]["points"]
        times = np.array([t_recv + _secs(p["time_from_start"]) for p in pts])
        qs = np.array([p["positions"] for p in pts], float)
        q_now = self.q_at(t_recv)
        with self.lock:
            self.t = np.concatenate([[t_recv], times])
            self.q = np.vstack([q_now[None], qs])
            prev, self.active = self.active, goal["goal_id"]["id"]
        return prev

    def cancel(self, t: float) -> str | None:
        q_now = self.q_at(t)
        with self.lock:
            self.t, self.q = np.array([t]), q_now[None]
            prev, self.active = self.active, None
        return prev

    def finished(self, t: float) -> str | None:
        """The active goal id once its last point is reached (reported once)."""
        with self.lock:
            if self.active is not None and t >= self.t[-1] and self.active not in self.done:
                self.done.add(self.active)
                gid, self.active = self.active, None
                return gid
        return None


class FakeRosbridge:
    """The server (127.0.0.1, ephemeral port), recording every message it received with its arrival time."""

    def __init__(self, q0: np.ndarray, joints: tuple[str, ...], rate_hz: float = 100.0) -> None:
        self.joints = tuple(joints)
        self.controller = FakeController(q0)
        self.received: list[dict] = []
        self.received_at: list[float] = []
        self.answering = True
        self.publishing = True
        self.abort_at_goal: int | None = None  # abort (and hold) when this many goals arrived: a tracking fault
        self.history: list[tuple[float, np.ndarray]] = []  # (t, q) of the modelled arm at the publish rate
        self._period = 1.0 / rate_hz
        self._conns: list = []
        self._subs: dict[int, set[str]] = {}
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._server = serve(self._handler, "127.0.0.1", 0)
        self.port = self._server.socket.getsockname()[1]
        threading.Thread(target=self._server.serve_forever, daemon=True).start()
        threading.Thread(target=self._tick, daemon=True).start()

    # -- inspection --------------------------------------------------------------------------------------
    def msgs(self, op: str | None = None, since: float = 0.0, **match) -> list[dict]:
        with self._lock:
            out = [m for m, t in zip(self.received, self.received_at, strict=True) if t >= since]
        return [m for m in out if (op is None or m.get("op") == op) and all(m.get(k) == v for k, v in match.items())]

    def goals(self, since: float = 0.0) -> list[dict]:
        return [m["msg"] for m in self.msgs("publish", since=since, topic=f"{ACTION}/goal")]

    def freeze(self) -> float:
        """Stop answering (nothing in or out, the socket stays open like a dead network); returns the time."""
        t = time.monotonic()
        self.answering = False
        return t

    # -- protocol --------------------------------------------------------------------------------------
    def _send(self, ws, msg: dict) -> None:
        if not self.answering:
            return
        with contextlib.suppress(Exception), self._lock:
            ws.send(json.dumps(msg))

    def _broadcast(self, topic: str, msg: dict) -> None:
        for ws in list(self._conns):
            if topic in self._subs.get(id(ws), ()):
                self._send(ws, {"op": "publish", "topic": topic, "msg": msg})

    def _result(self, gid: str, status: int) -> None:
        self._broadcast(f"{ACTION}/result", {"header": {"stamp": {"secs": 0, "nsecs": 0}},
                                              "status": {"goal_id": {"id": gid}, "status": status, "text": ""},
                                              "result": {"error_code": 0, "error_string": ""}})

    def _tick(self) -> None:
        while not self._stop.wait(self._period):
            t = time.monotonic()
            q = self.controller.q_at(t)
            self.history.append((t, q))
            if self.publishing:
                self._broadcast("/joint_states", {
                    "header": {"stamp": {"secs": 0, "nsecs": 0}, "frame_id": ""}, "name": list(self.joints),
                    "position": q.tolist(), "velocity": [0.0] * len(self.joints), "effort": []})
            gid = self.controller.finished(t)
            if gid is not None:
                self._result(gid, 3)  # SUCCEEDED

    def _handler(self, ws) -> None:
        self._conns.append(ws)
        subs = self._subs.setdefault(id(ws), set())
        try:
            for raw in ws:
                if not self.answering:
                    continue  # a dead link: nothing arrives
                t = time.monotonic()
                msg = json.loads(raw)
                with self._lock:
                    self.received.append(msg)
                    self.received_at.append(t)
                op = msg.get("op")
                if op == "subscribe":
                    subs.add(msg["topic"])
                elif op == "call_service":
                    self._send(ws, {"op": "service_response", "id": msg.get("id"), "service": msg["service"],
                                    "values": {"success": True, "message": ""}, "result": True})
                elif op == "publish" and msg["topic"] == f"{ACTION}/goal":
                    prev = self.controller.accept(msg["msg"], t)
                    if prev is not None:
                        self._result(prev, 2)  # PREEMPTED
                    if self.abort_at_goal is not None and len(self.goals()) >= self.abort_at_goal:
                        self.abort_at_goal = None
                        gid = self.controller.cancel(t)  # path tolerance violated: hold where it is
                        self._result(gid, 4)  # ABORTED
                elif op == "publish" and msg["topic"] == f"{ACTION}/cancel":
                    prev = self.controller.cancel(t)
                    if prev is not None:
                        self._result(prev, 2)
        except Exception:
            pass
        finally:
            with contextlib.suppress(ValueError):
                self._conns.remove(ws)

    def drop_connections(self) -> None:
        for ws in list(self._conns):
            with contextlib.suppress(Exception):
                ws.close()

    def close(self) -> None:
        self._stop.set()
        self.drop_connections()
        self._server.shutdown()

    # -- motion analysis -------------------------------------------------------------------------------
    def rest_time(self, after: float, tol_rad: float = 1e-9) -> float | None:
        """First time after ``after`` from which the modelled arm never moved again (None: still moving)."""
        hist = [(t, q) for t, q in self.history if t >= after]
        if len(hist) < 2:
            return None
        last = hist[-1][1]
        for t, q in reversed(hist):
            if np.max(np.abs(q - last)) > tol_rad:
                return t
        return hist[0][0]


#: Streaming horizon (s) for fake cells in tests. The streaming thread must send a chunk within the horizon; on a
#: loaded 2-core CI machine it was seen to stall 0.57 s (default horizon 0.3 s) and 0.6 s. A test that is not about
#: stream timing gets a margin of more than 3x the worst stall seen; the timing tests set their own horizon.
LOADED_MACHINE_HORIZON_S = 2.0


def write_cell_yaml(path: Path, port: int, gripper_url: str, extra: str = "", watchdog_s: float | None = 2.0,
                    horizon_s: float | None = LOADED_MACHINE_HORIZON_S) -> Path:
    """A hardware YAML for a fake cell at ``path``: the arm behind this fake rosbridge on loopback (``port``), the
    gripper a fake Modbus server (``gripper_url``), a ``cmd.jsonl`` command log; ``extra``: more YAML lines (for
    instance ``capture: {settle_s: 0.0}``). ``horizon_s`` (s): the streaming horizon, by default
    :data:`LOADED_MACHINE_HORIZON_S` so that a test about something else does not fail when a loaded machine
    stalls the streaming thread; ``None`` keeps the configuration's default (0.3 s). Returns ``path``."""
    lines = ["host: 127.0.0.1", f"port: {port}"] + ([f"watchdog_s: {watchdog_s}"] if watchdog_s is not None else [])
    lines += ["command_log: cmd.jsonl", f"gripper: {{device: '{gripper_url}'}}"]
    lines += [f"stream: {{horizon_s: {horizon_s}}}"] if horizon_s is not None else []
    lines += [extra] if extra else []
    path.write_text("\n".join(lines) + "\n")
    return path
