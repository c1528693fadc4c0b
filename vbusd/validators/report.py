"""Validation reports: findings filtered, ordered, counted and rendered as text or JSON.

The JSON form follows vbusd/schema/validation-report.schema.json (draft 2020-12) and carries the vbusd
version, counts per severity (of every finding that passed ``--only`` / ``--ignore``, including the
ones cut by ``--max-issues``), and a ``truncated`` flag.
"""

from __future__ import annotations

import textwrap

import json
from dataclasses import dataclass, field
from typing import Optional, Sequence

from vbusd.format import codes as _codes
from vbusd.format.codes import Severity
from vbusd.format.diagnostics import Finding

from vbusd.io.generator import VERSION
__all__ = ["REPORT_FORMAT", "REPORT_VERSION", "Report", "build_report"]

REPORT_FORMAT = "vbusd.validationReport"
REPORT_VERSION = 1


TEXT_WIDTH = 80
"""Default columns of :meth:`Report.to_text`: messages wrap at word boundaries to fit (``vbusd
validate`` passes the terminal's width, or None, no wrapping, when stdout is not a terminal)."""


@dataclass
class Report:
    """The result of validating one asset.

    Attributes:
        asset: The path validated, as given.
        findings: Findings kept, errors first (stable within a severity), at most ``max_issues``.
        counts: Findings per severity after filtering, before truncation.
        truncated: True when ``max_issues`` dropped findings.
        max_issues: The limit applied, or None.
        only: Code filters that selected findings (empty: all).
        ignore: Code filters that dropped findings.
        vbusd_version: Version of the validator.
    """

    asset: str
    findings: list
    counts: dict
    truncated: bool = False
    max_issues: Optional[int] = None
    only: tuple = ()
    ignore: tuple = ()
    vbusd_version: str = field(default_factory=lambda: _version())

    @property
    def error_count(self) -> int:
        """Errors found (before truncation)."""
        return self.counts.get("error", 0)

    @property
    def valid(self) -> bool:
        """True when no error was found (warnings, infos and hints allowed)."""
        return self.error_count == 0

    @property
    def exit_status(self) -> int:
        """1 when there is an error, else 0 (2, unreadable, never reaches a report)."""
        return 1 if self.error_count else 0

    def to_json(self) -> dict:
        """The report as a JSON-ready dict (vbusd/schema/validation-report.schema.json)."""
        return {
            "format": REPORT_FORMAT,
            "reportVersion": REPORT_VERSION,
            "vbusdVersion": self.vbusd_version,
            "asset": self.asset,
            "valid": self.error_count == 0,
            "counts": {s.value: self.counts.get(s.value, 0) for s in Severity},
            "truncated": self.truncated,
            "maxIssues": self.max_issues,
            "only": list(self.only),
            "ignore": list(self.ignore),
            "findings": [f.to_json() for f in self.findings],
        }

    def to_json_text(self) -> str:
        """JSON text, indented, keys in schema order."""
        return json.dumps(self.to_json(), indent=2, allow_nan=False)

    def to_text(self, width: Optional[int] = TEXT_WIDTH) -> str:
        """Human-readable report: a header, findings grouped by severity with locations, a summary.

        Args:
            width: Columns messages wrap at (between words); None: each message on one line.
        """
        lines = [f"vbusd {self.vbusd_version} validate {self.asset}"]
        for severity in Severity:
            group = [f for f in self.findings if f.severity is severity]
            if not group:
                continue
            lines.append("")
            lines.append(f"{severity.value}s ({self.counts.get(severity.value, 0)}):"
                         if severity is not Severity.INFO else f"info ({self.counts.get('info', 0)}):")
            for item in group:
                # Code and location stay whole on their line (they are what CI greps for); the
                # message wraps at 80 columns between words, never inside a path or a number.
                lines.append(f"  {item.code}  {item.location}")
                if width is None:
                    lines.append(" " * 6 + " ".join(item.message.split()))
                    continue
                lines.extend(textwrap.wrap(item.message, width, initial_indent=" " * 6,
                                           subsequent_indent=" " * 6, break_long_words=False,
                                           break_on_hyphens=False) or [" " * 6])
        lines.append("")
        summary = ", ".join(f"{self.counts.get(s.value, 0)} {s.value}{'' if s is Severity.INFO else '(s)'}"
                            for s in Severity)
        if self.truncated:
            summary += f"; only the first {len(self.findings)} shown (--max-issues {self.max_issues})"
        verdict = "INVALID" if self.error_count else "valid"
        lines.append(f"{verdict}: {summary}")
        return "\n".join(lines) + "\n"


def _version() -> str:
    return VERSION


def build_report(asset: str, findings: Sequence[Finding], *, only: Sequence[str] = (),
                 ignore: Sequence[str] = (), max_issues: Optional[int] = None) -> Report:
    """Filter, order, count and truncate findings.

    Args:
        asset: The asset validated.
        findings: Every finding, in check order.
        only: Keep only codes equal to or under these (``texture`` keeps ``texture.*``).
        ignore: Drop codes equal to or under these.
        max_issues: Keep at most this many findings (counts still cover all).

    Returns:
        The :class:`Report`.
    """
    kept = [f for f in findings if (not only or _codes.matches(f.code, only))
            and not _codes.matches(f.code, ignore)]
    kept.sort(key=lambda f: f.severity.rank)  # stable: check order within a severity
    counts = {s.value: 0 for s in Severity}
    for item in kept:
        counts[item.severity.value] += 1
    truncated = max_issues is not None and len(kept) > max_issues
    if truncated:
        kept = kept[:max_issues]
    return Report(asset=str(asset), findings=kept, counts=counts, truncated=truncated,
                  max_issues=max_issues, only=tuple(only), ignore=tuple(ignore))
