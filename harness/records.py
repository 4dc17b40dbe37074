"""Result tables that survive interruption: one CSV row per finished measurement.

Every experiment appends a row as soon as a measurement is done, and on a rerun skips the
measurements whose key (the values of ``key_columns``) is already in the file, so an
interrupted run loses nothing it computed.
"""

from __future__ import annotations

import os

import pandas as pd


class ResultTable:
    """The CSV at ``path``, keyed by ``key_columns``."""

    def __init__(self, path: str, key_columns: list[str]):
        self.path = path
        self.key_columns = list(key_columns)
        os.makedirs(os.path.dirname(path) or ".", exist_ok=True)
        self._done = {self._key(row) for row in self.read().to_dict("records")}

    def _key(self, row: dict) -> tuple[str, ...]:
        missing = [c for c in self.key_columns if c not in row]
        if missing:
            raise ValueError(f"row lacks key columns {missing}")
        return tuple(str(row[c]) for c in self.key_columns)

    def read(self) -> pd.DataFrame:
        """Every row so far (an empty frame with the key columns if there is none)."""
        if os.path.exists(self.path):
            return pd.read_csv(self.path)
        return pd.DataFrame(columns=self.key_columns)

    def has(self, key: dict) -> bool:
        """Whether a row with these key values is already written."""
        return self._key(key) in self._done

    def append(self, row: dict) -> None:
        """Write one row now (the header with the first row)."""
        pd.DataFrame([row]).to_csv(self.path, mode="a", header=not os.path.exists(self.path), index=False)
        self._done.add(self._key(row))
