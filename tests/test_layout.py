"""The house: one import name, imports that only point down, rooms of a size a reader can hold.

Layers, top to bottom (docs/dev.md draws them):

    slam.__main__
    slam.cli, perf                             commands; `swarmsplat bench` runs perf
    slam.run                                   one job end to end: drivers, results writers, guards
    slam.view                                  the browser viewer
    slam.metrics                               ATE/RPE, rendering quality
    slam.dense | slam.flocc | slam.synthetic   GRAND-SLAM, FLOCC-SLAM, the data generator (independent)
    slam.io                                    datasets, trajectories, progress, plots
    slam.config                                the one config tree
    registration | graph                       (independent of each other)
    kernels                                    numeric core, errors, files, camera, SE(3)
"""

from __future__ import annotations

import ast
import importlib.util
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
FOLDERS = ("kernels", "registration", "graph", "slam", "perf")

LAYERS = [
    ("kernels",),
    ("registration", "graph"),
    ("slam.config",),
    ("slam.io",),
    ("slam.dense", "slam.flocc", "slam.synthetic"),
    ("slam.metrics",),
    ("slam.view",),
    ("slam.run",),
    ("slam.cli", "perf"),
    ("slam.__main__", "slam"),
]
ALLOWED_ACROSS = {("slam.cli", "perf")}  # `swarmsplat bench` is the perf driver


def _module_name(path: Path) -> str:
    parts = list(path.relative_to(REPO).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _unit(module: str) -> tuple[int, str] | None:
    """(layer, unit) of a module given without the `swarmsplat.` prefix; the longest matching unit wins."""
    best = None
    for level, units in enumerate(LAYERS):
        for u in units:
            if (module == u or module.startswith(u + ".")) and (best is None or len(u) > len(best[1])):
                best = (level, u)
    return best


def _imports(path: Path, module: str):
    """Every module the file imports (at any depth, lazily or not), without the `swarmsplat.` prefix."""
    package = module if path.name == "__init__.py" else module.rpartition(".")[0]
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")[: len(package.split(".")) - node.level + 1]
                target = ".".join(base + ([node.module] if node.module else []))
            else:
                target = node.module or ""
                if not target.startswith("swarmsplat."):
                    continue
                target = target[len("swarmsplat."):]
            yield node.lineno, target
            for alias in node.names:
                yield node.lineno, f"{target}.{alias.name}"
        elif isinstance(node, ast.Import):
            for alias in node.names:
                if alias.name.startswith("swarmsplat."):
                    yield node.lineno, alias.name[len("swarmsplat."):]


def _files():
    for top in FOLDERS:
        yield from sorted((REPO / top).rglob("*.py"))


def test_imports_only_point_down():
    wrong = []
    for path in _files():
        here = _unit(_module_name(path))
        assert here is not None, f"{path.relative_to(REPO)} belongs to no layer: add its folder to LAYERS"
        for line, target in _imports(path, _module_name(path)):
            there = _unit(target)
            if there is None or there[1] == here[1] or (here[1], there[1]) in ALLOWED_ACROSS:
                continue
            if there[0] >= here[0]:
                wrong.append(f"{path.relative_to(REPO)}:{line} ({here[1]}) imports {target} ({there[1]})")
    assert not wrong, "imports that point up or sideways:\n" + "\n".join(sorted(set(wrong)))


def test_folders_stay_small():
    """Each folder of slam/ holds at most ~12 modules (besides __init__ / __main__)."""
    big = {}
    for d in [REPO / "slam", *(p for p in (REPO / "slam").rglob("*") if p.is_dir())]:
        mods = [p for p in d.glob("*.py") if p.name not in ("__init__.py", "__main__.py")]
        if d.name != "__pycache__" and len(mods) > 13:
            big[str(d.relative_to(REPO))] = len(mods)
    assert not big, big


def test_every_folder_is_in_the_one_namespace():
    """No module of the package imports a folder by its bare name (that name would not exist once installed)."""
    bare = []
    for path in _files():
        for node in ast.walk(ast.parse(path.read_text())):
            names = [a.name for a in node.names] if isinstance(node, ast.Import) else \
                [node.module] if isinstance(node, ast.ImportFrom) and not node.level and node.module else []
            bare += [f"{path.relative_to(REPO)}:{node.lineno} {n}" for n in names if n.split(".")[0] in FOLDERS]
    assert not bare, bare


def test_graph_imports_without_torch():
    code = ("import sys, swarmsplat.graph, swarmsplat.graph.pose_graph, swarmsplat.kernels.se3\n"
            "print(sorted({m.split('.')[0] for m in sys.modules} & {'torch', 'warp', 'taichi'}))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]", out.stdout


@pytest.mark.slow
def test_the_wheel_installs_one_top_level_name(tmp_path):
    # The build runs without network (--no-build-isolation: with this environment's packages, none fetched), so the
    # one thing it may lack is the build backend itself; any other failure is the wheel's and fails the test.
    if importlib.util.find_spec("setuptools") is None:
        pytest.skip("setuptools (the build backend) is not installed in this environment, and an offline build "
                    "with --no-build-isolation cannot fetch it")
    out = subprocess.run([sys.executable, "-m", "pip", "wheel", "-q", "--no-deps", "--no-build-isolation",
                          "-w", str(tmp_path), str(REPO)], capture_output=True, text=True)
    assert out.returncode == 0, out.stderr[-2000:]
    (wheel,) = tmp_path.glob("swarmsplat-*.whl")
    names = zipfile.ZipFile(wheel).namelist()
    assert {n.split("/")[0] for n in names} == {"swarmsplat", wheel.name.split("-py")[0] + ".dist-info"}
    for top in FOLDERS:  # every folder's modules are in it, under the one name
        expected = {f"swarmsplat/{p.relative_to(REPO).as_posix()}" for p in (REPO / top).rglob("*.py")}
        assert expected <= set(names), sorted(expected - set(names))[:5]
    presets = {f"swarmsplat/configs/{p.name}" for p in (REPO / "configs").glob("*.yaml")}  # SlamConfig.preset(...)
    assert presets and presets <= set(names), sorted(presets - set(names))
