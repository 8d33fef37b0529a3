"""A step's result, and the commissioning report the shop keeps.

The report is two files of one name: `.json` (every figure, for a later audit or a script comparing two
commissionings) and `.txt` (what the command printed, for a person and a printer). A step that failed, or
could not be checked, keeps the machine from being called commissioned.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any


@dataclass
class Step:
    name: str
    criterion: str
    problems: list[str] = field(default_factory=list)
    fixes: list[str] = field(default_factory=list)
    unchecked: list[str] = field(default_factory=list)
    figures: dict[str, Any] = field(default_factory=dict)

    def fail(self, problem: str, fix: str) -> None:
        self.problems.append(problem)
        self.fixes.append(fix)

    def not_checked(self, why: str) -> None:
        self.unchecked.append(why)

    @property
    def result(self) -> str:
        return "fail" if self.problems else "not checked" if self.unchecked else "pass"

    def as_dict(self) -> dict[str, Any]:
        return {"step": self.name, "result": self.result, "criterion": self.criterion, "problems": self.problems,
                "fixes": self.fixes, "not_checked": self.unchecked, "figures": self.figures}

    def lines(self) -> list[str]:
        out = [f"[{self.result.upper()}] {self.name}: {self.criterion}"]
        out += [f"    problem: {p}\n    fix:     {f}" for p, f in zip(self.problems, self.fixes)]
        out += [f"    not checked: {u}" for u in self.unchecked]
        return out


def default_path(directory: Path, machine: str, date_utc: str) -> Path:
    """`commissioning-<machine>-<UTC date>.json` in the state directory (the `.txt` beside it); a later run the
    same day takes `-2`, `-3`, …: the report is what the shop keeps, and a run after it (a failed one, one that
    could not check the feed hold) must not put itself in its place."""
    stem = f"commissioning-{machine}-{date_utc}"
    n = 1
    while True:
        path = directory / (f"{stem}.json" if n == 1 else f"{stem}-{n}.json")
        if not path.exists() and not path.with_suffix(".txt").exists():
            return path
        n += 1


def write(path: Path, record: dict[str, Any], text: str) -> tuple[Path, Path]:
    """Both files, each written whole (temporary file, renamed): a report is never half a report."""
    json_path = path if path.suffix == ".json" else path.with_name(path.name + ".json")
    text_path = json_path.with_suffix(".txt")
    for target, body in ((json_path, json.dumps(record, indent=2) + "\n"), (text_path, text)):
        tmp = target.with_name(f".{target.name}.{os.getpid()}.tmp")
        try:
            tmp.write_text(body, encoding="utf-8")
            tmp.replace(target)
        except OSError:
            tmp.unlink(missing_ok=True)
            raise
    return json_path, text_path
