"""A durable result store for studies: SQLite in WAL mode, one row per finished case.

Rows are keyed by study, case id and a hash of the study's settings; each is committed as soon as
its case finishes, so a study killed half-way keeps what it finished and a re-run skips it. A
store is tied to one settings hash per study: opening it with other settings is refused (use
another folder, or ``force`` to start the study afresh).
"""

from __future__ import annotations

import hashlib
import json
import os
import sqlite3
from collections.abc import Sequence
from pathlib import Path

__all__ = ["ResultStore", "StoreMismatch", "settings_hash"]

_SCHEMA = """
CREATE TABLE IF NOT EXISTS studies (
    study TEXT PRIMARY KEY, settings_hash TEXT NOT NULL, settings TEXT NOT NULL);
CREATE TABLE IF NOT EXISTS cases (
    study TEXT NOT NULL, case_id TEXT NOT NULL, settings_hash TEXT NOT NULL,
    result TEXT NOT NULL, seconds REAL NOT NULL,
    finished TEXT NOT NULL DEFAULT (datetime('now')),
    PRIMARY KEY (study, case_id, settings_hash));
"""


class StoreMismatch(ValueError):
    """The store holds this study with other settings."""


def settings_hash(settings: dict) -> str:
    """SHA-256 (16 hex digits) of the settings as canonical JSON."""
    text = json.dumps(settings, sort_keys=True, default=str, separators=(",", ":"))
    return hashlib.sha256(text.encode()).hexdigest()[:16]


class ResultStore:
    """The finished cases of one study in ``path`` (created).

    Parameters
    ----------
    path : path
        The SQLite file.
    study : str
    settings : dict
        JSON-serialisable; their hash keys every row.
    force : bool
        Drop what the store holds for this study under other settings instead of refusing.

    Raises
    ------
    StoreMismatch
        The store holds this study with other settings and ``force`` is not set.
    """

    def __init__(self, path: str | os.PathLike, study: str, settings: dict, *, force: bool = False):
        self.path = Path(path)
        self.study = study
        self.hash = settings_hash(settings)
        self._db = sqlite3.connect(self.path, timeout=30)
        self._db.execute("PRAGMA journal_mode=WAL")
        self._db.execute("PRAGMA synchronous=NORMAL")
        self._db.executescript(_SCHEMA)
        row = self._db.execute(
            "SELECT settings_hash, settings FROM studies WHERE study = ?", (study,)
        ).fetchone()
        if row is not None and row[0] != self.hash:
            if not force:
                self._db.close()
                raise StoreMismatch(
                    f"{self.path}: this folder holds study '{study}' run with other settings "
                    f"({row[1][:200]}); use another folder, or --force to start it afresh"
                )
            with self._db:
                self._db.execute("DELETE FROM cases WHERE study = ?", (study,))
                self._db.execute("DELETE FROM studies WHERE study = ?", (study,))
        with self._db:
            self._db.execute(
                "INSERT OR IGNORE INTO studies (study, settings_hash, settings) VALUES (?, ?, ?)",
                (study, self.hash, json.dumps(settings, sort_keys=True, default=str)),
            )

    def done(self) -> set[str]:
        """Case ids already stored."""
        rows = self._db.execute(
            "SELECT case_id FROM cases WHERE study = ? AND settings_hash = ?",
            (self.study, self.hash),
        )
        return {r[0] for r in rows}

    def put(self, case_id: str, result, seconds: float) -> bool:
        """Store one finished case (committed at once); False if it was already there."""
        with self._db:
            cur = self._db.execute(
                "INSERT OR IGNORE INTO cases (study, case_id, settings_hash, result, seconds) "
                "VALUES (?, ?, ?, ?, ?)",
                (self.study, case_id, self.hash, json.dumps(result, default=_json), seconds),
            )
        return cur.rowcount == 1

    def results(self, order: Sequence[str] | None = None) -> list[tuple[str, object, float]]:
        """``(case_id, result, seconds)`` of every stored case, in ``order`` when given."""
        rows = self._db.execute(
            "SELECT case_id, result, seconds FROM cases WHERE study = ? AND settings_hash = ?",
            (self.study, self.hash),
        ).fetchall()
        found = {cid: (cid, json.loads(r), s) for cid, r, s in rows}
        if order is None:
            return sorted(found.values())
        return [found[c] for c in order if c in found]

    def count(self) -> int:
        return len(self.done())

    def close(self) -> None:
        self._db.close()

    def __enter__(self) -> ResultStore:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def _json(x):
    """numpy scalars and arrays in results."""
    import numpy as np

    if isinstance(x, np.generic):
        return x.item()
    if isinstance(x, np.ndarray):
        return x.tolist()
    raise TypeError(f"not JSON serialisable: {type(x).__name__}")
