"""Ctrl-C inside a compiled run: a compiled loop asks the host, every few thousand steps, whether SIGINT arrived.

While XLA runs, Python's own SIGINT handler cannot run (the main thread is inside the
computation), so a long ``simulate`` would ignore Ctrl-C until it ends.  :func:`watching`
routes the signal's number to a pipe as it arrives (``signal.set_wakeup_fd``, written by
the C-level handler from any thread), and :func:`poll`, called from inside the compiled
loop through ``jax.debug.callback``, reads it and raises, which aborts the computation;
Python's handler then raises ``KeyboardInterrupt`` in the main thread as usual, and where it ran before the
abort reached the main thread (a signal in the first instants of a run), :func:`watching` turns the runtime's error
around the poll's ``KeyboardInterrupt`` into one.
"""

from __future__ import annotations

import contextlib
import os
import signal
import threading

__all__ = ["POLL_ABOVE", "POLL_STEPS", "poll", "watching"]

POLL_STEPS = 1024
"""Steps between two polls of a compiled loop (a chunk's step is far dearer than the poll)."""

POLL_ABOVE = 2**27
"""Work (path-steps × state components) above which a run polls for Ctrl-C.  A smaller run ends within seconds, and
its program has no host callback, which JAX's persistent compilation cache requires (JAX 0.10 writes no entry for a
program with one)."""

_pipe: tuple[int, int] | None = None
_pending = threading.Event()


def _drain() -> None:
    if _pipe is None:
        return
    try:
        data = os.read(_pipe[0], 512)
    except BlockingIOError:
        return
    if signal.SIGINT in data:
        _pending.set()


def poll(*_) -> None:
    """Raise once SIGINT arrived during :func:`watching` (called on the host from a compiled loop)."""
    _drain()
    if _pending.is_set():
        raise KeyboardInterrupt("interrupted (SIGINT) during a compiled run")


_depth = 0


@contextlib.contextmanager
def watching():
    """Route SIGINT to :func:`poll` while the block runs (main thread only; elsewhere a no-op; nests).

    Computations dispatched in the block must finish in it (``jax.block_until_ready``) to be interruptible.
    """
    global _pipe, _depth
    if _depth or threading.current_thread() is not threading.main_thread():
        _depth += 1
        try:
            yield
        finally:
            _depth -= 1
        return
    if _pipe is None:
        _pipe = os.pipe()
        for fd in _pipe:
            os.set_blocking(fd, False)
    _pending.clear()
    try:
        previous = signal.set_wakeup_fd(_pipe[1], warn_on_full_buffer=False)
    except ValueError:  # not the main interpreter
        yield
        return
    _depth = 1
    try:
        yield
    except Exception as error:  # a KeyboardInterrupt inside the compiled loop's callback (the poll's, or Python's
        # handler running in it) reaches here wrapped in the runtime's own error; the pipe says SIGINT arrived
        _drain()
        if _pending.is_set():
            raise KeyboardInterrupt("interrupted (SIGINT) during a compiled run") from error
        raise
    finally:
        _depth = 0
        signal.set_wakeup_fd(previous)
        _drain()
        _pending.clear()
