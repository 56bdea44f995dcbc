"""The README's results table, docs/results.md and docs/cli.md are what
``benchmarks/tables.py`` makes of the result files and the parsers: a figure cannot drift
from the file that measured it, nor a documented option from ``--help``."""

from __future__ import annotations

import importlib.util
import re
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def tables():
    spec = importlib.util.spec_from_file_location("tables", ROOT / "benchmarks" / "tables.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    yield module
    sys.path.remove(str(ROOT / "benchmarks"))


def test_readme_table_is_generated_from_its_files(tables):
    readme = (ROOT / "README.md").read_text()
    assert tables.render_readme(readme) == readme, "README's table differs: run python benchmarks/tables.py --write"
    block = re.search(r"<!-- table results:[^\n]*-->\n(.*?)<!-- end table results -->", readme, re.S).group(1)
    rows = [line for line in block.splitlines() if line.startswith("| ") and "---" not in line][1:]
    assert 3 <= len(rows) <= 10, "the README's table holds the headline figures: 3 to 10 rows"
    assert all(re.search(r"`[\w./-]+\.json`", row) for row in rows), "every row names its result file"


@pytest.mark.parametrize("page", ["docs/results.md", "docs/cli.md"])
def test_generated_pages_are_what_the_script_makes(tables, page):
    committed = (ROOT / page).read_text()
    assert tables.PAGES[page]() == committed, f"{page} differs: run python benchmarks/tables.py --write"


def test_every_section_reads_files_that_exist_and_every_file_is_indexed(tables):
    results = ROOT / "benchmarks" / "results"
    page = (ROOT / "docs" / "results.md").read_text()
    for section in tables.sections():
        for name in section.files:
            assert (results / name).exists(), f"{section.title}: {name} is missing"
    for entry in tables._entries():
        assert f"| `{entry}` |" in page, f"{entry} is not in the index of docs/results.md"


def test_provenance_is_read_from_the_file(tables, tmp_path, monkeypatch):
    (tmp_path / "new.json").write_text('{"provenance": {"commit": "abc123", "command": "python benchmarks/x.py '
                                       '--steps 300", "settings": {"steps": 300}}, "value": 1}')
    (tmp_path / "old.json").write_text('{"value": 1}')
    monkeypatch.setattr(tables, "RESULTS", tmp_path)
    assert tables.provenance("new.json") == {"commit": "abc123", "command": "python benchmarks/x.py --steps 300",
                                             "budget": "steps=300"}
    assert tables.provenance("old.json") == {"commit": None, "command": None, "budget": None}
