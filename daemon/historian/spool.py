"""The bounded local spool: rows PostgreSQL has not taken yet, kept in order on disk (docs/historian.md).

Append-only segment files `spool-<n>.jsonl` in `spool_dir`, one row a line (`[table, row]`), each append fsynced
(a historian killed mid-outage loses nothing it had spooled). A segment is closed at an eighth of the bound; past
the bound (`spool_max_mb`) the oldest closed segment is dropped whole and its rows counted in `dropped`. Replay
reads the closed segments oldest first and deletes each once PostgreSQL has committed it: a crash between the two
replays it again, which the writer's ON CONFLICT DO NOTHING makes harmless.
"""

from __future__ import annotations

import json
import os
import re
from collections.abc import Iterator
from pathlib import Path
from typing import Any

_SEGMENT = re.compile(r"^spool-(\d{12})\.jsonl\Z")


class SpoolError(OSError):
    pass


class Spool:
    def __init__(self, directory: Path, max_bytes: int) -> None:
        self.directory = Path(directory)
        self.max_bytes = max(int(max_bytes), 4096)
        self.segment_bytes = max(self.max_bytes // 8, 1024)
        self.dropped = 0          # rows dropped past the bound, since start
        self.directory.mkdir(parents=True, exist_ok=True, mode=0o700)
        self._segments: list[tuple[int, Path]] = sorted(
            (int(m[1]), self.directory / name) for name in os.listdir(self.directory) if (m := _SEGMENT.match(name)))
        self._current: Any = None
        self._rows = {path: self._count(path) for _, path in self._segments}   # counted once, then kept

    # ------------------------------------------------------------------ state
    def rows_waiting(self) -> int:
        return sum(self._rows.get(path, 0) for _, path in self._segments)

    def empty(self) -> bool:
        return not self._segments

    def size_bytes(self) -> int:
        return sum(_size(path) for _, path in self._segments)

    # ------------------------------------------------------------------ write
    def append(self, rows: list[tuple[str, list[Any]]]) -> None:
        """Append rows (in order), fsynced; past the bound drop the oldest segments. Raises SpoolError."""
        if not rows:
            return
        data = "".join(json.dumps([t, r], separators=(",", ":"), allow_nan=False) + "\n" for t, r in rows).encode()
        try:
            if self._current is None or self._current.tell() >= self.segment_bytes:
                self._open_next()
            self._current.write(data)
            self._current.flush()
            os.fsync(self._current.fileno())
        except (OSError, ValueError) as exc:
            raise SpoolError(f"spool {self.directory}: {getattr(exc, 'strerror', None) or exc}") from None
        current = self._segments[-1][1]
        self._rows[current] = self._rows.get(current, 0) + len(rows)
        while self.size_bytes() > self.max_bytes and len(self._segments) > 1:
            _, oldest = self._segments.pop(0)
            self.dropped += self._rows.pop(oldest, 0)
            oldest.unlink(missing_ok=True)

    def _open_next(self) -> None:
        self.close()
        n = self._segments[-1][0] + 1 if self._segments else 1
        path = self.directory / f"spool-{n:012d}.jsonl"
        self._current = open(path, "ab")   # noqa: SIM115 - kept open while it is the segment written
        self._segments.append((n, path))
        self._rows[path] = 0

    def close(self) -> None:
        if self._current is not None:
            self._current.close()
            self._current = None

    # ------------------------------------------------------------------ replay
    def segments(self) -> Iterator[tuple[Path, list[tuple[str, list[Any]]]]]:
        """Each segment, oldest first, with its rows (the one being written is closed first). A line cut short
        by a crash mid-write is skipped: everything before it was fsynced whole."""
        self.close()
        for _, path in list(self._segments):
            rows = []
            try:
                lines = path.read_bytes().splitlines()
            except FileNotFoundError:
                continue
            for line in lines:
                try:
                    table, row = json.loads(line)
                except (ValueError, TypeError):
                    continue
                rows.append((table, row))
            yield path, rows

    def done(self, path: Path) -> None:
        """The segment at `path` is in PostgreSQL: delete it."""
        self._segments = [(n, p) for n, p in self._segments if p != path]
        self._rows.pop(path, None)
        path.unlink(missing_ok=True)

    @staticmethod
    def _count(path: Path) -> int:
        try:
            with open(path, "rb") as fh:
                return sum(chunk.count(b"\n") for chunk in iter(lambda: fh.read(1 << 20), b""))
        except FileNotFoundError:
            return 0


def _size(path: Path) -> int:
    try:
        return path.stat().st_size
    except FileNotFoundError:
        return 0
