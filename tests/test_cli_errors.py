"""Every CLI command, walked through bad arguments: each gives the package's one-line error
(`swarmsplat CMD: error: ...`, exit 2) naming what is wrong — an output path that is a file, under a file, a
folder where a file is wanted, or not writable; a dataset path that is a file; negative counts; bad ranges — and
a file the user already had is left as it was."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from swarmsplat.slam.cli import main

PRECIOUS = "a file the user already had\n"


@pytest.fixture(scope="module")
def paths(tmp_path_factory):
    from swarmsplat.slam.synthetic import GeneratorConfig, generate

    root = tmp_path_factory.mktemp("cli_errors")
    f = root / "afile"
    f.write_text(PRECIOUS)
    (root / "adir").mkdir()
    rgbd = generate(root / "rgbd", GeneratorConfig.preset("tiny", agents=1, frames=2, seed=1))
    mono = generate(root / "mono", GeneratorConfig.preset("tiny", agents=2, frames=2, seed=1, mono=True))
    traj = root / "traj.txt"
    traj.write_text("".join(f"{t}.0 {t}.0 0 0 0 0 0 1\n" for t in range(5)))
    g2o = root / "g.g2o"
    g2o.write_text("VERTEX_SE3:QUAT 0 0 0 0 0 0 0 1\nVERTEX_SE3:QUAT 1 1 0 0 0 0 0 1\n"
                   "EDGE_SE3:QUAT 0 1 1 0 0 0 0 0 1 " + "1 0 0 0 0 0 1 0 0 0 0 1 0 0 0 1 0 0 1 0 1\n")
    if os.geteuid() == 0:  # root writes anywhere a mode allows; /sys refuses new entries even to root
        ro = Path("/sys/swarmsplat-cli-test")
    else:
        ro = root / "readonly"
        ro.mkdir()
        ro.chmod(0o500)
        ro = ro / "out"
    return {"FILE": str(f), "DIR": str(root / "adir"), "SEQ": str(rgbd / "agent_0"),
            "MONO": str(mono), "TRAJ": str(traj), "G2O": str(g2o), "RO": str(ro), "MISSING": str(root / "missing")}


CASES = [  # (argv with placeholders, a fragment the error line must contain)
    ("demo --out FILE", "is a file"),
    ("demo --out FILE/x", "is a file"),
    ("demo --out NEW --seed -1", "seed"),
    ("demo --out NEW --preset huge", "invalid choice"),
    ("generate --out FILE", "is a file"),
    ("generate --out FILE/x", "is a file"),
    ("generate --out NEW --agents 0", "agents"),
    ("generate --out NEW --frames -1", "frames"),
    ("generate --out NEW --fps -1", "fps"),
    ("generate --preview DIR", "is a folder"),
    ("generate", "--out"),
    ("run SEQ --out FILE", "is a file"),
    ("run SEQ --out FILE/sub", "is a file"),
    ("run SEQ --out RO", "cannot write"),
    ("run FILE --out NEW", "not a folder"),
    ("run MISSING --out NEW", "not found"),
    ("run SEQ --out NEW --frames -3", "--frames must be at least 1"),
    ("run SEQ --out NEW --frames 0", "--frames must be at least 1"),
    ("run SEQ --out NEW --frames abc", "invalid int value"),
    ("run SEQ --out NEW --config MISSING", "config file not found"),
    ("run SEQ --out NEW --split 3:1,0:2", "--split"),
    ("run SEQ", "--out"),
    ("run SEQ --out NEW --processes", "--processes"),
    ("run SEQ --out NEW --set server.top_k", "KEY=VALUE"),
    ("run SEQ --out NEW --set server.top_k=zero", "--set server.top_k=zero: field 'server.top_k'"),
    ("run SEQ --out NEW --set server.no_such_key=1", "server.no_such_key"),
    ("demo --out NEW --set loop_closure.descriptor=nope", "loop_closure.descriptor"),
    ("server --agents 0 --out NEW", "--agents"),
    ("server --agents 2 --out FILE", "is a file"),
    ("server --agents 2 --out NEW --listen 127.0.0.1", "--listen"),
    ("server --agents 2 --out NEW --split 0:1,1:", "--dataset"),
    ("agent SEQ --server 127.0.0.1:7447 --id 0", "--server"),
    ("agent SEQ --server 127.0.0.1:7447 --split 0:1,1:", "--id"),  # which part: --name one of them or --id
    ("agent SEQ --server 127.0.0.1:7447 --id 30", "--id"),
    ("agent SEQ --id 0 --out NEW", "--server"),
    ("agent SEQ", "--out"),
    ("eval --gt MISSING --est TRAJ", "not found"),
    ("eval --gt TRAJ --est DIR", "both be files"),
    ("eval --gt TRAJ --est TRAJ --max-diff -1", "max_diff"),
    ("eval --gt TRAJ --est TRAJ --align none --delta 0", "delta"),
    ("eval --gt TRAJ --est TRAJ --json DIR", "is a folder"),
    ("eval --gt TRAJ --est TRAJ --plot DIR", "is a folder"),
    ("eval --gt TRAJ --est TRAJ --json FILE/m.json", "is a file"),
    ("graph solve MISSING --out NEW", "not found"),
    ("graph solve G2O --out DIR", "is a folder"),
    ("graph solve G2O --out FILE/o.g2o", "is a file"),
    ("graph solve G2O --out NEW --solver gnc --gnc-probability 2", "probability"),
    ("graph solve G2O --out NEW --distributed --relax 2.5", "--relax in"),
    ("graph solve G2O --out NEW --distributed --sparse-tol -1", "--sparse-tol"),
    ("graph solve G2O --out NEW --sparse-tol 0.001", "--sparse-tol applies to --distributed"),
    ("graph solve DIR --out NEW --distributed", "no <k>.g2o files"),
    ("graph solve G2O --out NEW --distributed", "needs robot keys"),
    ("graph solve G2O --out NEW --processes", "add --distributed"),
    ("graph solve G2O --out NEW --gnc-steps 5", "add --distributed --solver gnc"),
    ("graph solve G2O --out NEW --distributed --solver gnc --gnc-steps 0", "--gnc-steps, --gnc-rounds and --gnc-ls-rounds"),
    ("pairs MONO --out DIR", "is a folder"),
    ("pairs MONO --out FILE/p.csv", "is a file"),
    ("pairs FILE --out NEW", "not a folder"),
    ("pairs SEQ --out NEW", "at least two agents"),
    ("pairs MONO --out NEW --stride 0", "stride"),
    ("pairs MONO --out NEW --top-k -1", "top_k"),
    ("pairs MONO --out NEW --threshold 2", "threshold"),
    ("swarm MONO --out FILE", "is a file"),
    ("swarm FILE --out NEW", "not a folder"),
    ("swarm MONO --out NEW --stride -1", "--stride"),
    ("swarm MONO --out NEW --schedule MISSING", "schedule"),
    ("swarm MONO --out NEW --processes --port-base -4", "--port-base"),
    ("swarm MONO --out NEW --place nope", "place-recognition"),
    ("swarm MONO --out NEW --formulation nope", "invalid choice"),
    ("robot --id -1 MONO --out NEW --start-time 0", "--id"),
    ("robot --id 0 MONO --out FILE --start-time 0", "is a file"),
    ("robot --id 0 MONO --out NEW --start-time 0 --port-base 70000", "--port-base"),
    ("bench nosuch", "invalid choice"),
    ("bench raster --json DIR", "is a folder"),
]


@pytest.mark.parametrize("argv, fragment", CASES, ids=[c[0] for c in CASES])
def test_bad_argument_is_one_line(paths, tmp_path, capsys, argv, fragment):
    if "RO" in argv.split() and not Path(paths["RO"]).parent.is_dir():
        pytest.skip("no read-only place to try")
    paths = {**paths, "NEW": str(tmp_path / "new")}  # a fresh output path for each case
    args = [paths.get(a, a) if "/" not in a else paths[a.split("/")[0]] + "/" + a.split("/", 1)[1]
            for a in argv.split()]
    try:
        code = main(args)
    except SystemExit as e:  # argparse: unknown choice, missing or non-numeric value
        code = e.code
    assert code == 2, argv
    err = [ln for ln in capsys.readouterr().err.splitlines() if ln.strip() and not ln.startswith(("Warp ", "[I "))]
    command = args[0]
    assert len(err) == 1, err
    assert err[0].startswith(f"swarmsplat {command}: error: ") and fragment in err[0], err[0]
    assert Path(paths["FILE"]).read_text() == PRECIOUS
