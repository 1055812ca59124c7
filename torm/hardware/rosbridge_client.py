"""A small synchronous rosbridge v2 (JSON over websocket) client with a receive thread.

Why not ``roslibpy``: it runs on twisted/autobahn with its own reactor thread, which is hard to stop
and restart inside one process (the reactor is not restartable) and hides connection loss behind
callbacks. This client uses ``websockets.sync.client`` only: one socket, one receive thread that
dispatches ``publish`` messages to topic callbacks and ``service_response`` messages to waiting
callers, and an ``on_disconnect`` hook the arm's watchdog uses. Operations used (rosbridge protocol
v2): ``advertise``, ``unadvertise``, ``publish``, ``subscribe``, ``unsubscribe``, ``call_service``.
"""

from __future__ import annotations

import contextlib
import itertools
import json
import logging
import threading
from collections.abc import Callable
from typing import Any

from torm.errors import HardwareError

log = logging.getLogger(__name__)

Callback = Callable[[dict[str, Any]], None]


class RosbridgeClient:
    """Connection to ``ws://host:port``; raises HardwareError naming host:port when it cannot connect.

    Args:
        host, port: the rosbridge_server websocket (Inovo controller: port 9090).
        connect_timeout_s: handshake timeout (s).
        on_disconnect: called once (with a reason string) when the connection drops.
    """

    def __init__(self, host: str, port: int = 9090, connect_timeout_s: float = 5.0,
                 on_disconnect: Callable[[str], None] | None = None) -> None:
        try:
            from websockets.sync.client import connect
        except ImportError as exc:
            raise HardwareError("the 'websockets' package is missing; pip install 'torm[hardware]'") from exc
        self.host, self.port = host, int(port)
        self.url = f"ws://{host}:{self.port}"
        self._on_disconnect = on_disconnect
        try:
            ws = connect(self.url, open_timeout=connect_timeout_s, close_timeout=1.0, max_size=None)
            # entering the context marks the connection as managed (websockets >= 17 warns otherwise); close() ends it
            self._ws = ws.__enter__()
        except Exception as exc:  # OSError, TimeoutError, InvalidHandshake, InvalidURI ...
            raise HardwareError(
                f"cannot reach rosbridge at {host}:{self.port} ({type(exc).__name__}: {exc}); check the robot "
                f"controller is on and reachable (ping {host}), that rosbridge_server runs on it "
                f"(roslaunch rosbridge_server rosbridge_websocket.launch) and listens on port {self.port}; "
                "nothing was sent"
            ) from exc
        self._ids = itertools.count(1)
        self._lock = threading.Lock()
        self._subs: dict[str, list[Callback]] = {}
        self._pending: dict[str, tuple[threading.Event, list[dict[str, Any]]]] = {}
        self._advertised: set[str] = set()
        self.connected = True
        self.disconnect_reason = ""
        self._closing = False
        self._thread = threading.Thread(target=self._receive_loop, name=f"rosbridge-{host}:{port}", daemon=True)
        self._thread.start()
        log.info("connected to rosbridge at %s", self.url)

    # -- sending -------------------------------------------------------------------------------------
    def send(self, msg: dict[str, Any]) -> None:
        """Send one protocol message; HardwareError when the connection is gone."""
        if not self.connected:
            raise HardwareError(f"rosbridge connection to {self.host}:{self.port} is closed "
                                f"({self.disconnect_reason}); reconnect before sending")
        try:
            with self._lock:
                self._ws.send(json.dumps(msg))
        except Exception as exc:
            self._mark_disconnected(f"send failed: {exc}")
            raise HardwareError(f"rosbridge send to {self.host}:{self.port} failed: {exc}") from exc

    def _next_id(self, prefix: str) -> str:
        return f"{prefix}:{next(self._ids)}"

    def advertise(self, topic: str, msg_type: str) -> None:
        if topic not in self._advertised:
            self.send({"op": "advertise", "id": self._next_id("advertise"), "topic": topic, "type": msg_type})
            self._advertised.add(topic)

    def publish(self, topic: str, msg: dict[str, Any]) -> None:
        self.send({"op": "publish", "topic": topic, "msg": msg})

    def subscribe(self, topic: str, msg_type: str, callback: Callback, queue_length: int = 1) -> None:
        self._subs.setdefault(topic, []).append(callback)
        self.send({"op": "subscribe", "id": self._next_id("subscribe"), "topic": topic, "type": msg_type,
                   "queue_length": queue_length})

    def call_service(self, service: str, args: dict[str, Any] | None = None, timeout_s: float = 5.0,
                     wait: bool = True) -> dict[str, Any]:
        """Call ``service`` and return its ``values``; HardwareError on timeout or ``result: false``."""
        cid = self._next_id(f"call_service:{service}")
        ev: threading.Event = threading.Event()
        box: list[dict[str, Any]] = []
        if wait:
            self._pending[cid] = (ev, box)
        self.send({"op": "call_service", "id": cid, "service": service, "args": args or {}})
        if not wait:
            return {}
        try:
            if not ev.wait(timeout_s):
                raise HardwareError(f"service {service} on {self.host}:{self.port} did not answer within "
                                    f"{timeout_s} s; is the robot driver running (rosservice list)?")
        finally:
            self._pending.pop(cid, None)
        if not box:
            raise HardwareError(f"rosbridge connection lost while calling {service} ({self.disconnect_reason})")
        resp = box[0]
        if resp.get("result") is False:
            raise HardwareError(f"service {service} failed: {resp.get('values')}")
        return resp.get("values") or {}

    # -- receiving -----------------------------------------------------------------------------------
    def _receive_loop(self) -> None:
        reason = "connection closed by the server"
        try:
            for raw in self._ws:
                try:
                    msg = json.loads(raw)
                except (TypeError, ValueError):
                    log.warning("rosbridge: ignoring a non-JSON message")
                    continue
                self._dispatch(msg)
        except Exception as exc:
            reason = f"connection lost: {type(exc).__name__}: {exc}"
        self._mark_disconnected(reason)

    def _dispatch(self, msg: dict[str, Any]) -> None:
        op = msg.get("op")
        if op == "publish":
            for cb in list(self._subs.get(msg.get("topic", ""), ())):
                try:
                    cb(msg.get("msg") or {})
                except Exception:  # a bad callback must not kill the receive thread
                    log.exception("rosbridge callback for %s failed", msg.get("topic"))
        elif op == "service_response":
            pending = self._pending.get(str(msg.get("id")))
            if pending is not None:
                pending[1].append(msg)
                pending[0].set()
        elif op == "status":
            log.warning("rosbridge status (%s): %s", msg.get("level"), msg.get("msg"))

    def _mark_disconnected(self, reason: str) -> None:
        if not self.connected:
            return
        self.connected = False
        self.disconnect_reason = "closed by us" if self._closing else reason
        for ev, _ in list(self._pending.values()):
            ev.set()
        if not self._closing:
            log.error("rosbridge %s: %s", self.url, reason)
            if self._on_disconnect is not None:
                self._on_disconnect(reason)

    def close(self) -> None:
        """Close the socket (idempotent)."""
        self._closing = True
        with contextlib.suppress(Exception):
            self._ws.close()
        self._thread.join(timeout=2.0)
        self._mark_disconnected("closed by us")
