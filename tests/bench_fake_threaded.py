"""A module that starts a thread when imported: a fork server that preloads it must refuse to fork."""

from __future__ import annotations

import threading
import time

_STARTED = threading.Thread(target=time.sleep, args=(3600,), daemon=True)
_STARTED.start()


def run(spec, overrides=(), record_path=None):  # noqa: ANN001, ANN201 - a stand-in trial, never meant to run
    raise AssertionError("the fork server should have been refused")
