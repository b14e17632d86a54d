"""slam.io.progress: tqdm on a terminal, plain periodic lines (no carriage returns) elsewhere, silent when off; the
team's per-round callback; and a real run's stderr in a log (not a terminal) reads as lines."""

from __future__ import annotations

import io

import pytest

from swarmsplat.slam.io.progress import Bar, TeamRounds, bar, format_seconds, reporting


class Clock:
    def __init__(self):
        self.t = 100.0

    def __call__(self) -> float:
        return self.t


def test_plain_lines_every_interval_and_a_last_one():
    out, clock = io.StringIO(), Clock()
    b = Bar(6, "[a] frames", unit="frame", stream=out, tty=False, interval=10.0, clock=clock)
    for dt in (1, 2, 3):  # 6 s in: nothing yet
        clock.t += dt
        b.update(1, f"{dt} submaps")
    assert out.getvalue() == ""
    clock.t += 6  # 12 s in: one line
    b.update(1, "4 submaps")
    clock.t += 1
    b.update(1)
    clock.t += 1
    b.update(1)  # the last one is left to close()
    b.close()
    b.close()  # idempotent
    lines = out.getvalue().splitlines()
    assert lines == ["[a] frames 4/6 (67%)  12s elapsed, ~6s left, 3.0 s/frame  4 submaps",
                     "[a] frames 6/6 (100%)  14s elapsed, 2.3 s/frame  4 submaps"]
    assert "\r" not in out.getvalue()


def test_a_terminal_gets_a_tqdm_bar():
    out = io.StringIO()
    with Bar(3, "[team] rounds", unit="round", stream=out, tty=True) as b:
        for _ in range(3):
            b.update(1, "loops 2 intra")
    text = out.getvalue()
    assert "\r" in text and "3/3" in text and "loops 2 intra" in text and "[team] rounds" in text


def test_off_is_silent_and_library_bars_follow_reporting():
    out = io.StringIO()
    with bar(2, "x", enabled=False, stream=out, tty=False, interval=0) as b:
        b.update(2)
    with bar(2, "y", enabled=None, stream=out, tty=False, interval=0) as b:  # outside reporting(): off
        b.update(2)
    assert out.getvalue() == ""
    with reporting(True):
        with bar(2, "z", enabled=None, stream=out, tty=False, interval=0) as b:
            b.update(1)
    with reporting(False):
        assert not bar(1, "w", enabled=None, stream=out).enabled
    assert out.getvalue().splitlines()[0].startswith("z 1/2 (50%)")


def test_unknown_total_and_format_seconds():
    out, clock = io.StringIO(), Clock()
    b = Bar(None, "steps", unit="step", stream=out, tty=False, interval=1.0, clock=clock)
    clock.t += 90
    b.update(3)
    assert out.getvalue().startswith("steps 3 step  1m30s elapsed")
    assert [format_seconds(s) for s in (5, 65, 3725)] == ["5s", "1m05s", "1h02m"]


def test_team_rounds_callback_counts_rounds_and_feeds_the_observer():
    out, seen = io.StringIO(), []
    team = object()
    with TeamRounds(team, enabled=True, observer=seen.append, stream=out) as cb:
        cb.bar.interval = 0.0
        for i in range(1, 4):
            cb(i, 3, f"round {i}/3  keyframes {i}")
    assert seen == [team] * 3
    lines = out.getvalue().splitlines()
    assert lines[-1].startswith("[team] rounds 3/3 (100%)") and lines[-1].endswith("keyframes 3")


def test_a_run_in_a_log_prints_lines_not_carriage_returns(tmp_path, capsys, monkeypatch):
    """`swarmsplat run` with stderr captured (not a terminal): the frame progress is plain lines."""
    from swarmsplat.slam.cli import main
    from swarmsplat.slam.synthetic import GeneratorConfig, generate

    data = generate(tmp_path / "d", GeneratorConfig.preset("tiny", agents=1, frames=2))
    monkeypatch.setenv("SWARMSPLAT_PROGRESS_INTERVAL", "0")
    cfg = tmp_path / "fast.yaml"
    cfg.write_text("mapping: {iterations: 4, first_iterations: 8}\ntracking: {refine: false}\n")
    assert main(["run", str(data / "agent_0"), "--out", str(tmp_path / "o"), "--config", str(cfg)]) == 0
    err = capsys.readouterr().err
    assert "\r" not in err
    assert "[agent_0] frames 1/2 (50%)" in err and "[agent_0] frames 2/2 (100%)" in err


def test_a_bad_interval_setting_is_named(monkeypatch):
    from swarmsplat.kernels.errors import InputError

    monkeypatch.setenv("SWARMSPLAT_PROGRESS_INTERVAL", "soon")
    with pytest.raises(InputError, match="SWARMSPLAT_PROGRESS_INTERVAL must be a number of seconds >= 0, got 'soon'"):
        bar(3, "x", stream=io.StringIO(), tty=False)


@pytest.mark.parametrize("quiet", [False, True])
def test_generate_pairs_and_swarm_in_a_log_print_lines_and_nothing_when_quiet(tmp_path, capsys, monkeypatch, quiet):
    """`generate`, `pairs` and `swarm` report through the same module: plain lines in a log (no carriage returns),
    nothing with --quiet."""
    from swarmsplat.slam.cli import main

    monkeypatch.setenv("SWARMSPLAT_PROGRESS_INTERVAL", "0")
    flag = ["--quiet"] if quiet else []
    assert main(["generate", "--preset", "tiny", "--mono", "--frames", "4", "--out", str(tmp_path / "m"), *flag]) == 0
    assert main(["pairs", str(tmp_path / "m"), "--out", str(tmp_path / "p.csv"), "--stride", "2", *flag]) == 0
    assert main(["swarm", str(tmp_path / "m"), "--out", str(tmp_path / "s"), "--stride", "2", *flag]) == 0
    err = capsys.readouterr().err
    assert "\r" not in err
    for head in ("[generate] mono frames", "[pairs] describe", "[pairs] register", "[swarm] ticks"):
        assert (head in err) is not quiet, (head, err[-500:])
