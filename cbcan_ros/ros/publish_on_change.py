"""A whole picture (every node's state, every device's boot) published on every change.

A change is told from a bus, boot or watcher thread, which must not wait for DDS; the picture
is published by a thread of its own (rclpy's EventsExecutor takes no guard conditions). One
publication covers every change told before it, so a storm of changes (all nodes started at
once) costs a few publications, not one each.
"""

import threading
from typing import Callable


class PublishOnChange:
    """Calls ``publish()`` from a thread of its own after each ``changed()``."""

    def __init__(self, publish: Callable[[], None], name: str):
        self._publish = publish
        self._changed = threading.Event()
        self._closing = False
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)
        self._thread.start()

    def changed(self) -> None:
        """Say the picture changed (any thread; it returns at once)."""
        self._changed.set()

    def close(self) -> None:
        """Publish no more; returns once the thread ended."""
        self._closing = True
        self._changed.set()
        self._thread.join()

    def _run(self) -> None:
        while True:
            self._changed.wait()
            if self._closing:
                return
            self._changed.clear()
            self._publish()
