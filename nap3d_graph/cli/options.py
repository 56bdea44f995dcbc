"""Options several commands share, defined once: the output folder with ``--force``, the
random seed. Each command adds them with the words that are its own (what is seeded, the
default folder)."""

from __future__ import annotations

from pathlib import Path

__all__ = ["add_force", "add_output_folder", "add_seed"]


def add_force(parser) -> None:
    """``--force``: write into a folder that holds files already (they are replaced)."""
    parser.add_argument("--force", action="store_true", help="write into a non-empty folder (its files are replaced)")


def add_output_folder(parser, default: Path | None = None) -> None:
    """``--out FOLDER`` (required unless ``default``), empty or new unless ``--force``, and ``--force``."""
    where = f" (default {default})" if default is not None else ""
    parser.add_argument("--out", type=Path, required=default is None, default=default,
                        help=f"output folder, empty or new unless --force{where}")
    add_force(parser)


def add_seed(parser, what: str) -> None:
    """``--seed N`` (default 0): the seed of ``what``."""
    parser.add_argument("--seed", type=int, default=0, help=f"seed of {what} (default 0)")
