"""``python -m nap3d_graph.cli``: the ``nap3d-graph`` command."""

import sys

from . import main

sys.exit(main())
