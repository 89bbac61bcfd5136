"""SIGINT and SIGTERM for runs that last days: stop promptly, keep what can be kept, say how to go on.

Python runs a signal handler only when the main thread returns to the interpreter, and a compiled
chunk or an XLA compilation keeps it away for minutes; a ``KeyboardInterrupt`` raised in the wrong
place (a garbage-collection callback, a thread's teardown) is swallowed or crashes the runtime. So
:class:`StopController` never raises into the main thread. Its Python handler does nothing; the
signal number reaches a watcher thread through ``signal.set_wakeup_fd`` at once, whatever the main
thread is doing, and the watcher decides:

* during training, when the running chunk is expected to end within ``grace_s`` (and the
  checkpoint after it fits in that time too), it asks the host loop to stop at that boundary,
  where the trainer writes a checkpoint and returns;
* otherwise (start-up, a chunk that runs for long, a second signal) it ends the process at once
  with ``os._exit``. Nothing is lost that a resume needs: checkpoints are committed atomically and
  metric lines are appended and forced to disk, and a resume drops whatever follows the newest
  checkpoint. The message says what is kept.

The exit status is the shell's convention, 128 + the signal number (130 for SIGINT, 143 for SIGTERM).
"""

from __future__ import annotations

import os
import signal
import sys
import threading
import time
from collections.abc import Callable

SIGNALS = (signal.SIGINT, signal.SIGTERM)
DEFAULT_GRACE_S = 30.0  # what a cluster typically allows between SIGTERM and SIGKILL


def exit_status(signum: int) -> int:
    return 128 + int(signum)


class RunInterrupted(Exception):
    """Raised by the trainer after it stopped cleanly at a chunk boundary on request."""

    def __init__(self, signum: int, kept: str):
        super().__init__(f"stopped by {signal.Signals(signum).name}; {kept}")
        self.signum = int(signum)
        self.kept = kept


class StopController:
    """Watches SIGINT/SIGTERM while installed (a context manager; main thread only).

    The trainer tells it where the run stands: :meth:`training` when a chunk starts (with the time
    the chunk and a checkpoint after it are expected to take), :meth:`idle` when it waits for
    nothing that a stop could keep, and :meth:`keep` with what a resume would continue from. It
    asks :attr:`requested` at every chunk boundary.
    """

    def __init__(
        self,
        grace_s: float | None = None,
        resume_hint: str = "",
        write: Callable[[str], None] | None = None,
        hard_exit: Callable[[int], None] = os._exit,
    ):
        if grace_s is None:
            grace_s = float(os.environ.get("XRL_JAX_STOP_GRACE_S", DEFAULT_GRACE_S))
        self.grace_s = grace_s
        self.resume_hint = resume_hint
        self._write = write or (lambda text: print(text, file=sys.stderr, flush=True))
        self._hard_exit = hard_exit
        self._lock = threading.Lock()
        self._requested: int | None = None
        self._boundary_at: float | None = None  # monotonic time the running chunk should end, or None
        self._kept = "nothing has been trained yet"
        self._previous: dict[int, object] = {}
        self._pipe: tuple[int, int] | None = None
        self._old_wakeup_fd = -1
        self._thread: threading.Thread | None = None

    # ---- what the trainer reports -------------------------------------------------------------
    @property
    def requested(self) -> int | None:
        """The signal that asked for a stop at the next chunk boundary, or None."""
        return self._requested

    def training(self, expected_s: float | None) -> None:
        """A chunk starts and should end (checkpoint included) ``expected_s`` from now (None: unknown)."""
        with self._lock:
            self._boundary_at = None if expected_s is None else time.monotonic() + expected_s

    def idle(self) -> None:
        """Nothing a graceful stop could keep is running (start-up, evaluation, the summary)."""
        with self._lock:
            self._boundary_at = None

    def keep(self, kept: str) -> None:
        """What a resume would continue from, for the messages (e.g. "checkpoint at step 2000 ...")."""
        with self._lock:
            self._kept = kept

    # ---- signal handling ----------------------------------------------------------------------
    def handle(self, signum: int) -> None:
        """Decide what ``signum`` does now (called by the watcher thread; tests call it directly)."""
        name = signal.Signals(signum).name
        with self._lock:
            again = self._requested is not None
            self._requested = signum
            remaining = None if self._boundary_at is None else self._boundary_at - time.monotonic()
            kept = self._kept
        resume = f"; continue with: {self.resume_hint}" if self.resume_hint else ""
        if not again and remaining is not None and remaining <= self.grace_s:
            self._write(
                f"\n{name}: stopping after the current chunk (~{max(remaining, 0):.0f} s) with a "
                f"checkpoint; send it again to stop at once"
            )
            return
        why = "again" if again else ("the next chunk boundary is far" if remaining is not None else "")
        self._write(f"\n{name}{' (' + why + ')' if why else ''}: stopping now; {kept}{resume}")
        sys.stdout.flush()
        self._hard_exit(exit_status(signum))

    def _watch(self, read_fd: int) -> None:
        while True:
            try:
                data = os.read(read_fd, 16)
            except OSError:
                return
            if not data:
                return
            for signum in data:
                if signum in SIGNALS:
                    self.handle(signum)

    def __enter__(self) -> StopController:
        if threading.current_thread() is not threading.main_thread():
            raise RuntimeError("StopController must be installed from the main thread")
        read_fd, write_fd = os.pipe()
        os.set_blocking(write_fd, False)
        self._pipe = (read_fd, write_fd)
        for signum in SIGNALS:
            self._previous[signum] = signal.signal(signum, lambda *_: None)
        self._old_wakeup_fd = signal.set_wakeup_fd(write_fd, warn_on_full_buffer=False)
        self._thread = threading.Thread(target=self._watch, args=(read_fd,), daemon=True, name="stop-watch")
        self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        signal.set_wakeup_fd(self._old_wakeup_fd)
        for signum, handler in self._previous.items():
            signal.signal(signum, handler)
        if self._pipe is not None:
            os.close(self._pipe[1])  # the watcher reads end-of-file and returns
            self._thread.join(timeout=5)
            os.close(self._pipe[0])
            self._pipe = None
