"""The child side of :mod:`brave6d.capture.ur_worker`: ur-rtde behind a pipe, one JSON line per call.

Run as ``python ur_worker_child.py REPLY_FD``: requests arrive on stdin, answers go to REPLY_FD
(ur-rtde itself prints to stdout and stderr, which the parent sends to a log file). Standard
library and ur-rtde only, so it starts fast; Ctrl-C is ignored (the parent decides).
"""

from __future__ import annotations

import json
import os
import signal
import sys
from typing import Any


def _plain(value: Any) -> Any:
    """A ur-rtde return value as JSON (AsyncOperationStatus -> its int value)."""
    if value is None or isinstance(value, (bool, int, float, str)):
        return value
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    if hasattr(value, "value") and callable(value.value):
        return int(value.value())
    return repr(value)


def _child(reply_fd: int) -> int:
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    out = os.fdopen(reply_fd, "w", buffering=1)
    ifaces: dict[str, Any] = {}
    for line in sys.stdin:
        try:
            request = json.loads(line)
            ident, target, method, args = request["id"], request["target"], request["method"], request["args"]
        except (ValueError, KeyError, TypeError):
            return 2
        reply: dict[str, Any] = {"id": ident}
        try:
            if target == "worker" and method == "connect":
                import rtde_control
                import rtde_receive

                ifaces["receive"] = rtde_receive.RTDEReceiveInterface(args[0])
                try:
                    ifaces["control"] = rtde_control.RTDEControlInterface(args[0])
                except BaseException:
                    ifaces["receive"].disconnect()
                    raise
                reply["ok"] = None
            elif target == "worker" and method == "close":
                for name in ("control", "receive"):
                    if name in ifaces:
                        try:
                            ifaces[name].disconnect()
                        except Exception:  # noqa: BLE001 - closing must not fail
                            pass
                out.write(json.dumps({"id": ident, "ok": None}) + "\n")
                out.flush()
                os._exit(0)  # ur-rtde's destructors would disconnect (and sleep 0.5 s) once more
            else:
                reply["ok"] = _plain(getattr(ifaces[target], method)(*args))
        except Exception as exc:  # noqa: BLE001 - every library error goes back as text
            reply = {"id": ident, "error": f"{type(exc).__name__}: {exc}"}
        out.write(json.dumps(reply) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(_child(int(sys.argv[1])))
