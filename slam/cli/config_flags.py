"""`--config FILE`, `--preset NAME` and `--set KEY=VALUE` for every command that runs SLAM, and the one way they
combine with the command's own flags: defaults, then the preset, then the file, then each flag the user gave (a
flag left out keeps the file's value), then each `--set` in order. `--set` reaches any key of the one config tree
(`--set server.top_k=4 --set loop_closure.descriptor=thumbnail`; the value is read as YAML). A bad value is one line
naming where it came from: `FILE: field 'a.b': expected ...`, or `--flag VALUE: field 'a.b': expected ...`."""

from __future__ import annotations

from typing import Any


def add_config_flags(p, *, preset: bool = True) -> None:
    p.add_argument("--config", metavar="YAML", help="config file (any sections of the one config tree, "
                                                    "docs/config.md); flags given on the command line override it")
    if preset:
        p.add_argument("--preset", metavar="NAME", help="start from the preset configs/NAME.yaml (the file given "
                                                        "with --config then overrides it)")
    p.add_argument("--set", dest="config_set", action="append", default=[], metavar="KEY=VALUE",
                   help="set one key of the config tree, e.g. --set server.top_k=4 (repeatable; applied last; the "
                        "value is read as YAML: numbers, true/false, null)")


def parse_sets(items) -> dict[str, tuple[str, Any]]:
    """['a.b=3', ...] -> load_config flags {"--set a.b=3": ("a.b", 3)}; InputError for an item without KEY=."""
    import yaml

    from swarmsplat.kernels.errors import InputError

    out = {}
    for item in items or ():
        key, eq, text = str(item).partition("=")
        if not eq or not key.strip() or any(not part for part in key.strip().split(".")):
            raise InputError(f"--set {item}: expected KEY=VALUE with a dotted key of the config tree, e.g. "
                             f"server.top_k=4")
        try:
            value = yaml.safe_load(text) if text.strip() else None
        except yaml.YAMLError:
            value = text
        out[f"--set {item}"] = (key.strip(), value)
    return out


def load_config(config: str | None, flags: dict[str, tuple[str, Any]], preset: str | None = None, sets=()):
    """The SlamConfig of a command: `preset`, then the file `config`, then `flags` ({"--flag": ("section.key",
    value)}; a None value was not given and changes nothing), then `sets` (the --set items), each validated where
    it comes from."""
    from swarmsplat.slam.config import SlamConfig

    cfg = SlamConfig.from_yaml(config, preset=preset)
    for flag, (path, value) in flags.items():
        if value is None:
            continue
        cfg = cfg.override(_nested(path, value), where=f"{flag} {value}" if not isinstance(value, bool) else flag)
    for flag, (path, value) in parse_sets(sets).items():  # null is a value here: --set server.tau_sim=null
        cfg = cfg.override(_nested(path, value), where=flag)
    return cfg


def _nested(path: str, value: Any) -> dict:
    update: Any = value
    for key in reversed(path.split(".")):
        update = {key: update}
    return update


def section_flags(args, section: str, keys) -> dict[str, tuple[str, Any]]:
    """`load_config`'s flags for options named after keys of `section`: --a-b sets section.a_b."""
    return {f"--{key.replace('_', '-')}": (f"{section}.{key}", getattr(args, key)) for key in keys}
