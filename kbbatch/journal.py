"""A persistent job journal (SQLite in the output folder): what was done, with which settings.

The daemon and the one-shot batch both use it, so a restart (even after kill -9) finishes
interrupted work without redoing what is complete, and a re-run skips up-to-date clips.
"""

from __future__ import annotations

import hashlib
import json
import sqlite3
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

JOURNAL_NAME = ".kbbatch-journal.sqlite"
STATES = ("queued", "running", "done", "failed")


@dataclass(frozen=True)
class Job:
    source: str
    fingerprint: str
    settings: str
    state: str
    output: str | None
    error: str | None
    attempts: int
    seconds: float | None
    updated: float


def source_fingerprint(path: Path) -> str:
    """Size and modification time: a changed photo is a new job."""
    stat = path.stat()
    return f"{stat.st_size}:{stat.st_mtime_ns}"


def settings_fingerprint(*parts: Any) -> str:
    """A short hash of everything that shapes a clip (preset, options, manifest entry)."""
    text = json.dumps(parts, sort_keys=True, default=str)
    return hashlib.sha256(text.encode()).hexdigest()[:16]


class Journal:
    def __init__(self, folder: Path) -> None:
        folder.mkdir(parents=True, exist_ok=True)
        self.path = folder / JOURNAL_NAME
        self.connection = sqlite3.connect(self.path, timeout=30, isolation_level=None)
        self.connection.execute("PRAGMA journal_mode=WAL")
        self.connection.execute("PRAGMA synchronous=FULL")
        self.connection.execute(
            "CREATE TABLE IF NOT EXISTS jobs (source TEXT PRIMARY KEY, fingerprint TEXT NOT NULL,"
            " settings TEXT NOT NULL, state TEXT NOT NULL, output TEXT, error TEXT,"
            " attempts INTEGER NOT NULL DEFAULT 0, seconds REAL, updated REAL NOT NULL)"
        )

    def close(self) -> None:
        self.connection.close()

    def get(self, source: str) -> Job | None:
        row = self.connection.execute("SELECT * FROM jobs WHERE source = ?", (source,)).fetchone()
        return Job(*row) if row else None

    def jobs(self, state: str | None = None) -> list[Job]:
        query, args = "SELECT * FROM jobs", ()
        if state:
            query, args = query + " WHERE state = ?", (state,)
        return [Job(*row) for row in self.connection.execute(query + " ORDER BY source", args)]

    def start(self, source: str, fingerprint: str, settings: str, output: str) -> None:
        attempts = self.connection.execute(
            "SELECT attempts FROM jobs WHERE source = ? AND fingerprint = ?",
            (source, fingerprint)).fetchone()
        self.connection.execute(
            "INSERT OR REPLACE INTO jobs VALUES (?, ?, ?, 'running', ?, NULL, ?, NULL, ?)",
            (source, fingerprint, settings, output, (attempts[0] if attempts else 0) + 1,
             time.time()),
        )

    def finish(self, source: str, state: str, seconds: float, error: str | None = None) -> None:
        self.connection.execute(
            "UPDATE jobs SET state = ?, seconds = ?, error = ?, updated = ? WHERE source = ?",
            (state, seconds, error, time.time(), source),
        )

    def outputs_taken(self) -> dict[str, str]:
        """Clip name -> the source that owns it."""
        rows = self.connection.execute("SELECT output, source FROM jobs WHERE output IS NOT NULL")
        return dict(rows.fetchall())

    def counts(self) -> dict[str, int]:
        rows = self.connection.execute("SELECT state, COUNT(*) FROM jobs GROUP BY state")
        return {state: 0 for state in STATES} | dict(rows.fetchall())

    def is_up_to_date(self, source: str, fingerprint: str, settings: str, output: Path) -> bool:
        job = self.get(source)
        return (job is not None and job.state == "done" and job.fingerprint == fingerprint
                and job.settings == settings and output.is_file())
