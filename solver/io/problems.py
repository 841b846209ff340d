"""Counted, located problems of a recording's ingest.

A recording is read to its end whatever is wrong with parts of it: each problem (a truncated
ASTERIX block, an unknown category or SAC/SIC, a bad value in a table row, a track too short to
reconstruct) is recorded with where it is (byte offset, row, aircraft key) and counted, so
nothing is dropped silently. Problems of the same ``kind`` and ``key`` (e.g. every record of one
unknown SAC/SIC) are merged into one entry that keeps the first location and counts the rest.
"""

from __future__ import annotations

from dataclasses import dataclass, field

MAX_ENTRIES_PER_KIND = 100
"""Distinct entries kept per kind; beyond it only :attr:`Problems.counts` grows."""


@dataclass
class Problem:
    """One problem: ``kind`` (stable name, e.g. ``"truncated_block"``), ``where`` (the first
    location, e.g. ``"byte 1234"``, ``"row 17"``, ``"aircraft mode_s:4CA2D1"``), a message, how
    many times it occurred, how many plots (or records, rows) it cost and how many bytes of the
    input it skipped where that is known and no message says it (blocks of a category not
    decoded)."""

    kind: str
    where: str
    message: str
    count: int = 1
    dropped: int = 0
    key: str | None = None
    skipped_bytes: int = 0

    def __str__(self) -> str:
        more = f" ({self.count} times)" if self.count > 1 else ""
        lost = f"; {self.dropped} dropped" if self.dropped else ""
        skipped = f"; {self.skipped_bytes} bytes skipped" if self.skipped_bytes else ""
        return f"{self.kind} at {self.where}: {self.message}{more}{lost}{skipped}"


@dataclass
class Problems:
    """The problems of one ingest, in order of first occurrence, with exact counts per kind
    (also beyond :data:`MAX_ENTRIES_PER_KIND` entries)."""

    entries: list[Problem] = field(default_factory=list)
    counts: dict[str, int] = field(default_factory=dict)
    dropped: dict[str, int] = field(default_factory=dict)
    _keyed: dict[tuple[str, str], Problem] = field(default_factory=dict, repr=False)
    _per_kind: dict[str, int] = field(default_factory=dict, repr=False)

    def add(self, kind: str, where: str, message: str, *, key: str | None = None,
            dropped: int = 0, skipped_bytes: int = 0) -> None:
        """Record a problem; with ``key``, occurrences of the same ``(kind, key)`` merge into
        the first entry (its ``where`` and ``message`` stay the first occurrence's)."""
        self.counts[kind] = self.counts.get(kind, 0) + 1
        self.dropped[kind] = self.dropped.get(kind, 0) + dropped
        if key is not None and (kind, key) in self._keyed:
            entry = self._keyed[(kind, key)]
            entry.count += 1
            entry.dropped += dropped
            entry.skipped_bytes += skipped_bytes
            return
        if self._per_kind.get(kind, 0) >= MAX_ENTRIES_PER_KIND:
            return
        self._keep(Problem(kind, where, message, 1, dropped, key, skipped_bytes))

    def _keep(self, entry: Problem) -> None:
        self._per_kind[entry.kind] = self._per_kind.get(entry.kind, 0) + 1
        self.entries.append(entry)
        if entry.key is not None:
            self._keyed[(entry.kind, entry.key)] = entry

    def extend(self, other: Problems) -> None:
        """Add the problems of a later part of the same input (counts add up; entries of the
        same kind and key merge into the first)."""
        for e in other.entries:
            first = self._keyed.get((e.kind, e.key)) if e.key is not None else None
            if first is not None:
                first.count += e.count
                first.dropped += e.dropped
                first.skipped_bytes += e.skipped_bytes
            elif self._per_kind.get(e.kind, 0) < MAX_ENTRIES_PER_KIND:
                self._keep(Problem(e.kind, e.where, e.message, e.count, e.dropped, e.key,
                                   e.skipped_bytes))
        for k, n in other.counts.items():
            self.counts[k] = self.counts.get(k, 0) + n
        for k, n in other.dropped.items():
            self.dropped[k] = self.dropped.get(k, 0) + n

    def without(self, kind: str) -> Problems:
        """These problems but those of ``kind``."""
        out = Problems()
        out.extend(Problems([e for e in self.entries if e.kind != kind],
                            {k: n for k, n in self.counts.items() if k != kind},
                            {k: n for k, n in self.dropped.items() if k != kind}))
        return out

    def drain(self) -> Problems:
        """The problems recorded so far, moved to a new collection (this one starts empty)."""
        out = Problems(self.entries, self.counts, self.dropped, self._keyed, self._per_kind)
        self.entries, self.counts, self.dropped = [], {}, {}
        self._keyed, self._per_kind = {}, {}
        return out

    def left_out(self) -> dict[str, int]:
        """Plots (records, rows) left out per kind, where any were: what a run's
        ``summary.json`` and a job's status report as ``dropped`` (damaged stretches of an
        ASTERIX file hold records of no known count: their problems say how many bytes)."""
        return {k: n for k, n in self.dropped.items() if n}

    def of_kind(self, kind: str) -> list[Problem]:
        return [e for e in self.entries if e.kind == kind]

    @property
    def total(self) -> int:
        return sum(self.counts.values())

    def __len__(self) -> int:
        return self.total

    def __bool__(self) -> bool:
        return self.total > 0

    def summary(self) -> str:
        """One line per kind with its count, then every kept entry."""
        lines = [f"{k}: {n}" + (f" ({self.dropped[k]} dropped)" if self.dropped.get(k) else "")
                 for k, n in self.counts.items()]
        return "\n".join(lines + [f"  {e}" for e in self.entries])
