"""Which recording a sequence is: a content fingerprint that survives renames and frame ranges.

A field records the recording it was built from so that a run can tell "this very frame was
trained on" from "another recording's frame with the same stamp": simulated sequences (and
re-stamped real ones) share stamps, so stamps alone misreport. The fingerprint hashes files
that tell recordings apart and do not depend on which frames a run selects (the lists, the
ground truth, the first and last listed images), so the first and the second half of one
recording have the same identity.
"""

from __future__ import annotations

import hashlib
from pathlib import Path

__all__ = ["fingerprint_files"]

#: Bytes read from each file at most: enough to tell recordings apart, cheap on a large bag.
_MAX_BYTES = 1 << 20


def fingerprint_files(paths) -> str:
    """A 16-hex-digit SHA-1 fingerprint of the given files' contents (missing files count as
    empty; each file contributes at most its first MiB and its size)."""
    digest = hashlib.sha1()
    for path in paths:
        path = Path(path)
        try:
            with path.open("rb") as handle:
                digest.update(handle.read(_MAX_BYTES))
            digest.update(str(path.stat().st_size).encode())
        except OSError:
            digest.update(b"<missing>")
        digest.update(b"\0")
    return digest.hexdigest()[:16]
