"""``python -m nap3d_graph``: the ``nap3d-graph`` command."""

import sys

from nap3d_graph.cli import main

sys.exit(main())
