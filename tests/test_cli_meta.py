"""The console script's own flags: --version, and `swarmsplat bench` as a front end of perf's driver (its usage
under its own name, its errors as the package's one line)."""

from __future__ import annotations

import subprocess
import sys
from importlib import metadata

import pytest

from swarmsplat.slam.cli import main


def _cli(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "swarmsplat.slam", *args], capture_output=True, text=True,
                          timeout=120)


def test_version_is_the_installed_distributions():
    out = _cli("--version")
    assert out.returncode == 0 and out.stdout.strip() == f"swarmsplat {metadata.version('swarmsplat')}"


def test_bench_help_is_perfs_under_its_own_name():
    out = _cli("bench", "--help")
    assert out.returncode == 0, out.stderr
    assert out.stdout.startswith("usage: swarmsplat bench") and "--quick" in out.stdout


@pytest.mark.parametrize("args, expected", [(["bench", "nosuch"], "invalid choice: 'nosuch'"),
                                            (["bench", "raster", "--frames", "3"], "unrecognized arguments")])
def test_bench_usage_errors_are_one_line(args, expected, capsys):
    assert main(args) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("swarmsplat bench: error:") and expected in err and "\n" not in err, err
