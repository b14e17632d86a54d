"""A short, deterministic slice of the fuzzers (perf/fuzz_targets.py; `python -m perf fuzz` runs them for hours):
every parser of outside data is fed its seed corpus (tests/fuzz/corpus/<target>/), every crash the fuzzers ever
found (tests/fuzz/crashes/<target>/), and 300 seeded mutations of the seeds — bytes flipped, inserted, deleted,
lines duplicated or cut, numbers swapped for extremes — and may only return or raise InputError, each input
within a second."""

from __future__ import annotations

import random
import re
import time
import warnings

import pytest

from swarmsplat.perf.fuzz_targets import TARGETS, corpus_dir, expected_errors

MUTATIONS = 300
SECONDS_PER_INPUT = 1.0
_NUMBERS = [b"0", b"-1", b"1e308", b"-1e308", b"nan", b"inf", b"4294967296", b"9" * 40, b"", b"1e-320", b"0x10"]


def _mutate(data: bytes, rng: random.Random) -> bytes:
    b = bytearray(data)
    for _ in range(rng.randint(1, 4)):
        op = rng.randrange(7)
        if op == 0 and b:  # flip a byte
            b[rng.randrange(len(b))] = rng.randrange(256)
        elif op == 1:  # insert random bytes
            i = rng.randint(0, len(b))
            b[i:i] = bytes(rng.randrange(256) for _ in range(rng.randint(1, 8)))
        elif op == 2 and b:  # delete a run
            i = rng.randrange(len(b))
            del b[i:i + rng.randint(1, 16)]
        elif op == 3:  # truncate
            del b[rng.randint(0, len(b)):]
        elif op == 4:  # duplicate or drop a line
            lines = bytes(b).split(b"\n")
            k = rng.randrange(len(lines))
            lines[k:k + 1] = [lines[k]] * rng.choice([0, 2, 3])
            b = bytearray(b"\n".join(lines))
        else:  # a number swapped for an extreme one
            nums = list(re.finditer(rb"-?\d+(\.\d+)?(e-?\d+)?", bytes(b)))
            if nums:
                m = rng.choice(nums)
                b[m.start():m.end()] = rng.choice(_NUMBERS)
    return bytes(b)


def _inputs(name: str) -> list[tuple[str, bytes]]:
    seeds = [(p.name, p.read_bytes()) for p in sorted(corpus_dir(name).iterdir())]
    crashes = corpus_dir(name).parent.parent / "crashes" / name
    found = [(f"crash {p.name}", p.read_bytes()) for p in sorted(crashes.iterdir())] if crashes.is_dir() else []
    rng = random.Random(f"fuzz-{name}")
    mutated = [(f"mutation {k}", _mutate(rng.choice(seeds)[1], rng)) for k in range(MUTATIONS)]
    return seeds + found + mutated + [("empty", b"")]


@pytest.mark.parametrize("name", sorted(TARGETS))
def test_parser_returns_or_raises_input_error(name):
    assert corpus_dir(name).is_dir() and any(corpus_dir(name).iterdir()), f"no seed corpus for {name}"
    target, ok = TARGETS[name], expected_errors()
    inputs = _inputs(name)
    try:  # the first call imports the parser's modules (torch for some): not a parser's time
        target(inputs[0][1])
    except ok:
        pass
    slow = []
    for label, data in inputs:
        t0 = time.perf_counter()
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                target(data)
        except ok:
            pass
        except Exception as e:  # noqa: BLE001 - the point: anything else is a bug, shown with its input
            raise AssertionError(f"{name} {label}: {type(e).__name__}: {e}\ninput: {data[:200]!r}") from e
        dt = time.perf_counter() - t0
        if dt > SECONDS_PER_INPUT:
            slow.append((label, round(dt, 2)))
    assert not slow, f"{name}: inputs over {SECONDS_PER_INPUT} s: {slow}"
