"""InputSilence: the node's wall-clock rule for "no message at all", confirmed before it acts.

Sweeps that wait for their odometry are bounded in stream time by the pipeline; when messages
stop altogether, nothing newer comes to end the wait, so the node also lets them in after
`limit_sec` of wall time without any message. Silence is read from callbacks that have run,
not from what DDS holds: after the process stalled (a long GIL hold, a page-in, a busy core)
every input looks silent although odometry sits ready in DDS. So the first look that finds the
input silent only marks it; the rule fires at a later look, at least `confirm_sec` on, when no
message came in between: by then the executor has run the callbacks that were ready.
"""
from __future__ import annotations

import time

CONFIRM_SEC = 0.1  # a few executor rounds: callbacks ready after a stall have run by then


class InputSilence:
    """Wall-clock silence of the inputs. heard() on every message; expired() from the polls."""

    def __init__(self, limit_sec: float, confirm_sec: float = CONFIRM_SEC,
                 now: float | None = None) -> None:
        self.limit_sec = limit_sec
        self.confirm_sec = confirm_sec
        self.last_heard = time.monotonic() if now is None else now
        self.silent_since_look: float | None = None  # the look that first found it silent

    def heard(self, now: float | None = None) -> None:
        """A message arrived (any input)."""
        self.last_heard = time.monotonic() if now is None else now

    def expired(self, now: float | None = None) -> bool:
        """True when nothing was heard for limit_sec, as found by two looks confirm_sec apart
        with no message in between."""
        now = time.monotonic() if now is None else now
        if now - self.last_heard <= self.limit_sec:
            self.silent_since_look = None
            return False
        if self.silent_since_look is None or self.silent_since_look < self.last_heard:
            self.silent_since_look = now  # first look at this silence: mark it only
            return False
        return now - self.silent_since_look >= self.confirm_sec
