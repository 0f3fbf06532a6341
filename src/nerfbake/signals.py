"""How nerfbake's commands end on SIGTERM."""
from __future__ import annotations

import signal
import threading


def terminate_like_ctrl_c() -> None:
    """SIGTERM (``kill``, a job scheduler, a closed container) ends a command as Ctrl-C does: cleanup code runs, so
    ``process`` and the bakes remove their hidden temporary folders and trainers save a checkpoint (their own handler
    stops at the next step). Python's default would end the process at once and leave them behind.

    Call it again after importing pycolmap: its glog failure handler takes over SIGTERM and aborts. A signal that
    arrives inside a long native call (pycolmap's matching or mapping) takes effect when that call returns."""
    if threading.current_thread() is not threading.main_thread():
        return

    def handler(signum, frame):
        raise KeyboardInterrupt

    signal.signal(signal.SIGTERM, handler)
