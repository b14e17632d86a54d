"""perf/flocc_experiment.py runs end to end on a tiny team and its table has every row and column."""

from __future__ import annotations

import numpy as np

from swarmsplat.graph.synthetic import TeamConfig
from swarmsplat.perf.flocc_experiment import INITS, ROWS, markdown, run_backbone


def test_flocc_experiment_tiny_team():
    cfg = TeamConfig(robots=3, length_m=150, target_loops=60, seed=1, grid_nodes=3)
    res = run_backbone("lio", quick=True, gnc=False, log=lambda m: None, config=cfg)
    for row, _, solver in ROWS:
        for _, init in INITS:
            cell = res["cells"].get(f"{row}/{init}")
            assert (cell is None) == (solver == "gnc")
            if cell:
                assert np.isfinite(cell["ate"][0]) and cell["time_s"] > 0
    # IS does not depend on the initial scale: the same optimum from every initialisation
    ates = [res["cells"][f"IS-LM/{init}"]["ate"][0] for _, init in INITS]
    assert max(ates) - min(ates) < 0.05
    table = markdown(res)
    assert table.count("\n| ") >= len(ROWS) and "IS-LM" in table and "—" in table  # GNC rows skipped
