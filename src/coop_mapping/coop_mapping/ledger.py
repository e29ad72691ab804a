"""Which map contributions a map has fused, per source: fuse each once, count what is missing
(no rclpy).

Every contribution a rover sends carries its sender's session (the node's start time, ns: a
restarted node is a new session) and a sequence number 1, 2, ... within the session. A link
that drops out and comes back, a durable writer that sends its history again to a mapper that
rejoins, or a mapper restarted from its saved map can all deliver a contribution twice or out
of order. The ledger says, per (source, session, sequence), whether it is new; it keeps the
highest sequence below which everything has come and the few above it that came early, so it
stays small, and it is saved with the map (`VoxelMap.save`), so a restart fuses nothing twice.
"""
from __future__ import annotations

import enum
from dataclasses import dataclass, field
from typing import Any

__all__ = ['Admission', 'ContributionLedger', 'SourceRecord']


class Admission(enum.Enum):
    """What a map does with a contribution."""

    NEW = 'new'                        # fuse it
    DUPLICATE = 'duplicate'            # fused before: skip
    OLD_SESSION = 'old_session'        # from a session the source has left: skip
    BAD_SEQUENCE = 'bad_sequence'      # sequence 0 or session 0: skip


@dataclass
class SourceRecord:
    """One source's state in the ledger."""

    session: int = 0
    contiguous: int = 0                 # every sequence 1..contiguous has been fused
    early: set[int] = field(default_factory=set)  # fused sequences above contiguous + 1
    fused: int = 0                      # in this session
    sessions: int = 0                   # sessions seen (restarts + 1)

    @property
    def highest(self) -> int:
        return max(self.early, default=self.contiguous)

    @property
    def missing(self) -> int:
        """Sequences below the highest fused one that have not come (yet)."""
        return self.highest - self.contiguous - len(self.early)


class ContributionLedger:
    """Per source: the session and the sequences fused (see the module docstring)."""

    def __init__(self) -> None:
        self.sources: dict[str, SourceRecord] = {}

    def admit(self, source: str, session: int, sequence: int) -> Admission:
        """Whether (session, sequence) of `source` is new; if it is, it is recorded as fused
        (call it when the contribution is about to be fused). A session later than the
        source's current one starts it afresh; an earlier one is refused."""
        if session <= 0 or sequence <= 0:
            return Admission.BAD_SEQUENCE
        rec = self.sources.get(source)
        if rec is None or session > rec.session:
            sessions = rec.sessions if rec else 0
            rec = self.sources[source] = SourceRecord(session=session, sessions=sessions + 1)
        elif session < rec.session:
            return Admission.OLD_SESSION
        if sequence <= rec.contiguous or sequence in rec.early:
            return Admission.DUPLICATE
        rec.early.add(sequence)
        while rec.contiguous + 1 in rec.early:
            rec.contiguous += 1
            rec.early.remove(rec.contiguous)
        rec.fused += 1
        return Admission.NEW

    def missing(self, source: str | None = None) -> int:
        """Contributions of the current sessions below the highest fused that have not come:
        of one source, or of all."""
        recs = self.sources.values() if source is None else \
            [self.sources[source]] if source in self.sources else []
        return sum(r.missing for r in recs)

    def to_json(self) -> dict[str, Any]:
        return {s: {'session': r.session, 'contiguous': r.contiguous, 'early': sorted(r.early),
                    'fused': r.fused, 'sessions': r.sessions}
                for s, r in self.sources.items()}

    @classmethod
    def from_json(cls, d: dict[str, Any]) -> ContributionLedger:
        """The inverse of to_json; ValueError / TypeError / KeyError on a malformed one."""
        out = cls()
        for s, r in d.items():
            rec = SourceRecord(session=int(r['session']), contiguous=int(r['contiguous']),
                               early={int(x) for x in r['early']}, fused=int(r['fused']),
                               sessions=int(r['sessions']))
            if rec.session <= 0 or rec.contiguous < 0 or any(x <= rec.contiguous + 1
                                                             for x in rec.early):
                raise ValueError(f'ledger entry of {s!r} is inconsistent')
            out.sources[str(s)] = rec
        return out

    def copy(self) -> ContributionLedger:
        return ContributionLedger.from_json(self.to_json())
