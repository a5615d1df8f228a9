"""SQLite session store (embedded default). Placeholder until the sessions work lands."""

from __future__ import annotations

import os
import sqlite3

from service.stores.base import SessionStore


class SqliteStore(SessionStore):
    kind = "sqlite"

    def __init__(self, path: str):
        if path != ":memory:":
            os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
        self.path = path
        self._db = sqlite3.connect(path, check_same_thread=False)

    @classmethod
    def from_url(cls, url: str) -> "SqliteStore":
        return cls(url.removeprefix("sqlite:///") or ":memory:")

    def ping(self) -> None:
        self._db.execute("select 1")

    def close(self) -> None:
        self._db.close()
