"""What a loader found wrong with its input: counted by reason, with examples.

A loader never drops or changes a row silently. Every problem is one of three
actions:

- ``skipped``: the row was dropped (``missing_field``, ``non_numeric``, ...);
- ``kept``: the row was kept but is suspicious (``unknown_agent_type``: kept
  as ``AgentType.UNKNOWN``);
- ``repaired``: a value was replaced (``start_velocity_from_positions``, ...).

Each reason keeps its count and the first ``MAX_EXAMPLES`` places (file, line,
detail). ``LoadReport`` is the frozen result; ``ReportBuilder`` collects it.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Iterable

MAX_EXAMPLES = 3

SKIPPED = "skipped"
KEPT = "kept"
REPAIRED = "repaired"
ACTIONS = (SKIPPED, KEPT, REPAIRED)


@dataclass(frozen=True, slots=True, kw_only=True)
class ProblemExample:
    """One place where a problem occurred: ``file`` and 1-based ``line`` (0: whole file)."""

    file: str
    line: int
    detail: str

    def __str__(self) -> str:
        where = f"{self.file}:{self.line}" if self.line > 0 else self.file
        return f"{where}: {self.detail}"


@dataclass(frozen=True, slots=True, kw_only=True)
class ProblemCount:
    """How often one reason occurred, what was done about it, and the first examples."""

    reason: str
    action: str
    count: int
    examples: tuple[ProblemExample, ...]


@dataclass(frozen=True, slots=True, kw_only=True)
class LoadReport:
    """Everything a load found wrong, in a stable order (action, then reason).

    ``rows_read`` counts data rows of all track files; ``rows_kept`` those that
    made it into the arrays. ``ignored_files`` lists files beside the tracks
    that the loader did not recognise.
    """

    rows_read: int = 0
    rows_kept: int = 0
    problems: tuple[ProblemCount, ...] = ()
    ignored_files: tuple[str, ...] = ()

    def count(self, reason: str) -> int:
        """Occurrences of ``reason`` (0 when it never occurred)."""
        return sum(p.count for p in self.problems if p.reason == reason)

    def get(self, reason: str) -> ProblemCount | None:
        return next((p for p in self.problems if p.reason == reason), None)

    def by_action(self, action: str) -> tuple[ProblemCount, ...]:
        return tuple(p for p in self.problems if p.action == action)

    @property
    def rows_skipped(self) -> int:
        return sum(p.count for p in self.by_action(SKIPPED))

    @property
    def ok(self) -> bool:
        """True when nothing was skipped, flagged or repaired."""
        return not self.problems

    def merged(self, *others: "LoadReport") -> "LoadReport":
        """This report plus ``others``: counts add up, examples keep the first ones."""
        builder = ReportBuilder()
        for rep in (self, *others):
            builder.add_report(rep)
        return builder.build()

    def as_dict(self) -> dict:
        """For a JSON report: rows read and kept, and per reason its action, count and first example."""
        return {
            "rows_read": self.rows_read,
            "rows_kept": self.rows_kept,
            "problems": {p.reason: {"action": p.action, "count": p.count, "first": str(p.examples[0]) if p.examples else ""} for p in self.problems},
            "ignored_files": list(self.ignored_files),
        }

    def summary(self) -> str:
        """One line: ``rows_read=… rows_kept=… skipped[reason]=n …``."""
        parts = [f"rows_read={self.rows_read}", f"rows_kept={self.rows_kept}"]
        parts += [f"{p.action}[{p.reason}]={p.count}" for p in self.problems]
        if self.ignored_files:
            parts.append(f"ignored_files={len(self.ignored_files)}")
        return " ".join(parts)


@dataclass
class _Entry:
    action: str
    count: int = 0
    examples: list[ProblemExample] = field(default_factory=list)


class ReportBuilder:
    """Mutable collector used while loading; ``build()`` freezes it."""

    def __init__(self) -> None:
        self._entries: dict[str, _Entry] = {}
        self.rows_read = 0
        self.rows_kept = 0
        self._ignored: list[str] = []

    def add(self, reason: str, action: str, file: str, line: int, detail: str, count: int = 1) -> None:
        """Record ``count`` occurrences of ``reason``; the place becomes an example if among the first."""
        if action not in ACTIONS:
            raise ValueError(f"unknown action {action!r}; known: {', '.join(ACTIONS)}")
        entry = self._entries.get(reason)
        if entry is None:
            entry = self._entries[reason] = _Entry(action)
        elif entry.action != action:
            raise ValueError(f"reason {reason!r} recorded as {entry.action} and {action}")
        entry.count += count
        if len(entry.examples) < MAX_EXAMPLES:
            entry.examples.append(ProblemExample(file=file, line=line, detail=detail))

    def skip(self, reason: str, file: str, line: int, detail: str) -> None:
        self.add(reason, SKIPPED, file, line, detail)

    def ignore_file(self, path: str) -> None:
        self._ignored.append(path)

    def add_report(self, report: LoadReport) -> None:
        self.rows_read += report.rows_read
        self.rows_kept += report.rows_kept
        self._ignored.extend(report.ignored_files)
        for p in report.problems:
            entry = self._entries.get(p.reason)
            if entry is None:
                entry = self._entries[p.reason] = _Entry(p.action)
            entry.count += p.count
            room = MAX_EXAMPLES - len(entry.examples)
            entry.examples.extend(p.examples[: max(room, 0)])

    def extend_ignored(self, paths: Iterable[str]) -> None:
        self._ignored.extend(paths)

    def count(self, reason: str) -> int:
        entry = self._entries.get(reason)
        return entry.count if entry else 0

    def build(self) -> LoadReport:
        order = {a: i for i, a in enumerate(ACTIONS)}
        problems = tuple(
            ProblemCount(reason=r, action=e.action, count=e.count, examples=tuple(e.examples))
            for r, e in sorted(self._entries.items(), key=lambda kv: (order[kv[1].action], kv[0]))
            if e.count
        )
        return LoadReport(
            rows_read=self.rows_read, rows_kept=self.rows_kept, problems=problems, ignored_files=tuple(dict.fromkeys(self._ignored))
        )


def report_lines(name: str, report: dict) -> list[str]:
    """For a tool's printed table: what the loader did to recording ``name``'s files (``LoadReport.as_dict()``, as a
    JSON report holds it), one line per reason; nothing when every row was kept as it was."""
    problems, ignored = report.get("problems", {}), report.get("ignored_files", [])
    if not problems and not ignored:
        return []
    skipped = sum(v["count"] for v in problems.values() if v["action"] == SKIPPED)
    lines = [f"{name}: rows read {report['rows_read']}, kept {report['rows_kept']} ({skipped} skipped); what the loader found:"]
    for reason, v in problems.items():
        first = f"  first: {v['first']}" if v.get("first") else ""
        lines.append(f"  {v['action']:<9} {reason:<32} {v['count']:>7d}{first}")
    if ignored:
        lines.append(f"  ignored files: {', '.join(ignored)}")
    return lines
