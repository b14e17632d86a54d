"""A procedural indoor world: a grid of rooms joined by openings, with furniture, as one triangle mesh.

World frame: z up, floor at z = 0, metres. Every solid is an axis-aligned box (walls, floors, ceilings,
cabinets, tables, crates, columns), which keeps surface texturing exact (see texture.py) and meshing trivial.
Rooms differ in size, furniture and materials; the opening between room A (grid cell 0, 0) and its first
neighbour B is wide (1.8-2.4 m) so the agents placed around it (trajectories.py) see across it.

A twin world (`WorldConfig.twin`) is that building plus a second copy of it standing `TWIN_GAP_M` beyond its
+x wall. Copy 1 is exactly the world of the same seed without a twin; in copy 2 room A (or, with "building", every
room) has the same geometry, furniture and textures: its faces look up the texture at the copy-1 point they
repeat, so the two copies are indistinguishable from inside. Closed outer walls keep every camera from seeing
the other copy. Agent k walks slot k // 2's path in copy k % 2: agents 0 and 1 take the same path through the
two copies, agents 0 and 3 stand to each other as slots 0 and 1 of one building (a pair that shares views), but
in different copies.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from functools import cached_property

import numpy as np

from .config import MAX_AGENTS, WorldConfig
from .texture import (PATTERNS, MaterialTable, TextureField, lambert, material_table, random_material,
                      surface_offset)
from .trajectories import LoopSpec, plan_loops

WALL_T = 0.12  # wall thickness, metres
TWIN_GAP_M = 3.0  # between the two copies of a twin world, outer wall to outer wall
_FURNITURE_CLEARANCE = 0.55  # metres between any furniture and any agent path


@dataclass(frozen=True)
class Room:
    index: int
    ix: int
    iy: int
    lo: tuple[float, float]  # x, y of the wall centre lines, metres
    hi: tuple[float, float]
    copy: int = 0  # 1: the second copy of a twin world


@dataclass(frozen=True)
class Opening:
    rooms: tuple[int, int]
    axis: int  # 0: the wall is a line of constant x; 1: constant y
    coord: float  # that constant, metres
    centre: float  # position along the wall, metres
    width: float
    top: float  # height of the lintel, metres


@dataclass(frozen=True)
class Box:
    lo: tuple[float, float, float]
    hi: tuple[float, float, float]
    kind: str  # wall | floor | ceiling | furniture
    material: int = -1  # furniture's own material; -1: from the room the face looks into


@dataclass
class World:
    """Geometry (mesh and boxes), materials and the agents' loops of one generated world."""

    seed: int
    config: WorldConfig
    height: float
    rooms: list[Room]
    openings: list[Opening]
    boxes: list[Box]
    loops: list[LoopSpec]  # one per agent slot (MAX_AGENTS)
    materials: MaterialTable
    vertices: np.ndarray = field(repr=False)  # [V, 3] float32
    triangles: np.ndarray = field(repr=False)  # [T, 3] int32
    tri_material: np.ndarray = field(repr=False)  # [T] int64 material id per triangle
    tri_normal: np.ndarray = field(repr=False)  # [T, 3] float32 outward unit normal per triangle
    tri_axis: np.ndarray = field(repr=False)  # [T] int64 world axis of that normal (0 x, 1 y, 2 z)
    # [T, 3] float metres: a triangle's texture is that of the point this far back (twin copies; None: zero).
    tri_texture_shift: np.ndarray | None = field(default=None, repr=False)

    # Per-triangle shading constants, derived from the above in __post_init__.
    tri_surface_axes: np.ndarray = field(init=False, repr=False)  # [T, 2] int64 world axes spanning the face
    tri_surface_offset: np.ndarray = field(init=False, repr=False)  # [T, 2] float32 texture coordinate offset
    tri_light: np.ndarray = field(init=False, repr=False)  # [T] float32 Lambertian brightness

    def __post_init__(self):
        # Walls: (horizontal axis, z); floors and ceilings: (x, y).
        self.tri_surface_axes = np.stack([np.where(self.tri_axis == 0, 1, 0), np.where(self.tri_axis == 2, 1, 2)], 1)
        self.tri_surface_offset = surface_offset(self.materials, self.tri_material, self.tri_axis)
        if self.tri_texture_shift is not None:  # a copy's face reads the texture where its original stands
            rows = np.arange(len(self.tri_axis))[:, None]
            self.tri_surface_offset -= self.tri_texture_shift[rows, self.tri_surface_axes].astype(np.float32)
        self.tri_light = lambert(self.tri_normal)

    @cached_property
    def texture(self) -> TextureField:
        return TextureField(self.seed, self.materials)

    @cached_property
    def scene(self):
        """Open3D RaycastingScene of the mesh (built on first use)."""
        import open3d as o3d

        scene = o3d.t.geometry.RaycastingScene()
        scene.add_triangles(o3d.core.Tensor(self.vertices), o3d.core.Tensor(self.triangles.astype(np.uint32)))
        return scene

    def room_at(self, xy: np.ndarray) -> np.ndarray:
        """[N, 2] world x y -> [N] room index, -1 outside every room."""
        xy = np.atleast_2d(xy)
        out = np.full(len(xy), -1)
        for r in self.rooms:
            inside = np.all((xy >= r.lo) & (xy < r.hi), axis=1)
            out[inside] = r.index
        return out

    def to_mesh(self):
        """The world as a legacy open3d.geometry.TriangleMesh (for viewing or export)."""
        import open3d as o3d

        m = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(self.vertices.astype(np.float64)),
                                      o3d.utility.Vector3iVector(self.triangles))
        m.compute_triangle_normals()
        return m


def generate_world(seed: int, config: WorldConfig | None = None) -> World:
    """Build the world for `seed` (deterministic: same seed and config, same world)."""
    config = config or WorldConfig()
    rng = np.random.default_rng([seed, 1])
    nx, ny = config.rooms_x, config.rooms_y
    widths = rng.uniform(*config.room_size_m, size=nx)
    depths = rng.uniform(*config.room_size_m, size=ny)
    xs = np.concatenate([[0.0], np.cumsum(widths)])
    ys = np.concatenate([[0.0], np.cumsum(depths)])
    height = float(rng.uniform(*config.height_m))
    rooms = [Room(iy * nx + ix, ix, iy, (xs[ix], ys[iy]), (xs[ix + 1], ys[iy + 1]))
             for iy in range(ny) for ix in range(nx)]

    openings, boxes = _walls(rooms, nx, ny, xs, ys, height, rng)
    for r in rooms:
        boxes.append(Box((r.lo[0], r.lo[1], -0.1), (r.hi[0], r.hi[1], 0.0), "floor"))
        boxes.append(Box((r.lo[0], r.lo[1], height), (r.hi[0], r.hi[1], height + 0.1), "ceiling"))

    loops = plan_loops(rooms, openings[0], np.random.default_rng([seed, 2]), MAX_AGENTS)

    # Materials: per room a wall, floor and ceiling material with patterns drawn without repeats across
    # neighbouring rooms; then one per furniture piece.
    mats: list[dict] = []
    room_mats = []
    wall_kinds = ["stripes", "blotches", "noise", "tiles"]
    floor_kinds = ["planks", "tiles", "noise", "blotches"]
    for r in rooms:
        wk = wall_kinds[(r.index + int(rng.integers(0, 2)) * 2) % len(wall_kinds)]
        fk = floor_kinds[(r.index + int(rng.integers(0, 2)) * 2) % len(floor_kinds)]
        base = len(mats)
        mats += [random_material(rng, wk), random_material(rng, fk), random_material(rng, "noise")]
        room_mats.append((base, base + 1, base + 2))
    outside = len(mats)
    mats.append(random_material(rng, "noise"))

    path_xy = np.concatenate([lp.xy(np.linspace(0, 2 * np.pi, 180, endpoint=False)) for lp in loops])
    furn_rng = np.random.default_rng([seed, 3])
    furniture = [_furnish(r, openings, path_xy, height, config, furn_rng, mats) for r in rooms]
    boxes += [b for fb in furniture for b in fb]
    shift = np.zeros((len(boxes), 3))
    if config.twin != "none":
        rooms, openings, boxes, loops, room_mats, shift = _twin(
            seed, config, height, rooms, openings, boxes, furniture, loops, room_mats, mats, path_xy, xs[-1])

    vertices, triangles, tri_box, tri_face = _mesh(boxes)
    tri_material = _face_materials(boxes, rooms, room_mats, outside, vertices, triangles, tri_box, tri_face)
    return World(seed=seed, config=config, height=height, rooms=rooms, openings=openings, boxes=boxes,
                 loops=loops, materials=material_table(mats), vertices=vertices, triangles=triangles,
                 tri_material=tri_material, tri_normal=_FACE_NORMALS[tri_face].astype(np.float32), tri_axis=tri_face // 2,
                 tri_texture_shift=shift[tri_box] if shift.any() else None)


def _twin(seed, config, height, rooms, openings, boxes, furniture, loops, room_mats, mats, path_xy, width):
    """The second copy of a twin world, `TWIN_GAP_M` beyond copy 1's +x wall (see the module docstring).

    Returns rooms, openings and boxes of both copies, the agents' loops (agent k: slot k // 2 in copy k % 2),
    the rooms' materials and each box's texture shift [B, 3] (copy 2's boxes: the translation, so they look like
    the copy-1 box they repeat). Appends copy 2's new materials to `mats`.
    """
    d = width + WALL_T + TWIN_GAP_M
    n = len(rooms)
    move = lambda b: Box((b.lo[0] + d, *b.lo[1:]), (b.hi[0] + d, *b.hi[1:]), b.kind, b.material)  # noqa: E731
    rooms2 = [Room(r.index + n, r.ix, r.iy, (r.lo[0] + d, r.lo[1]), (r.hi[0] + d, r.hi[1]), copy=1) for r in rooms]
    openings2 = [Opening((op.rooms[0] + n, op.rooms[1] + n), op.axis, op.coord + d * (op.axis == 0),
                         op.centre + d * (op.axis == 1), op.width, op.top) for op in openings]
    n_furniture = sum(len(fb) for fb in furniture)
    boxes2 = [move(b) for b in boxes[: len(boxes) - n_furniture]]  # walls, floors, ceilings
    room_mats2 = list(room_mats)
    same = {r.index for r in rooms} if config.twin == "building" else {openings[0].rooms[0]}  # room A
    rng = np.random.default_rng([seed, 4])
    wall_kinds = ["stripes", "blotches", "noise", "tiles"]
    floor_kinds = ["planks", "tiles", "noise", "blotches"]
    for r, fb in zip(rooms, furniture):
        if r.index in same:
            boxes2 += [move(b) for b in fb]
            continue
        base = len(mats)  # another paint and other furniture, in the shape of the same room
        mats += [random_material(rng, wall_kinds[int(rng.integers(0, 4))]),
                 random_material(rng, floor_kinds[int(rng.integers(0, 4))]), random_material(rng, "noise")]
        room_mats2[r.index] = (base, base + 1, base + 2)
        boxes2 += [move(b) for b in _furnish(r, openings, path_xy, height, config, rng, mats)]
    shift = np.zeros((len(boxes) + len(boxes2), 3))
    shift[len(boxes):, 0] = d
    twins = [replace(loops[k // 2], agent=k, room=loops[k // 2].room + n * (k % 2),
                     centre=(loops[k // 2].centre[0] + d * (k % 2), loops[k // 2].centre[1]))
             for k in range(MAX_AGENTS)]
    return rooms + rooms2, openings + openings2, boxes + boxes2, twins, room_mats + room_mats2, shift


def _walls(rooms, nx, ny, xs, ys, height, rng) -> tuple[list[Opening], list[Box]]:
    """Wall boxes along every grid line, with one opening between each pair of neighbouring rooms."""
    openings: list[Opening] = []
    boxes: list[Box] = []
    h = WALL_T / 2
    # Lines of constant x (axis 0), then constant y (axis 1). The first interior line's first segment holds
    # the wide main opening between room (0, 0) and its neighbour.
    for axis, lines, spans, n_along in ((0, xs, ys, ny), (1, ys, xs, nx)):
        for i, c in enumerate(lines):
            for j in range(n_along):
                a, b = spans[j] - h, spans[j + 1] + h
                interior = 0 < i < len(lines) - 1
                if not interior:
                    boxes.append(_wall_box(axis, c, a, b, 0.0, height))
                    continue
                wide = not openings
                width = rng.uniform(1.8, 2.4) if wide else rng.uniform(0.9, 1.3)
                lo_c, hi_c = spans[j] + 0.5 + width / 2, spans[j + 1] - 0.5 - width / 2
                centre = rng.uniform(lo_c, hi_c) if hi_c > lo_c else (spans[j] + spans[j + 1]) / 2
                if wide:  # keep the main opening near the middle of its wall
                    centre = (spans[j] + spans[j + 1]) / 2 + rng.uniform(-0.3, 0.3)
                top = min(rng.uniform(2.05, 2.35), height - 0.2)
                ra, rb = _rooms_across(axis, i, j, nx)
                openings.append(Opening((ra, rb), axis, float(c), float(centre), float(width), float(top)))
                boxes.append(_wall_box(axis, c, a, centre - width / 2, 0.0, height))
                boxes.append(_wall_box(axis, c, centre + width / 2, b, 0.0, height))
                boxes.append(_wall_box(axis, c, centre - width / 2, centre + width / 2, top, height))
    return openings, boxes


def _rooms_across(axis: int, line: int, j: int, nx: int) -> tuple[int, int]:
    if axis == 0:  # x line `line` between columns line-1 and line, row j
        return j * nx + line - 1, j * nx + line
    return (line - 1) * nx + j, line * nx + j


def _wall_box(axis: int, c: float, a: float, b: float, z0: float, z1: float) -> Box:
    h = WALL_T / 2
    if axis == 0:
        return Box((c - h, a, z0), (c + h, b, z1), "wall")
    return Box((a, c - h, z0), (b, c + h, z1), "wall")


def _furnish(room: Room, openings, path_xy, height, config: WorldConfig, rng, mats: list[dict]) -> list[Box]:
    """Random furniture in one room that keeps clear of agent paths, doorways and other furniture."""
    lo = np.asarray(room.lo) + WALL_T / 2
    hi = np.asarray(room.hi) - WALL_T / 2
    keep_out = []  # [x0, y0, x1, y1] rectangles: doorways (both sides)
    for op in openings:
        if room.index in op.rooms:
            d = 0.9
            if op.axis == 0:
                keep_out.append([op.coord - d, op.centre - op.width / 2 - 0.1, op.coord + d, op.centre + op.width / 2 + 0.1])
            else:
                keep_out.append([op.centre - op.width / 2 - 0.1, op.coord - d, op.centre + op.width / 2 + 0.1, op.coord + d])
    placed: list[list[float]] = []
    boxes: list[Box] = []
    want = int(rng.integers(config.furniture_per_room[0], config.furniture_per_room[1] + 1))
    kinds = ["cabinet", "table", "crate", "column", "cabinet", "crate"]
    for _ in range(want * 25):
        if len(placed) >= want:
            break
        kind = kinds[int(rng.integers(0, len(kinds)))]
        if kind == "column" and any(b.hi[2] >= height for b in boxes if b.kind == "furniture"):
            continue  # at most one column per room
        w, d, h = {"cabinet": (rng.uniform(0.5, 1.6), rng.uniform(0.35, 0.6), rng.uniform(0.8, 2.0)),
                   "table": (rng.uniform(0.8, 1.6), rng.uniform(0.6, 0.9), rng.uniform(0.7, 0.78)),
                   "crate": (rng.uniform(0.3, 0.6), rng.uniform(0.3, 0.6), rng.uniform(0.3, 0.6)),
                   "column": (rng.uniform(0.25, 0.4),) * 2 + (height,)}[kind]
        if rng.random() < 0.5:
            w, d = d, w
        if kind == "cabinet":  # against a random wall
            side = int(rng.integers(0, 4))
            if side < 2:
                x0 = lo[0] if side == 0 else hi[0] - min(w, d)
                w, d = min(w, d), max(w, d)
                y0 = rng.uniform(lo[1], hi[1] - d)
            else:
                y0 = lo[1] if side == 2 else hi[1] - min(w, d)
                w, d = max(w, d), min(w, d)
                x0 = rng.uniform(lo[0], hi[0] - w)
        else:
            x0, y0 = rng.uniform(lo[0], hi[0] - w), rng.uniform(lo[1], hi[1] - d)
        rect = [x0, y0, x0 + w, y0 + d]
        if not _fits(rect, placed, keep_out, path_xy):
            continue
        placed.append(rect)
        mats.append(random_material(rng, PATTERNS[int(rng.integers(0, len(PATTERNS)))]))
        m = len(mats) - 1
        if kind == "table":
            top_t, leg = 0.04, 0.05
            boxes.append(Box((x0, y0, h - top_t), (x0 + w, y0 + d, h), "furniture", m))
            for lx, ly in ((x0, y0), (x0 + w - leg, y0), (x0, y0 + d - leg), (x0 + w - leg, y0 + d - leg)):
                boxes.append(Box((lx, ly, 0.0), (lx + leg, ly + leg, h - top_t), "furniture", m))
        else:
            boxes.append(Box((x0, y0, 0.0), (x0 + w, y0 + d, h), "furniture", m))
            if kind == "crate" and rng.random() < 0.4:  # a smaller crate stacked on top
                s = rng.uniform(0.5, 0.9)
                boxes.append(Box((x0 + 0.05, y0 + 0.05, h), (x0 + 0.05 + w * s, y0 + 0.05 + d * s, h + h * s),
                                 "furniture", m))
    return boxes


def _fits(rect, placed, keep_out, path_xy) -> bool:
    def overlap(a, b, gap):
        return a[0] < b[2] + gap and b[0] < a[2] + gap and a[1] < b[3] + gap and b[1] < a[3] + gap

    if any(overlap(rect, p, 0.1) for p in placed) or any(overlap(rect, k, 0.0) for k in keep_out):
        return False
    c = _FURNITURE_CLEARANCE
    near = ((path_xy[:, 0] > rect[0] - c) & (path_xy[:, 0] < rect[2] + c)
            & (path_xy[:, 1] > rect[1] - c) & (path_xy[:, 1] < rect[3] + c))
    return not near.any()


# Unit-box corners (bit 0: x, bit 1: y, bit 2: z) and the two triangles of each face, counter-clockwise seen
# from outside; face order -x, +x, -y, +y, -z, +z.
_CORNERS = np.array([[(i >> 0) & 1, (i >> 1) & 1, (i >> 2) & 1] for i in range(8)], dtype=np.float64)
_FACES = np.array([[0, 4, 6], [0, 6, 2], [1, 3, 7], [1, 7, 5], [0, 1, 5], [0, 5, 4],
                   [2, 6, 7], [2, 7, 3], [0, 2, 3], [0, 3, 1], [4, 5, 7], [4, 7, 6]], dtype=np.int32)
_FACE_NORMALS = np.array([[-1, 0, 0], [1, 0, 0], [0, -1, 0], [0, 1, 0], [0, 0, -1], [0, 0, 1]], dtype=np.float64)


def _mesh(boxes: list[Box]):
    lo = np.array([b.lo for b in boxes])
    hi = np.array([b.hi for b in boxes])
    verts = lo[:, None, :] + _CORNERS[None] * (hi - lo)[:, None, :]  # [B, 8, 3]
    tris = _FACES[None] + 8 * np.arange(len(boxes), dtype=np.int32)[:, None, None]  # [B, 12, 3]
    tri_box = np.repeat(np.arange(len(boxes)), 12)
    tri_face = np.tile(np.repeat(np.arange(6), 2), len(boxes))
    return verts.reshape(-1, 3).astype(np.float32), tris.reshape(-1, 3).astype(np.int32), tri_box, tri_face


def _face_materials(boxes, rooms, room_mats, outside, vertices, triangles, tri_box, tri_face) -> np.ndarray:
    """Furniture keeps its own material; a wall, floor or ceiling face takes that of the room it looks into."""
    centre = vertices[triangles].astype(np.float64).mean(axis=1)
    probe = centre + 0.05 * _FACE_NORMALS[tri_face]
    room = np.full(len(triangles), -1)
    for r in rooms:
        inside = np.all((probe[:, :2] >= r.lo) & (probe[:, :2] < r.hi), axis=1)
        room[inside] = r.index
    kind_slot = {"wall": 0, "floor": 1, "ceiling": 2}
    out = np.empty(len(triangles), dtype=np.int64)
    for t, (b, rm) in enumerate(zip(tri_box, room)):
        box = boxes[b]
        if box.kind == "furniture":
            out[t] = box.material
        else:
            out[t] = room_mats[rm][kind_slot[box.kind]] if rm >= 0 else outside
    return out
