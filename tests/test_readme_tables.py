"""The README's generated tables are what ``benchmarks/tables.py`` makes of the result files:
a figure cannot drift from the file that measured it."""

from __future__ import annotations

import importlib.util
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _tables():
    spec = importlib.util.spec_from_file_location("tables", ROOT / "benchmarks" / "tables.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_readme_tables_are_generated_from_their_files():
    tables = _tables()
    readme = (ROOT / "README.md").read_text()
    for name in tables.TABLES:
        assert f"<!-- table {name}:" in readme, f"README has no generated table {name}"
    assert tables.render_readme(readme) == readme, "README's tables differ: run python benchmarks/tables.py --write"


def test_every_row_names_its_file():
    tables = _tables()
    for name in tables.MAP_SURVEY_FILES:
        if (ROOT / "benchmarks" / "results" / name).is_file():
            assert f"`{name}`" in tables.map_survey_table()
