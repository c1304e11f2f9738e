"""Child processes that end with their parent: evaluation workers and the runs a grid trains side
by side each watch the process that started them."""

from __future__ import annotations

import os
import threading
import time


def exit_with_parent(parent: int, poll_seconds: float = 1.0, signum: int | None = None) -> None:
    """Worker initializer: exit when process ``parent`` is gone. A pool's workers otherwise outlive
    a parent killed without a clean shutdown (SIGTERM, SIGKILL), each holding a scene library.
    ``signum``: send this process that signal instead (a trainer's SIGTERM: checkpoint, then end)."""

    def watch() -> None:
        while os.getppid() == parent:
            time.sleep(poll_seconds)
        if signum is None:
            os._exit(1)
        os.kill(os.getpid(), signum)

    threading.Thread(target=watch, daemon=True, name="exit-with-parent").start()
