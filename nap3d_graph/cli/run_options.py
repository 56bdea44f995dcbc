"""The run's options, generated from its settings tree
(:class:`~nap3d_graph.run.settings.RunSettings`): each field that declares a flag
(:func:`~nap3d_graph.run.settings.setting`) is one :class:`~nap3d_graph.cli.binding.Option`
(its flag, the ``section.setting`` it sets, how argparse reads it; its default is the
field's). ``run`` and ``compare`` add :data:`SOURCE_OPTIONS` (``compare`` writes its own
``--out``), ``run`` also :data:`RUN_OPTIONS`.
"""

from __future__ import annotations

from nap3d_graph.run.settings import RunSettings

from .binding import Option, flag_options

__all__ = ["SOURCE_OPTIONS", "RUN_OPTIONS"]

SOURCE_OPTIONS: tuple[Option, ...] = flag_options(RunSettings, only_run=False)

#: The options only ``run`` has (``compare`` runs inline from the start, writes its own folder).
RUN_OPTIONS: tuple[Option, ...] = flag_options(RunSettings, only_run=True)
