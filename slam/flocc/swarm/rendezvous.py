"""Rendezvous schedule: which robots can talk at which tick (FLOCC-SLAM's "within communication range").

A schedule is a list of windows `[start, end)` in ticks, each naming a group of robots that are all in range of
one another during it; outside every window a robot is alone. In-process runs apply it in the simulated network;
Zenoh runs apply it on both ends (a robot neither sends to nor accepts from a robot it is not linked with).

YAML form (`--schedule FILE`):

    ticks: 80            # length of the run
    frames_per_tick: 2   # dataset frames each robot reads per tick
    tick_seconds: 0.25   # wall-clock length of a tick on Zenoh runs (ignored in-process)
    windows:
      - {start: 30, end: 40, robots: [0, 1]}
      - {start: 60, end: 80, robots: [0, 1, 2]}
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from swarmsplat.kernels.errors import InputError


@dataclass(frozen=True)
class Window:
    start: int  # first tick, inclusive
    end: int  # last tick, exclusive
    robots: frozenset[int]


@dataclass
class Schedule:
    ticks: int
    frames_per_tick: int = 1
    tick_seconds: float = 0.25
    windows: list[Window] = field(default_factory=list)

    def linked(self, tick: int, a: int, b: int) -> bool:
        """True when robots a and b can exchange messages at `tick` (a robot is always linked with itself). Past
        the last tick (a mission's end protocol, ending.py) the links of the last tick hold."""
        if a == b:
            return True
        tick = min(tick, self.ticks - 1)
        return any(w.start <= tick < w.end and a in w.robots and b in w.robots for w in self.windows)

    def neighbours(self, tick: int, robot: int, robots) -> list[int]:
        return [r for r in robots if r != robot and self.linked(tick, robot, r)]

    def frames_at(self, tick: int) -> int:
        """Number of dataset frames a robot has read once `tick` has started."""
        return (tick + 1) * self.frames_per_tick

    @classmethod
    def always(cls, robots, ticks: int, frames_per_tick: int = 1, tick_seconds: float = 0.25) -> "Schedule":
        """Everyone in range for the whole run."""
        return cls(ticks, frames_per_tick, tick_seconds, [Window(0, ticks, frozenset(robots))])

    @classmethod
    def default(cls, n_robots: int, n_frames: int, frames_per_tick: int = 2, tick_seconds: float = 0.25,
                tail: int = 12) -> "Schedule":
        """Pairs meet while recording (0-1 at one third, 1-2 at two thirds), then all robots meet for `tail`
        ticks after the last frame, so the final estimate includes everything."""
        rec = -(-n_frames // frames_per_tick)
        ticks = rec + tail
        wins = []
        for k in range(n_robots - 1):
            s = rec * (k + 1) // n_robots
            wins.append(Window(s, s + max(2, rec // (2 * n_robots)), frozenset({k, k + 1})))
        wins.append(Window(rec, ticks, frozenset(range(n_robots))))
        return cls(ticks, frames_per_tick, tick_seconds, wins)

    def to_dict(self) -> dict:
        return {"ticks": self.ticks, "frames_per_tick": self.frames_per_tick, "tick_seconds": self.tick_seconds,
                "windows": [{"start": w.start, "end": w.end, "robots": sorted(w.robots)} for w in self.windows]}

    @classmethod
    def from_dict(cls, d: dict, where: str = "schedule") -> "Schedule":
        if not isinstance(d, dict):
            raise InputError(f"{where}: expected a mapping with ticks, frames_per_tick, tick_seconds, windows")
        unknown = set(d) - {"ticks", "frames_per_tick", "tick_seconds", "windows"}
        if unknown:
            raise InputError(f"{where}: unknown field(s) {sorted(unknown)}")
        try:
            ticks, fpt = int(d.get("ticks", 0)), int(d.get("frames_per_tick", 1))
            tick_s = float(d.get("tick_seconds", 0.25))
        except (TypeError, ValueError):
            raise InputError(f"{where}: ticks and frames_per_tick must be integers, tick_seconds a number") from None
        if ticks < 1 or fpt < 1 or not tick_s > 0:
            raise InputError(f"{where}: need ticks >= 1, frames_per_tick >= 1, tick_seconds > 0")
        wins = []
        for n, w in enumerate(d.get("windows") or []):
            try:
                win = Window(int(w["start"]), int(w["end"]), frozenset(int(r) for r in w["robots"]))
            except (KeyError, TypeError, ValueError):
                raise InputError(f"{where}: windows[{n}] needs integer start, end and a list of robot ids") from None
            if not 0 <= win.start < win.end or any(r < 0 or r > 254 for r in win.robots):
                raise InputError(f"{where}: windows[{n}] needs 0 <= start < end and robot ids in 0..254")
            wins.append(win)
        return cls(ticks, fpt, tick_s, wins)

    @classmethod
    def load(cls, path: str | Path) -> "Schedule":
        import yaml

        p = Path(path)
        try:
            d = yaml.safe_load(p.read_text())
        except OSError as e:
            raise InputError(f"{p}: cannot read schedule ({e.strerror})") from None
        except yaml.YAMLError as e:
            raise InputError(f"{p}: not valid YAML ({e})") from None
        return cls.from_dict(d, str(p))
