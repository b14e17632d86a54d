"""How many bytes of arrays a team holds: the keyframes' images, the submaps' Gaussians, the encodings and clouds
the server caches, the messages waiting to be handled.

The team server keeps every agent's map in memory, so its resident memory grows with the map by design. What it
holds is measured here (numpy arrays, torch tensors, bytes, reached from the given roots through swarmsplat's own
objects and the containers they hold); the server's status line reports it, and a soak tells a leak from the map's
growth by the memory beyond it (perf/soak_checks.py). Objects of other packages (Open3D clouds, say) are not
entered: their bytes are not counted.
"""

from __future__ import annotations

from collections import deque

import numpy as np

_CONTAINERS = (list, tuple, set, frozenset, deque)


def _ours(obj) -> bool:
    return type(obj).__module__.startswith("swarmsplat")


def held_bytes(*roots) -> int:
    """The bytes of every distinct numpy array (its whole buffer, counted once however many views share it),
    torch tensor storage and bytes object reachable from `roots`."""
    import sys

    torch = sys.modules.get("torch")  # a process that never imported torch holds no tensors
    seen: set[int] = set()
    buffers: set[tuple] = set()
    total = 0
    stack = list(roots)
    while stack:
        obj = stack.pop()
        if obj is None or isinstance(obj, (int, float, str, bool)) or id(obj) in seen:
            continue
        seen.add(id(obj))
        if isinstance(obj, np.ndarray):
            base = obj
            while isinstance(base.base, np.ndarray):
                base = base.base
            if ("np", id(base)) not in buffers:
                buffers.add(("np", id(base)))
                total += base.nbytes
                if base.dtype == object:
                    stack.extend(base.ravel().tolist())
        elif torch is not None and isinstance(obj, torch.Tensor):
            st = obj.untyped_storage()
            key = ("torch", st.data_ptr())
            if key not in buffers:
                buffers.add(key)
                total += st.nbytes()
        elif isinstance(obj, (bytes, bytearray, memoryview)):
            total += len(obj) if not isinstance(obj, memoryview) else obj.nbytes
        elif isinstance(obj, dict):
            stack.extend(obj.values())
        elif isinstance(obj, _CONTAINERS):
            stack.extend(obj)
        elif _ours(obj):
            d = getattr(obj, "__dict__", None)
            if d is not None:
                stack.extend(d.values())
            for cls in type(obj).__mro__:
                for name in getattr(cls, "__slots__", ()):
                    stack.append(getattr(obj, name, None))
    return total
