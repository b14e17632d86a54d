"""A long run never loses its work: corrupt frames are skipped, and an interrupt or a failure mid-run saves what
exists before the run ends.

    @guarded("run")
    def run_sequence(...):
        ...
        keep(lambda status, reason: write_partial_agent(agent, out, status=status, reason=reason, ...))
        for i in range(n):
            f = read_frame(seq, i, agent, strict=strict)   # None: unreadable, skipped with one warning
            ...

While a `guarded` function runs, SIGINT and SIGTERM raise `Interrupted` (a KeyboardInterrupt) in the main thread
at once, even where the parent shell had set SIGINT to be ignored (a job started with `&` from a script). When
the function raises, the last `keep(save)` callback runs as save(status, reason) — status "interrupted" or
"failed" — and the exception goes on to the caller (slam.cli exits 130 / the error's code). A second signal
while saving ends the process at once (exit 130) without writing more; every output is written atomically, so a
file is there whole or not at all.
"""

from __future__ import annotations

import functools
import os
import signal
import sys
import threading
import warnings
from contextlib import contextmanager
from typing import Callable

from swarmsplat.kernels.errors import InputError, OutputError

SIGNALS = (signal.SIGINT, signal.SIGTERM)
Save = Callable[[str, str], object]  # (status, reason) -> where the partial results went (printed) or None


class Interrupted(KeyboardInterrupt):
    """SIGINT or SIGTERM arrived during a guarded run; str() is the signal's name."""


def _hard_exit(signum, frame) -> None:
    os.write(2, f"\n{signal.Signals(signum).name} again: exiting now\n".encode())
    os._exit(130)


def _raise_interrupted(signum, frame) -> None:
    for s in SIGNALS:  # the next signal ends the process at once
        signal.signal(s, _hard_exit)
    raise Interrupted(signal.Signals(signum).name)


class RunGuard:
    """One guarded run: `save` is what to call if it ends early (None: nothing worth keeping yet)."""

    def __init__(self, what: str, save: Save | None = None):
        self.what, self.save = what, save


_ACTIVE: list[RunGuard] = []  # innermost last (a demo runs a team, ...)


def keep(save: Save) -> None:
    """From inside a guarded run: if the run ends early, call save(status, reason) to write what exists."""
    if _ACTIVE:
        _ACTIVE[-1].save = save


@contextmanager
def guarded_run(save: Save | None = None, *, what: str = "run"):
    """Run the body with SIGINT/SIGTERM raising `Interrupted`; if it raises, call the guard's save(status, reason)
    (when set; `keep` sets it) with status "interrupted" (reason: the signal, e.g. "SIGINT") or "failed" (reason:
    "<ExceptionType>: <message>"), then re-raise. Yields the RunGuard. Signal handlers are installed only in the
    main thread and restored on the way out (after an interrupt, a further signal still exits at once)."""
    guard = RunGuard(what, save)
    main = threading.current_thread() is threading.main_thread()
    previous = {s: signal.getsignal(s) for s in SIGNALS} if main else {}
    for s in previous:
        signal.signal(s, _raise_interrupted)
    _ACTIVE.append(guard)
    interrupted = False
    try:
        yield guard
    except KeyboardInterrupt as e:
        interrupted = True
        _save(guard, e, "interrupted", str(e) if isinstance(e, Interrupted) else "KeyboardInterrupt", main)
        raise
    except Exception as e:
        _save(guard, e, "failed", f"{type(e).__name__}: {e}", main)
        raise
    finally:
        _ACTIVE.remove(guard)
        for s, h in previous.items():
            if interrupted and h is _raise_interrupted:  # an outer guarded run: it still saves, then exits
                h = _hard_exit
            signal.signal(s, h if h is not None else signal.SIG_DFL)


def guarded(what: str):
    """Decorator: the function runs inside `guarded_run(what=what)`; it calls `keep` once it has work to keep."""

    def wrap(fn):
        @functools.wraps(fn)
        def run(*args, **kwargs):
            with guarded_run(what=what):
                return fn(*args, **kwargs)

        return run

    return wrap


def _save(guard: RunGuard, exc: BaseException, status: str, reason: str, main: bool) -> None:
    if guard.save is None or getattr(exc, "_swarmsplat_saved", False):  # nothing yet, or an inner run saved
        return
    if main:
        for s in SIGNALS:  # a signal while saving: out at once, the atomic writes leave no half file
            signal.signal(s, _hard_exit)
    what = guard.what
    # A file the disk refused (full, read-only): the error's own line says so, and the partial results, tried
    # quietly, mostly meet the same disk; the folder's last checkpoint and journal are what --resume needs.
    quiet = isinstance(exc, OutputError)
    if not quiet:
        print(f"\n[{what}] {status} ({reason}); writing what was done so far", file=sys.stderr, flush=True)
    try:
        where = guard.save(status, reason)
    except Exception as e:  # noqa: BLE001 - the run's own exception matters more; keep it
        if not quiet:
            print(f"[{what}] could not write the partial results: {type(e).__name__}: {e}", file=sys.stderr)
        return
    try:
        exc._swarmsplat_saved = True
    except AttributeError:
        pass
    if where and not quiet:
        print(f"[{what}] partial results (status '{status}') in {where}", file=sys.stderr, flush=True)


# Reading a frame fails with these when its file is missing, truncated, corrupt or of the wrong kind.
_READ_ERRORS = (InputError, OSError)


def read_frame(seq, i: int, skipper, *, strict: bool = False):
    """`seq[i]`, or None when the frame cannot be read: one warning line, and `skipper.skip_frame(i, reason)`
    records it (Agent.skip_frame: listed in metrics.json `skipped_frames`). strict: raise instead."""
    try:
        return seq[i]
    except _READ_ERRORS as e:
        if strict:
            raise
        reason = f"unreadable: {e}"
    except Exception as e:  # noqa: BLE001 - a decoder failing on a corrupt file (cv2.error, ...)
        if strict or not _looks_like_decoding(e):
            raise
        reason = f"unreadable: {type(e).__name__}: {e}"
    skipper.skip_frame(i, reason)
    return None


def _looks_like_decoding(e: Exception) -> bool:
    return type(e).__module__.split(".")[0] in ("cv2", "PIL", "imageio")


class SkipLog:
    """Frames a runner without an Agent skipped (swarm robots, pairs): `skip_frame` warns once per frame and keeps
    {"frame", "reason"} rows (plus "agent" when given) for metrics.json `skipped_frames`."""

    def __init__(self, agent: str | None = None, *, quiet: bool = False):
        self.agent, self.quiet = agent, quiet  # quiet: a look-ahead read; the run proper warns about the frame
        self.rows: list[dict] = []

    def skip_frame(self, index: int, reason: str) -> None:
        if not self.quiet:
            warn_skipped(self.agent or "input", index, reason)
        row = {"frame": int(index), "reason": reason}
        self.rows.append({"agent": self.agent, **row} if self.agent else row)


def warn_skipped(name: str, index: int, reason: str) -> None:
    warnings.warn(f"{name}: frame {index} skipped: {reason}", RuntimeWarning, stacklevel=3)
