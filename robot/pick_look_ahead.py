"""The picker's look ahead: the next cycle's first frame, taken while the arm still holds the part at the place pose
and perceived in a worker thread while the arm lets go (``robot.picker``, ``PickerConfig.look_while_placing``).

One look at a time, one worker per run (``LookAhead.running``): only perception runs in it, never a robot or gripper
command, and the perception is never called from two threads at once (a new look, a dropped one and the end of the
run all wait for the look in flight first). A look's error is raised where its result is used (``Future.result``);
a dropped look's is not (it was of a pile that the cycle looks at again). The robot's moves are awaited by polling
(``robot.ur_motion``), which leaves the interpreter to the worker, and perception's native code (onnxruntime,
open3d, numpy) runs beside it.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from contextlib import contextmanager
from typing import Any

from perception.camera import Frame


class LookAhead:
    """The look taken ahead, if any: ``start`` takes one, ``take`` hands it to the next cycle, ``drop`` forgets it."""

    def __init__(self) -> None:
        self._worker: ThreadPoolExecutor | None = None
        self._look: tuple[Frame, Future] | None = None

    @contextmanager
    def running(self) -> Iterator[None]:
        """The worker of one run; on the way out a look in flight is waited for and dropped, so no thread outlives
        the run."""
        self._worker = ThreadPoolExecutor(max_workers=1, thread_name_prefix="look-ahead")
        try:
            yield
        finally:
            self.drop()
            self._worker.shutdown(wait=True)
            self._worker = None

    def start(self, capture: Callable[[], Frame], perceive: Callable[[Frame], Any]) -> None:
        """Takes a frame now and perceives it in the worker; nothing outside a run (``running``)."""
        if self._worker is None:
            return
        self.drop()
        frame = capture()
        self._look = (frame, self._worker.submit(perceive, frame))

    def take(self) -> tuple[Frame, Future] | None:
        """The look taken ahead and its perception (running or done), or None; it is the caller's from now on."""
        look, self._look = self._look, None
        return look

    def drop(self) -> None:
        """Forgets the look taken ahead, after its perception has ended (its result or error unused)."""
        look = self.take()
        if look is not None:
            look[1].exception()  # waits for it
