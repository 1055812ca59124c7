"""Stop the real arm from outside the process that drove it: cancel every goal, then disable.

A trial's own stop path (:meth:`torm.hardware.backend.RealBackend.close`, run on SIGTERM too) cannot run
when its process is SIGKILLed, runs out of memory or segfaults. The benchmark's driver (the local pool's
runner or the Ray driver) then calls :func:`stop_arm` with the trial's hardware config: a fresh rosbridge
connection that publishes a cancel of every goal of the trajectory action (goal id ``""``) and calls the
disable service, bounded by ``timeout_s``. Both are safe on an arm at rest and on one already disabled.
"""

from __future__ import annotations

import logging
import time
from typing import Any

from torm.errors import HardwareError
from torm.hardware.command_log import CommandLog
from torm.hardware.config import HardwareConfig
from torm.hardware.rosbridge import CANCEL_TYPE
from torm.hardware.rosbridge_client import RosbridgeClient

log = logging.getLogger(__name__)

#: Default bound of :func:`stop_arm` (s): connection, cancel and the disable service's answer together.
STOP_TIMEOUT_S = 3.0


def stop_arm(hw: HardwareConfig, timeout_s: float = STOP_TIMEOUT_S, reason: str = "driver stop") -> dict[str, Any]:
    """Cancel every trajectory goal and disable the arm over a new rosbridge connection.

    Args:
        hw: the hardware config of the trial whose process died (host, port, action namespace, services).
        timeout_s: bound on the whole stop (s).
        reason: written to the command log.

    Returns:
        ``{"cancel": bool, "disable": bool, "elapsed_s": float, "error": str | None}``: what was sent and
        answered. Never raises: a driver must go on stopping the other trials.
    """
    t0 = time.monotonic()
    out: dict[str, Any] = {"cancel": False, "disable": False, "elapsed_s": 0.0, "error": None}
    if hw.dry_run:
        out["error"] = "dry run: nothing was sent to the arm"
        return out
    cmd_log = CommandLog(hw.command_log)
    client = None
    try:
        client = RosbridgeClient(hw.host, hw.port, min(hw.connect_timeout_s, timeout_s))
        topic = f"{hw.action_ns.rstrip('/')}/cancel"
        client.advertise(topic, CANCEL_TYPE)
        cmd_log.write("cancel", topic=topic, goal_id="", reason=reason)
        client.publish(topic, {"stamp": {"secs": 0, "nsecs": 0}, "id": ""})
        out["cancel"] = True
        cmd_log.write("call_service", service=hw.disable_service, args={}, reason=reason)
        left = max(0.1, timeout_s - (time.monotonic() - t0))
        values = client.call_service(hw.disable_service, {}, timeout_s=left)
        out["disable"] = values.get("success") is not False
    except (HardwareError, OSError) as exc:
        out["error"] = str(exc)
        log.error("stopping the arm at %s:%d from the driver failed: %s", hw.host, hw.port, exc)
    finally:
        if client is not None:
            client.close()
        out["elapsed_s"] = round(time.monotonic() - t0, 3)
    log.warning("arm at %s:%d stopped from the driver (%s): cancel %s, disable %s in %.2f s", hw.host, hw.port,
                reason, out["cancel"], out["disable"], out["elapsed_s"])
    return out


__all__ = ["STOP_TIMEOUT_S", "stop_arm"]
