"""What a process reports of its own memory: the peak a map's stages and submap jobs record."""

import subprocess
import sys


def test_a_process_peak_memory_rises_by_what_it_held():
    """A fresh process that fills 300 MB (0.29 GB of 1024^3) reports a peak of at least that, and
    not more than that above the peak it had before (its imports' own, partly freed since); what
    it reports before is its own, not the process that started it (pytest's, a GB here)."""
    script = ("import numpy as np; from nap3d_graph.pools import peak_memory_gb as p; a = p(); "
              "b = np.ones(300 * 2**20 // 8); print(a, p())")
    before, after = map(float, subprocess.check_output([sys.executable, "-c", script], text=True).split())
    assert 0.02 < before < 0.5 and before < after
    assert 0.29 < after < before + 0.32
