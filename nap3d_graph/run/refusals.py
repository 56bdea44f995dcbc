"""Telling the user, while the run goes, that corrections keep failing for one reason."""

from __future__ import annotations

import logging

from nap3d_graph.run.output import refusal_hint_for
from nap3d_graph.run.records import KeyframeRecord, refusal_kind

__all__ = ["RefusalWatch"]

log = logging.getLogger(__name__)


class RefusalWatch:
    """Warns (once per streak) when the last ``streak`` keyframes were all refused for the same
    reason: the run then goes on on its odometry alone, and the user should know it now, not
    from the summary."""

    #: Consecutive keyframes refused for one reason before the run says so.
    STREAK = 5

    def __init__(self, streak: int = STREAK):
        self.streak = streak
        self.kind: str | None = None  # the current run of refusals: its reason's kind, and how many
        self.count = 0

    def observe(self, record: KeyframeRecord) -> None:
        """One finished keyframe's verdict."""
        if record.accepted:
            self.kind, self.count = None, 0
            return
        kind = refusal_kind(record.reason)
        self.count = self.count + 1 if kind == self.kind else 1
        self.kind = kind
        if self.count == self.streak:
            log.warning("the last %d keyframes (to frame %d) were all refused for '%s' (the last: %s); the run goes "
                        "on on its odometry alone until corrections land again. %s", self.count, record.frame_index,
                        kind, record.reason, refusal_hint_for(kind))
