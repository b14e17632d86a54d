"""Timing and reporting helpers shared by every benchmark subject.

A subject module `perf/<name>.py` defines
    DESCRIPTION: str
    def run(*, backends: list[str], device: str, quick: bool) -> dict   # backends ⊆ ["warp", "taichi"]
returning {"rows": [dict, ...], "columns": [str, ...], "notes": [str, ...]} — each row one measurement, the
peer's numbers in the same row or its own row, ratios computed from medians in the same process.
"""

from __future__ import annotations

import contextlib
import os
import platform
import statistics
import subprocess
import tempfile
import time
from typing import Callable


def sync(device: str) -> None:
    """Wait for queued GPU work so a timer measures it."""
    if device == "cuda":
        import torch

        torch.cuda.synchronize()


def time_fn(fn: Callable[[], object], *, repeat: int = 5, warmup: int = 1, device: str = "cpu",
            max_seconds: float | None = None) -> dict:
    """Run `fn` `warmup` times untimed, then up to `repeat` times timed; report the median and spread in seconds.

    `max_seconds` stops repeating early (after at least one timed run) so slow peers do not stall a run.
    """
    for _ in range(warmup):
        fn()
        sync(device)
    times = []
    start = time.perf_counter()
    for _ in range(max(1, repeat)):
        t0 = time.perf_counter()
        fn()
        sync(device)
        times.append(time.perf_counter() - t0)
        if max_seconds is not None and time.perf_counter() - start > max_seconds:
            break
    return {"median_s": statistics.median(times), "min_s": min(times), "max_s": max(times), "runs": len(times)}


def _git(*args: str) -> str | None:
    # realpath: a checkout imported through a namespace folder of links (tree_env) still names its own commit
    here = os.path.dirname(os.path.dirname(os.path.realpath(__file__)))
    try:
        r = subprocess.run(["git", "-C", here, *args], capture_output=True, text=True, check=False, timeout=10)
    except (OSError, subprocess.SubprocessError):
        return None
    return r.stdout.strip() if r.returncode == 0 else None


def cpu_model() -> str:
    """The CPU's model name (/proc/cpuinfo on Linux; platform.processor() elsewhere)."""
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.lower().startswith(("model name", "hardware", "cpu model")):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def _version(module: str) -> str | None:
    from importlib import metadata

    try:
        return metadata.version(module)
    except metadata.PackageNotFoundError:
        return None


def machine_info() -> dict:
    """Where and from what a result came: commit (and whether the tree had uncommitted changes), date, CPU model,
    cores, load average, GPU, and the versions of Python and the libraries that set the speed. Every result file
    of perf/ carries it, so a file's name never has to."""
    info = {"commit": _git("rev-parse", "--short=12", "HEAD"),
            "dirty": None if _git("rev-parse", "HEAD") is None else
            bool(_git("status", "--porcelain", "--untracked-files=no")),
            "date": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
            "cpu_model": cpu_model(), "cpu_count": os.cpu_count(),
            "load_average_1min": round(os.getloadavg()[0], 2) if hasattr(os, "getloadavg") else None,
            "platform": platform.platform(), "python": platform.python_version(),
            "processor": platform.processor() or platform.machine()}
    for dist, key in (("torch", "torch"), ("warp-lang", "warp"), ("taichi", "taichi"), ("gtsam", "gtsam"),
                      ("numpy", "numpy"), ("open3d", "open3d")):
        info[key] = _version(dist)
    try:
        import torch

        info["torch"] = torch.__version__
        info["torch_threads"] = torch.get_num_threads()
        if torch.cuda.is_available():
            info["gpu"] = torch.cuda.get_device_name(0)
    except Exception:  # noqa: BLE001
        pass
    return info


def provenance_line(info: dict) -> str:
    """One Markdown line for a result file's head: commit, date, CPU, load and library versions."""
    # a dirty tree says so here, in the first line, so the file cannot pass for a measurement of the commit
    dirty = " (uncommitted changes)" if info.get("dirty") else ""
    libs = ", ".join(f"{k} {info[k]}" for k in ("torch", "warp", "taichi", "gtsam") if info.get(k))
    return (f"_Measured at commit {info.get('commit')}{dirty} on {info.get('date')}: {info.get('cpu_model')}, "
            f"{info.get('cpu_count')} cores, load {info.get('load_average_1min')}; {libs}._")


def read_provenance(path: str | os.PathLike) -> dict:
    """What a result file says of where it came from: {"commit": short hex or None, "clean": bool, "line": the
    Markdown file's first line or the JSON's machine record as text}. Clean means a commit is named and the tree
    measured had no uncommitted changes: a Markdown file's first line is `_Measured at commit HEX on ...` without
    "(uncommitted changes)"; a JSON file's `machine` has a hex `commit` and `dirty` false. A file from before
    provenance was recorded (`provenance` instead) names no measured commit and is not clean."""
    import json
    import re

    path = os.fspath(path)
    if path.endswith(".json"):
        with open(path) as f:
            m = json.load(f).get("machine") or {}
        commit = m.get("commit")
        ok = isinstance(commit, str) and re.fullmatch(r"[0-9a-f]{7,40}", commit) is not None
        return {"commit": commit if ok else None, "clean": ok and m.get("dirty") is False, "line": str(m)}
    with open(path) as f:
        line = f.readline().strip()
    hit = re.match(r"_Measured at commit ([0-9a-f]{7,40})\b", line)
    return {"commit": hit.group(1) if hit else None,
            "clean": hit is not None and "(uncommitted changes)" not in line, "line": line}


def write_results(json_out: str | None, md_out: str | None, report: dict, md: str | None = None) -> None:
    """Write a result (JSON, with `machine` = machine_info() unless it has one) and its Markdown (headed by the
    provenance line), each atomically."""
    import json

    from swarmsplat.kernels.fileio import atomic_write_text

    report = dict(report)
    report.setdefault("machine", machine_info())
    if json_out:
        atomic_write_text(json_out, json.dumps(report, indent=1, default=float))
    if md_out and md is not None:
        atomic_write_text(md_out, provenance_line(report["machine"]) + "\n\n" + md.rstrip("\n") + "\n")


def print_and_save(res: dict, json_out: str | None) -> None:
    """Print res["rows"] as a Markdown table; with json_out, write res plus the machine's description there."""
    print(markdown_table(res["rows"], list(res["rows"][0])))
    if json_out:
        write_results(json_out, None, res)


def fmt(v) -> str:
    if isinstance(v, float):
        if v == 0:
            return "0"
        if abs(v) >= 1000 or abs(v) < 0.01:
            return f"{v:.3g}"
        return f"{v:.3f}".rstrip("0").rstrip(".")
    return str(v)


def markdown_table(rows: list[dict], columns: list[str]) -> str:
    lines = ["| " + " | ".join(columns) + " |", "|" + "|".join("---" for _ in columns) + "|"]
    for r in rows:
        lines.append("| " + " | ".join(fmt(r.get(c, "")) for c in columns) + " |")
    return "\n".join(lines)


SCALAR_PEER = "warp-scalar"  # Warp with its scalar compositing kernels on the CPU (the CUDA ones): the same-run peer
TAICHI_SCALAR_PEER = "taichi-scalar"  # Taichi with its one-pixel-at-a-time compositing (its GPU kernels) on the CPU


def with_scalar_peer(backends: list[str], device: str) -> list[str]:
    """The backends to time: on the CPU, Warp is followed by SCALAR_PEER, so the vector kernels' gain is a ratio
    measured in the same run."""
    if device == "cpu" and "warp" in backends and SCALAR_PEER not in backends:
        i = backends.index("warp")
        return backends[:i + 1] + [SCALAR_PEER] + backends[i + 1:]
    return list(backends)


def use_backend(name: str, device: str) -> str:
    """kernels.use for a perf backend name; SCALAR_PEER is Warp with its scalar CPU kernels (the CUDA ones):
    kernels._warp.raster.CPU_COMPOSITE = kernels._warp.project.CPU_PROJECT = kernels._warp.activate.CPU_ACTIVATE =
    kernels._warp.loss.CPU_LOSS = "scalar", kernels._warp.sort.CPU_SORT = "warp"; TAICHI_SCALAR_PEER is Taichi
    with kernels._taichi.raster.CPU_COMPOSITE = "scalar". Returns the kernels backend name."""
    from swarmsplat import kernels
    from swarmsplat.kernels._warp import activate as warp_activate
    from swarmsplat.kernels._warp import loss as warp_loss
    from swarmsplat.kernels._warp import project as warp_project
    from swarmsplat.kernels._warp import raster as warp_raster
    from swarmsplat.kernels._warp import sort as warp_sort

    base = {SCALAR_PEER: "warp", TAICHI_SCALAR_PEER: "taichi"}.get(name, name)
    kernels.use(base, device)
    peer = name == SCALAR_PEER
    warp_raster.CPU_COMPOSITE = warp_project.CPU_PROJECT = warp_activate.CPU_ACTIVATE = "scalar" if peer else "vector"
    warp_sort.CPU_SORT = "warp" if peer else "native"
    warp_loss.CPU_LOSS = "scalar" if peer else "native"
    if base == "taichi":  # imported only here: a Warp-only install (e.g. a Jetson without Taichi) has no taichi
        from swarmsplat.kernels._taichi import raster as taichi_raster

        taichi_raster.CPU_COMPOSITE = "scalar" if name == TAICHI_SCALAR_PEER else "vector"
    return base


@contextlib.contextmanager
def checkout(against: str, tool: str):
    """(this repository's root, a temporary git worktree of commit `against`), removed on exit; `tool` names the
    caller in the error a missing commit gets."""
    here = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    with tempfile.TemporaryDirectory(prefix="swarmsplat-ab-") as tmp:
        old = os.path.join(tmp, "tree")
        r = subprocess.run(["git", "-C", here, "worktree", "add", "--detach", old, against], capture_output=True,
                           text=True, check=False)
        if r.returncode:
            raise SystemExit(f"{tool}: cannot check out --against {against!r} from {here} (a shallow clone "
                             f"lacks older commits; `git fetch --unshallow`): {r.stderr.strip()}")
        try:
            yield here, old
        finally:
            subprocess.run(["git", "-C", here, "worktree", "remove", "--force", old], check=False,
                           capture_output=True)


FOLDERS = ("kernels", "registration", "graph", "slam", "perf")

# The start of a child that imports the package from a checkout (tree_env): `kernels` and `perf` bound to that
# tree's, under the one import name (this layout) or as the top-level folders of older commits.
CHILD_IMPORTS = r"""
import os
if os.environ.get("SWARMSPLAT_TREE_LAYOUT") == "namespace":
    from swarmsplat import kernels, perf
else:
    import kernels, perf
"""


def tree_env(tree: str, scratch: str) -> dict:
    """The environment of a child process that imports the package from `tree`, a checkout of any commit. The
    `swarmsplat.*` names resolve to the tree's folders through a namespace folder of links in `scratch`; older
    commits, whose folders were top-level packages, find them on the path (the tree itself)."""
    ns = os.path.join(scratch, "namespace")
    os.makedirs(os.path.join(ns, "swarmsplat"), exist_ok=True)
    for top in FOLDERS:
        link = os.path.join(ns, "swarmsplat", top)
        if not os.path.lexists(link):
            os.symlink(os.path.join(tree, top), link)
    layout = "namespace" if os.path.exists(os.path.join(tree, "setup.py")) else "folders"
    return dict(os.environ, PYTHONPATH=os.pathsep.join([ns, tree]), SWARMSPLAT_TREE_LAYOUT=layout)


def shared_data(name: str, subject: str):
    """../shared/data/NAME (or $SWARMSPLAT_SHARED_DATA/NAME) as a Path; a missing one ends `python -m perf
    SUBJECT` with one line saying where it looked."""
    import os
    from pathlib import Path

    root = Path(os.environ.get("SWARMSPLAT_SHARED_DATA", Path(__file__).resolve().parents[2] / "shared" / "data"))
    p = root / name
    if not p.exists():
        raise SystemExit(f"perf {subject}: {p} not found (set SWARMSPLAT_SHARED_DATA to ../shared/data)")
    return p
