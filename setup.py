"""One import name: the design card's folders stay at the top of the repository and install as
swarmsplat.kernels, swarmsplat.registration, swarmsplat.graph, swarmsplat.slam and swarmsplat.perf (`swarmsplat`
itself is a namespace package holding only these), plus the YAML presets of configs/ as swarmsplat.configs.
Nothing else lands in site-packages. Everything else about the distribution is in pyproject.toml."""

from setuptools import find_packages, setup

FOLDERS = ("kernels", "registration", "graph", "slam", "perf")

setup(
    packages=[f"swarmsplat.{top}{'.' + sub if sub else ''}" for top in FOLDERS for sub in ["", *find_packages(top)]]
    + ["swarmsplat.configs"],
    package_dir={**{f"swarmsplat.{top}": top for top in FOLDERS}, "swarmsplat.configs": "configs"},
    package_data={"swarmsplat.configs": ["*.yaml"],
                  "swarmsplat.registration": ["place_recognition/vocabularies/*.npz"],
                  "swarmsplat.slam": ["io/ros2/msg/*/*.msg"]},
)
