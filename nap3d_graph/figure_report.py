"""A report of figures against their bad lines, written as ``report.md``: the run's report
(:mod:`nap3d_graph.run.report`) and the map's (:mod:`nap3d_graph.mapping.report`)."""

from __future__ import annotations

from pathlib import Path

__all__ = ["FigureReport"]


class FigureReport:
    """Figures against their bad lines (``rows``: figure, value, good when, verdict; ``bad``:
    the figures past their line), written as ``report.md``. The map's report is one too."""

    def __init__(self):
        self.rows: list[tuple[str, str, str, str]] = []
        self.bad: list[str] = []

    def add(self, figure: str, value: str, good: str, ok: bool | None) -> None:
        self.rows.append((figure, value, good, "n/a" if ok is None else ("good" if ok else "BAD")))
        if ok is False:
            self.bad.append(figure)

    def write(self, path: Path, title: str, picture: str) -> None:
        """``path`` (report.md): ``title``, the table, what to look at, then ``picture``
        (a markdown image line)."""
        lines = [f"# {title}", "",
                 "Figures that need no ground truth (what each means and what a bad value looks like: "
                 "docs/usage/7-own-camera.md, \"Reading the reports\").", "",
                 "| figure | value | good when | verdict |", "|---|---|---|---|"]
        lines += [f"| {a} | {b} | {c} | {d} |" for a, b, c, d in self.rows]
        lines += ["", ("**Look at:** " + "; ".join(self.bad) + ".") if self.bad else "Nothing is past its bad line.",
                  "", picture, ""]
        Path(path).write_text("\n".join(lines))
