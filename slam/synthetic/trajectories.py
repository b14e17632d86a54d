"""Agent camera paths: smooth closed loops through the rooms, placed so that agents overlap.

World frame: z up, metres. Camera frame: OpenCV (x right, y down, z forward). Poses are `T_world_cam`.

Each agent walks a closed loop (an ellipse with a little higher-harmonic wobble) while its view sweeps left and
right around a base heading without turning all the way round, as a person scanning a room does. Walking the
loop a bit more than once (`MotionConfig.loop_turns`) makes the agent revisit its start: an intra-agent loop
closure. The six agent slots are laid out around the world's main (wide) opening between room A and room B
(layout version 2, `GeneratorConfig.trajectory_layout`):

    slot 0: room A, looking into B
    slot 1: room A, between slot 0 and the opening, looking into B: its loop's back end reaches slot 0's front,
            so 0 and 1 see the same surfaces from nearly the same place and direction for a stretch of frames
    slot 2: room A, beside and behind 0, looking into B (same direction as 0 and 1)
    slot 3: room B, looking into A            (opposite direction of slots 0, 1 and 2)
    slot 4: room C (or B), looking at A       slot 5: room A, looking at C    (a second opposite pair)

so every agent of the default 3-agent dataset shares same-direction views with the others (views that
inter-agent place recognition and registration can match), while slot 3 sees the region around the opening
only from the side opposite to slots 0-2 and slots 4 and 5 face each other (negatives: same place, no usable
overlap). Layout version 1 had slot 1 in room B looking into A, so agent 1 of the default dataset saw the
others' region from behind only and never joined the global frame.

Speeds are the largest that respect the per-frame translation and rotation limits of `MotionConfig`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from swarmsplat.kernels import se3

from .config import MAX_AGENTS, MotionConfig

_WALL_MARGIN_M = 0.75  # a loop keeps at least this far from any wall of its room
# Slot 1's loop centre: this far into room A from the main opening, 0.6-1.1 m ahead of slot 0's centre. Measured
# with tests/test_synthetic.py's _same_direction_frames on the default dataset (seeds 0/1/3): agent 1 has a
# same-direction partner in 10/15/17 of 20 sampled frames (layout 1's slot 1, in room B: 0/0/0). Closer to the
# opening the two loops no longer meet and agent 1's views hold only part of agent 0's.
_FRONT_LOOP_BACK_M = 1.3


@dataclass(frozen=True)
class LoopSpec:
    """One agent's closed path, parametrised by an angle theta (radians; one loop = 2 pi)."""

    agent: int
    room: int
    centre: tuple[float, float]  # metres, world x y
    axes: tuple[tuple[float, float], tuple[float, float]]  # unit vectors: along the base heading, lateral
    radii: tuple[float, float]  # metres along axes[0], axes[1]
    wobble: tuple[float, float, float]  # amplitude (m) and phases of the 2nd/3rd harmonics
    direction: int  # +1 or -1: which way round
    theta0: float  # where on the loop the agent starts
    height: tuple[float, float, float]  # mean (m), amplitude (m), phase
    yaw: tuple[float, float, float, float, float]  # base, amp1, phase1, amp2, phase2 (radians)
    pitch: tuple[float, float, float]  # mean, amplitude, phase (radians; negative looks down)
    roll: tuple[float, float]  # amplitude, phase (radians)

    def xy(self, theta: np.ndarray) -> np.ndarray:
        """[N] -> [N, 2] world x y of the loop."""
        theta = np.asarray(theta, dtype=np.float64)
        a, ph2, ph3 = self.wobble
        p = self.radii[0] * np.cos(theta) + a * np.cos(2 * theta + ph2)
        q = self.radii[1] * np.sin(theta) + a * np.sin(3 * theta + ph3)
        u, v = np.asarray(self.axes[0]), np.asarray(self.axes[1])
        return np.asarray(self.centre) + p[:, None] * u + q[:, None] * v

    def poses(self, theta: np.ndarray) -> np.ndarray:
        """[N] loop parameters -> [N, 4, 4] T_world_cam."""
        theta = np.asarray(theta, dtype=np.float64)
        h0, ha, hp = self.height
        z = h0 + ha * np.sin(theta + hp)
        y0, ya1, yp1, ya2, yp2 = self.yaw
        yaw = y0 + ya1 * np.sin(theta + yp1) + ya2 * np.sin(2 * theta + yp2)
        pitch = self.pitch[0] + self.pitch[1] * np.sin(theta + self.pitch[2])
        roll = self.roll[0] * np.sin(2 * theta + self.roll[1])
        t = np.concatenate([self.xy(theta), z[:, None]], axis=1)
        return se3.make(camera_rotation(yaw, pitch, roll), t)


def camera_rotation(yaw: np.ndarray, pitch: np.ndarray, roll: np.ndarray) -> np.ndarray:
    """R_world_cam [N, 3, 3] for an OpenCV camera in a z-up world.

    yaw: heading of the optical axis from world +x towards +y; pitch: elevation (negative looks down);
    roll: about the optical axis. All [N] radians.
    """
    yaw, pitch, roll = (np.atleast_1d(np.asarray(a, dtype=np.float64)) for a in (yaw, pitch, roll))
    fwd = np.stack([np.cos(pitch) * np.cos(yaw), np.cos(pitch) * np.sin(yaw), np.sin(pitch)], axis=-1)
    right0 = np.cross(fwd, [0.0, 0.0, 1.0])
    right0 /= np.linalg.norm(right0, axis=-1, keepdims=True)
    down0 = np.cross(fwd, right0)
    c, s = np.cos(roll)[:, None], np.sin(roll)[:, None]
    right, down = c * right0 + s * down0, -s * right0 + c * down0
    return np.stack([right, down, fwd], axis=-1)


def plan_loops(rooms, main_opening, rng: np.random.Generator, n: int = MAX_AGENTS) -> list[LoopSpec]:
    """The loops of agent slots 0..n-1 in a world (see the module docstring for the layout).

    rooms: the world's rooms (objects with `lo`, `hi` [2] metres, `index`, `ix`, `iy`); main_opening: the wide
    opening between room A and room B (an object with `rooms` (A, B) indices, `axis`, `coord`, `centre`,
    `width`, as world.Opening). The loops do not depend on frame count or agent count, so agent k's path is the
    same in a 2-agent and a 6-agent dataset of the same world.
    """
    ra, rb = rooms[main_opening.rooms[0]], rooms[main_opening.rooms[1]]
    u = _unit(_centre(rb) - _centre(ra))
    v = np.array([-u[1], u[0]])
    # Room C: A's neighbour across the other axis, if there is one (the world is a grid of rooms).
    rc = next((r for r in rooms if r.index not in main_opening.rooms and _adjacent(ra, r)
               and abs(np.dot(_unit(_centre(r) - _centre(ra)), v)) > 0.9), None)
    if rc is not None:
        v = _unit(_centre(rc) - _centre(ra))
    loops = []
    for agent in range(min(n, MAX_AGENTS)):
        if agent == 1:
            loops.append(_front_loop(agent, ra, main_opening, u, v, rng))
            continue
        room, fu, fv, heading = {
            0: (ra, 0.0, 0.08, u), 2: (ra, -0.08, -0.13, u), 3: (rb, 0.1, 0.2, -u),
            4: (rc, 0.0, 0.2, -v) if rc is not None else (rb, 0.0, -0.15, v), 5: (ra, 0.0, -0.2, v)}[agent]
        size = np.asarray(room.hi) - np.asarray(room.lo)
        half_u, half_v = abs(np.dot(size, np.abs(u))) / 2, abs(np.dot(size, np.abs(v))) / 2
        shift_u, shift_v = fu * 2 * half_u, fv * 2 * half_v
        # Loop axes: first along the base heading. Radii bounded so the loop keeps clear of the walls.
        along_u = abs(np.dot(heading, u)) > 0.5
        a_half, a_shift = (half_u, shift_u) if along_u else (half_v, shift_v)
        l_half, l_shift = (half_v, shift_v) if along_u else (half_u, shift_u)
        loops.append(_loop(agent, room, _centre(room) + shift_u * u + shift_v * v, heading,
                           along=((0.3, 0.45), a_half - abs(a_shift) - _WALL_MARGIN_M),
                           lateral=((0.4, 0.65), l_half - abs(l_shift) - _WALL_MARGIN_M), rng=rng))
    return loops


def _front_loop(agent, ra, opening, u, v, rng) -> LoopSpec:
    """Slot 1: a loop in room A between slot 0 and the main opening, on the opening's centre line, looking into
    room B like slot 0.

    Its back end reaches slot 0's front, so for a stretch of frames the two see the opening and room B beyond it
    from nearly the same place and direction (what inter-agent place recognition and registration need); its
    front end, under a metre from the opening, sees room B closer up than slot 0 does.
    """
    door = np.array([opening.coord, opening.centre] if opening.axis == 0 else [opening.centre, opening.coord])
    centre = door - _FRONT_LOOP_BACK_M * u
    half_v = abs(np.dot(np.asarray(ra.hi) - np.asarray(ra.lo), np.abs(v))) / 2
    off_v = abs(np.dot(centre - _centre(ra), v))
    return _loop(agent, ra, centre, u, along=((0.5, 0.6), _FRONT_LOOP_BACK_M - _WALL_MARGIN_M),
                 lateral=((0.35, 0.45), half_v - off_v - _WALL_MARGIN_M), rng=rng)


def _loop(agent, room, centre, heading, *, along, lateral, rng) -> LoopSpec:
    """A loop around `centre` whose first axis is the base heading. along / lateral: ((lo, hi) range the radius
    is drawn from, the largest radius + wobble allowed there), metres."""
    wob = rng.uniform(0.0, 0.06)
    r_along = min(rng.uniform(*along[0]), along[1] - wob)
    r_lat = min(rng.uniform(*lateral[0]), lateral[1] - wob)
    lateral_axis = np.array([-heading[1], heading[0]])
    deg = np.deg2rad
    return LoopSpec(
        agent=agent, room=room.index, centre=tuple(float(c) for c in centre),
        axes=(tuple(float(c) for c in heading), tuple(float(c) for c in lateral_axis)),
        radii=(float(max(r_along, 0.15)), float(max(r_lat, 0.15))),
        wobble=(float(wob), float(rng.uniform(0, 2 * np.pi)), float(rng.uniform(0, 2 * np.pi))),
        direction=int(rng.choice([-1, 1])), theta0=float(rng.uniform(0, 2 * np.pi)),
        height=(float(rng.uniform(1.25, 1.55)), float(rng.uniform(0.03, 0.08)), float(rng.uniform(0, 2 * np.pi))),
        yaw=(float(np.arctan2(heading[1], heading[0]) + deg(rng.uniform(-10, 10))), float(deg(rng.uniform(18, 30))),
             float(rng.uniform(0, 2 * np.pi)), float(deg(rng.uniform(0, 5))), float(rng.uniform(0, 2 * np.pi))),
        pitch=(float(deg(rng.uniform(-16, -8))), float(deg(rng.uniform(2, 5))), float(rng.uniform(0, 2 * np.pi))),
        roll=(float(deg(rng.uniform(0.5, 2.0))), float(rng.uniform(0, 2 * np.pi))),
    )


def agent_trajectory(loop: LoopSpec, frames: int, motion: MotionConfig) -> np.ndarray:
    """[frames, 4, 4] T_world_cam: `motion.loop_turns` turns of the loop, or less where the limits demand it.

    The loop parameter advances by a constant step, the largest that keeps every frame-to-frame translation
    below `motion.max_step_m` and rotation below `motion.max_rot_deg`.
    """
    dtheta = step_per_frame(loop, frames, motion)
    theta = loop.theta0 + loop.direction * dtheta * np.arange(frames)
    return loop.poses(theta)


def step_per_frame(loop: LoopSpec, frames: int, motion: MotionConfig) -> float:
    """Loop-parameter increment per frame (radians) honouring the motion limits."""
    th = np.linspace(0.0, 2 * np.pi, 2049)
    T = loop.poses(th)
    d = np.diff(th)[0]
    speed = np.linalg.norm(np.diff(T[:, :3, 3], axis=0), axis=1).max() / d  # metres per radian
    rel = np.swapaxes(T[:-1, :3, :3], 1, 2) @ T[1:, :3, :3]
    spin = se3.rotation_angle(rel).max() / d  # radians of camera rotation per radian of loop
    limit = min(motion.max_step_m / speed, np.deg2rad(motion.max_rot_deg) / max(spin, 1e-9))
    wanted = 2 * np.pi * motion.loop_turns / max(frames - 1, 1)
    return float(min(wanted, limit))


def _centre(room) -> np.ndarray:
    return (np.asarray(room.lo, dtype=np.float64) + np.asarray(room.hi, dtype=np.float64)) / 2


def _unit(x: np.ndarray) -> np.ndarray:
    return x / np.linalg.norm(x)


def _adjacent(r1, r2) -> bool:
    return abs(r1.ix - r2.ix) + abs(r1.iy - r2.iy) == 1
