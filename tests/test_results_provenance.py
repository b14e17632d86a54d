"""Every figure of the README's "Results at a glance" has a source: each row links a result file under
perf/results/ (written by `python -m perf ...` through perf.common.write_results), each linked file's provenance
names the clean commit it measured (not a tree with uncommitted changes, not a file from before provenance was
recorded), and the commit the README cites beside a link is that file's."""

from __future__ import annotations

import json
import re
from pathlib import Path

import pytest

from swarmsplat.perf.common import provenance_line, read_provenance

REPO = Path(__file__).resolve().parents[1]
LINK = re.compile(r"\[[^\]]*\]\((perf/results/[^)\s]+)\)(?:\s*\(([0-9a-f]{7,40})\b)?")


def glance_rows(readme: str) -> list[str]:
    """The table rows of the README's "## Results at a glance" section (header and rule left out)."""
    section = readme.split("## Results at a glance", 1)[1].split("\n## ", 1)[0]
    rows = [ln for ln in section.splitlines() if ln.startswith("|")]
    return [r for r in rows[2:]]


def row_sources(row: str) -> list[tuple[str, str | None]]:
    """(result file, commit cited beside it or None) for each perf/results link in the row's last cell."""
    last = row.rstrip().rstrip("|").rsplit("|", 1)[-1]
    return LINK.findall(last)


def test_every_row_links_a_result_file():
    rows = glance_rows((REPO / "README.md").read_text())
    assert len(rows) >= 5
    unsourced = [r[:80] for r in rows if not row_sources(r)]
    assert not unsourced, f"rows without a perf/results file: {unsourced}"


def _cited() -> list[tuple[str, str | None]]:
    return sorted({s for r in glance_rows((REPO / "README.md").read_text()) for s in row_sources(r)})


@pytest.mark.parametrize("path,cited", _cited())
def test_each_cited_result_file_names_its_clean_commit(path, cited):
    assert (REPO / path).is_file(), f"{path} does not exist"
    prov = read_provenance(REPO / path)
    assert prov["clean"], f"{path} does not name a clean commit: {prov['line'][:200]}"
    if cited is not None:
        assert prov["commit"].startswith(cited) or cited.startswith(prov["commit"]), \
            f"the README cites {cited} for {path}, which was measured at {prov['commit']}"


def test_the_check_tells_clean_from_dirty_and_unrecorded(tmp_path):
    clean = {"commit": "0123456789ab", "dirty": False, "date": "2026-12-06T00:00:00+0000"}
    for name, machine, ok in (("clean", clean, True), ("dirty", {**clean, "dirty": True}, False),
                              ("none", {**clean, "commit": None, "dirty": None}, False)):
        (tmp_path / f"{name}.json").write_text(json.dumps({"machine": machine}))
        (tmp_path / f"{name}.md").write_text(provenance_line(machine) + "\n\n| a |\n")
        for ext in ("json", "md"):
            assert read_provenance(tmp_path / f"{name}.{ext}")["clean"] is ok, (name, ext)
    assert "(uncommitted changes)" in (tmp_path / "dirty.md").read_text().splitlines()[0]
    (tmp_path / "old.md").write_text("_Measured before result files recorded their provenance: committed in "
                                     "21d2fe5 on 2026-12-04._\n")
    (tmp_path / "old.json").write_text(json.dumps({"provenance": {"commit": None, "committed_in": "21d2fe5"}}))
    assert not read_provenance(tmp_path / "old.md")["clean"] and not read_provenance(tmp_path / "old.json")["clean"]
    row = ("| x | 1 cm | [perf/results/a-cpu.md](perf/results/a-cpu.md) (abc1234), [b](perf/results/b-cpu.json) "
           "(def5678, Intel Xeon) |")
    assert row_sources(row) == [("perf/results/a-cpu.md", "abc1234"), ("perf/results/b-cpu.json", "def5678")]
    assert row_sources("| x | 1 cm | [docs/decisions/0006](docs/decisions/0006.md) (eddbc45) |") == []
