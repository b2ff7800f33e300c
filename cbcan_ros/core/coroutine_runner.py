"""An asyncio event loop on a thread of its own: for requests made of several steps.

The PLC mailbox chains SDOs on one, the drives run their CiA 402 sequences on another. Each
coroutine is awaited by a ``concurrent.futures.Future``, so neither the bus thread nor the ROS
executor ever runs a coroutine or waits for one.
"""

import asyncio
from concurrent.futures import Future
import threading
from typing import Callable, Coroutine, Optional


class CoroutineRunner:
    """An asyncio event loop on a thread of its own, for calls that chain several steps.

    ``submit`` returns a ``concurrent.futures.Future``, so such a call is answered like any
    other (through the ROS layer's ``DeferredService``), and the ROS executor never runs
    coroutines.
    """

    def __init__(self, name: str):
        self._loop = asyncio.new_event_loop()
        self._closed = False
        self._lock = threading.Lock()
        self._thread = threading.Thread(target=self._loop.run_forever, name=name, daemon=True)
        self._thread.start()

    def submit(self, coroutine: Coroutine) -> Optional[Future]:
        """Run ``coroutine`` on the loop; return the future of its result, None once closed."""
        with self._lock:
            if self._closed:
                coroutine.close()
                return None
            return asyncio.run_coroutine_threadsafe(coroutine, self._loop)

    def call_soon(self, callback: Callable[[], None]) -> None:
        """Run ``callback()`` on the loop's thread soon (from any thread); not once closed."""
        with self._lock:
            if not self._closed:
                self._loop.call_soon_threadsafe(callback)

    def close(self) -> None:
        """Stop the loop (after the calls on it were answered) and end its thread."""
        with self._lock:
            if self._closed:
                return
            self._closed = True

        async def cancel_all() -> None:
            tasks = asyncio.all_tasks() - {asyncio.current_task()}
            for task in tasks:
                task.cancel()
            await asyncio.gather(*tasks, return_exceptions=True)

        # Each cancelled coroutine still gives its answer (see its CancelledError handling).
        asyncio.run_coroutine_threadsafe(cancel_all(), self._loop).result()
        self._loop.call_soon_threadsafe(self._loop.stop)
        self._thread.join()
        self._loop.close()
