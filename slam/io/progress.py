"""Progress reporting, the one helper every long loop uses: a tqdm bar on a terminal, plain periodic lines in a log.

A bar redrawn with carriage returns is right on a terminal and wrong in a log file (one enormous line), so
`bar(...)` looks at the stream it writes to (stderr by default): a terminal gets tqdm, anything else gets one
plain line every `interval` seconds and a last one when the loop ends:

    [team] rounds 12/60 (20%)  1m04s elapsed, ~4m16s left  keyframes 8  Gaussians 41k ...

    from swarmsplat.slam.io.progress import bar
    with bar(n, "[agent_0] frames", unit="frame") as b:
        for i in range(n):
            ...
            b.update(1, f"{len(gmap)} Gaussians")     # the text after the counts (optional)

Library code deep in a call chain (the server's map refinement) reports through `reporting(...)`, so the flag
does not have to be threaded through every signature: `with reporting(True): team.refine_map()` turns on the bars
that code opens with `bar(..., enabled=None)`. Off by default: a library call prints nothing unless asked.
"""

from __future__ import annotations

import contextlib
import contextvars
import math
import os
import sys
import time
from typing import IO, Iterator

# Seconds between plain lines when the stream is not a terminal (SWARMSPLAT_PROGRESS_INTERVAL overrides).
DEFAULT_INTERVAL = 10.0

_enabled: contextvars.ContextVar[bool] = contextvars.ContextVar("swarmsplat_progress", default=False)


@contextlib.contextmanager
def reporting(enabled: bool = True) -> Iterator[None]:
    """Within the block, bars opened with enabled=None show (or stay silent when `enabled` is False)."""
    token = _enabled.set(bool(enabled))
    try:
        yield
    finally:
        _enabled.reset(token)


def is_terminal(stream: IO) -> bool:
    try:
        return bool(stream.isatty())
    except (AttributeError, ValueError):  # no isatty, or a closed stream
        return False


def format_seconds(s: float) -> str:
    """12s, 4m05s, 1h02m."""
    if not math.isfinite(s) or s < 0:
        return "?"
    s = int(round(s))
    if s < 60:
        return f"{s}s"
    if s < 3600:
        return f"{s // 60}m{s % 60:02d}s"
    return f"{s // 3600}h{s % 3600 // 60:02d}m"


def env_interval() -> float:
    """Seconds between plain lines: $SWARMSPLAT_PROGRESS_INTERVAL, else DEFAULT_INTERVAL."""
    raw = os.environ.get("SWARMSPLAT_PROGRESS_INTERVAL")
    if raw is None:
        return DEFAULT_INTERVAL
    try:
        v = float(raw)
    except ValueError:
        v = float("nan")
    if not math.isfinite(v) or v < 0:
        from swarmsplat.kernels.errors import InputError

        raise InputError(f"SWARMSPLAT_PROGRESS_INTERVAL must be a number of seconds >= 0, got {raw!r}")
    return v


class Bar:
    """Counts done out of `total` (None: unknown). Use `bar(...)` to make one."""

    def __init__(self, total: int | None, desc: str, *, unit: str = "it", stream: IO | None = None,
                 enabled: bool = True, tty: bool | None = None, interval: float | None = None, clock=time.monotonic):
        self.total, self.desc, self.unit = total, desc, unit
        self.stream = stream if stream is not None else sys.stderr
        self.enabled = enabled
        self.n = 0
        self.text = ""
        self._clock = clock
        self._t0 = self._last = clock()
        self._tqdm = None
        self._closed = False
        self.interval = env_interval() if interval is None else float(interval)
        if enabled and (is_terminal(self.stream) if tty is None else tty):
            from tqdm import tqdm

            self._tqdm = tqdm(total=total, desc=desc, unit=unit, file=self.stream, dynamic_ncols=True)

    def set_total(self, total: int | None) -> None:
        """The total, once it is known (a bar may start before it is)."""
        self.total = total
        if self._tqdm is not None:
            self._tqdm.total = total
            self._tqdm.refresh()

    def update(self, n: int = 1, text: str | None = None) -> None:
        """`n` more done; `text` replaces the status shown after the counts."""
        self.n += n
        if text is not None:
            self.text = text
        if not self.enabled:
            return
        if self._tqdm is not None:
            if text is not None:
                self._tqdm.set_postfix_str(text, refresh=False)
            self._tqdm.update(n)
            return
        now = self._clock()
        if now - self._last >= self.interval and not self._finished():
            self._last = now
            self._print(now)

    def _finished(self) -> bool:
        return self.total is not None and self.n >= self.total

    def line(self, now: float | None = None) -> str:
        """The plain line for the current state."""
        el = (self._clock() if now is None else now) - self._t0
        if self.total:
            head = f"{self.desc} {self.n}/{self.total} ({100 * self.n / self.total:.0f}%)"
            left = el / self.n * (self.total - self.n) if self.n else float("nan")
            tail = f"{format_seconds(el)} elapsed" + (f", ~{format_seconds(left)} left" if self.n < self.total else "")
        else:
            head, tail = f"{self.desc} {self.n} {self.unit}", f"{format_seconds(el)} elapsed"
        if self.n and el > 0:
            rate = self.n / el
            tail += f", {rate:.2f} {self.unit}/s" if rate >= 1 else f", {1 / rate:.1f} s/{self.unit}"
        return f"{head}  {tail}" + (f"  {self.text}" if self.text else "")

    def _print(self, now: float) -> None:
        print(self.line(now), file=self.stream, flush=True)

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        if self._tqdm is not None:
            self._tqdm.close()
        elif self.enabled and (self.n or self.total == 0):
            self._print(self._clock())

    def __enter__(self) -> "Bar":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def bar(total: int | None, desc: str, *, unit: str = "it", enabled: bool | None = True, stream: IO | None = None,
        tty: bool | None = None, interval: float | None = None) -> Bar:
    """A progress bar on `stream` (stderr). enabled=None follows the enclosing `reporting(...)` block (off outside
    one). tty=None decides bar vs plain lines from the stream; interval: seconds between plain lines."""
    on = _enabled.get() if enabled is None else bool(enabled)
    return Bar(total, desc, unit=unit, stream=stream, enabled=on, tty=tty, interval=interval)


class TeamRounds:
    """The callback `Team.run(progress=...)` calls once per round, (done, total, status): it advances a rounds bar
    and hands the team to a live observer (slam.view.live), if there is one."""

    def __init__(self, team, *, enabled: bool, observer=None, stream: IO | None = None):
        self.team, self.observer = team, observer
        self.bar = bar(None, "[team] rounds", unit="round", enabled=enabled, stream=stream)  # clock starts now

    def __call__(self, done: int, total: int, status: str) -> None:
        if self.bar.total != total:
            self.bar.set_total(total)
        self.bar.update(done - self.bar.n, status)
        if self.observer is not None:
            self.observer(self.team)

    def close(self) -> None:
        self.bar.close()

    def __enter__(self) -> "TeamRounds":
        return self

    def __exit__(self, *exc) -> None:
        self.close()
