"""`--config FILE` and `--preset NAME` for every command that runs SLAM, and the one way they combine with the
command's own flags: defaults, then the preset, then the file, then each flag the user gave (a flag left out keeps
the file's value). A bad value is one line naming where it came from: `FILE: field 'a.b': expected ...`, or
`--flag VALUE: field 'a.b': expected ...`."""

from __future__ import annotations

from typing import Any


def add_config_flags(p, *, preset: bool = True) -> None:
    p.add_argument("--config", metavar="YAML", help="config file (any sections of the one config tree, "
                                                    "docs/config.md); flags given on the command line override it")
    if preset:
        p.add_argument("--preset", metavar="NAME", help="start from the preset configs/NAME.yaml (the file given "
                                                        "with --config then overrides it)")


def load_config(config: str | None, flags: dict[str, tuple[str, Any]], preset: str | None = None):
    """The SlamConfig of a command: `preset`, then the file `config`, then `flags` ({"--flag": ("section.key",
    value)}; a None value was not given and changes nothing), each validated where it comes from."""
    from swarmsplat.slam.config import SlamConfig

    cfg = SlamConfig.from_yaml(config, preset=preset)
    for flag, (path, value) in flags.items():
        if value is None:
            continue
        update: Any = value
        for key in reversed(path.split(".")):
            update = {key: update}
        cfg = cfg.override(update, where=f"{flag} {value}" if not isinstance(value, bool) else flag)
    return cfg


def section_flags(args, section: str, keys) -> dict[str, tuple[str, Any]]:
    """`load_config`'s flags for options named after keys of `section`: --a-b sets section.a_b."""
    return {f"--{key.replace('_', '-')}": (f"{section}.{key}", getattr(args, key)) for key in keys}
