"""How long a link pauses after a board's reply before its next command (:class:`CommandGap`).

``SVS_PROTOCOL.md`` §2: a board discards input for a short time after a reply, a time the page does not give. A
command that got nothing, sent within :data:`HOLD_OFF_SUSPECT_S` of the last reply ("prompt"), may have been
discarded so, and widens the pause; but not where the prompt commands before it at that pause were answered: then
the board takes them, and the silence was something else (a grab it stalled on, a radio's hiccup, §3's ``I`` that
sometimes returns nothing).
"""

from __future__ import annotations

import collections

__all__ = ["HOLD_OFF_STEP_S", "HOLD_OFF_SUSPECT_S", "MAX_COMMAND_GAP_S", "RECENT_PROMPT_COMMANDS", "CommandGap"]

#: A silent reply to a command sent within this long of the board's last reply is taken for its hold-off (§2) ...
HOLD_OFF_SUSPECT_S = 0.1
#: ... and widens the pause before each command to this at least, doubling up to :data:`MAX_COMMAND_GAP_S`.
HOLD_OFF_STEP_S, MAX_COMMAND_GAP_S = 0.05, 0.2
#: The prompt commands remembered at the current pause. A silence among them that were all answered is no hold-off;
#: a second one among them is, as is a first with none answered yet. Why: one grab the right board stalled on (1.2 s,
#: its late reply then drained) widened its pause to 50 ms for good, and each pair's right frame came 50 ms after the
#: left one, guide's pairs a second 16 -> 9 and its warnings 60 ms later for the rest of the walk (an audit); a third
#: such stall in a walk made it 200 ms, near the 0.25 s at which a pair is not ranged.
RECENT_PROMPT_COMMANDS = 20


class CommandGap:
    """The pause before a link's next command, seconds (``gap_s``), starting at ``gap_s`` and widened where a board's
    silences show a hold-off longer than it."""

    def __init__(self, gap_s: float) -> None:
        self.gap_s = gap_s
        self._recent: collections.deque[bool] = collections.deque(maxlen=RECENT_PROMPT_COMMANDS)  # answered or not

    def answered(self, prompt: bool) -> None:
        """A command sent ``prompt``-ly (within :data:`HOLD_OFF_SUSPECT_S` of the last reply) got its reply."""
        if prompt:
            self._recent.append(True)

    def silent(self, prompt: bool) -> bool:
        """A command sent ``prompt``-ly got nothing; whether the pause was widened (then :attr:`gap_s` says to what)."""
        if not prompt or self.gap_s >= MAX_COMMAND_GAP_S:
            return False
        if self._recent and all(self._recent):  # every prompt command before it answered: no hold-off
            self._recent.append(False)
            return False
        self.gap_s = min(max(2 * self.gap_s, HOLD_OFF_STEP_S), MAX_COMMAND_GAP_S)
        self._recent.clear()  # the new pause proves itself afresh
        return True
