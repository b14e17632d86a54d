"""`swarmsplat view RUN --screenshot PNG` in headless Chromium (skipped without the `view` extra or Chromium):
the PNG shows the page with the map's splats drawn (the run's three red Gaussians are red pixels in it)."""

from __future__ import annotations

import numpy as np
import pytest

from view_runs import write_team_run

pytest.importorskip("viser")


def test_screenshot_shows_the_splats(tmp_path, capsys):
    import cv2

    from swarmsplat.slam.cli import main
    from swarmsplat.slam.synthetic import GeneratorConfig, generate
    from swarmsplat.slam.view.screenshot import find_browser

    if find_browser() is None:
        pytest.skip("Chromium is not installed (Debian: apt-get install chromium)")
    data = generate(tmp_path / "d", GeneratorConfig.preset("tiny", frames=3))
    write_team_run(tmp_path / "run", data)
    png = tmp_path / "shot.png"
    assert main(["view", str(tmp_path / "run"), "--screenshot", str(png)]) == 0
    assert capsys.readouterr().out.strip() == str(png)
    img = cv2.imread(str(png))  # BGR
    assert img.shape == (800, 1280, 3)
    b, g, r = (img[..., i].astype(int) for i in range(3))
    red = (r > 150) & (g < 90) & (b < 90)
    assert red.mean() > 0.002, f"only {100 * red.mean():.3f} % red pixels: splats not in the picture"
    assert not list(tmp_path.glob(".shot.png.*"))  # written atomically, nothing left behind

