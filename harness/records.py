"""Results that survive interruption: one CSV row per finished measurement, and pickled states.

Every experiment appends a row as soon as a measurement is done, and on a rerun skips the
measurements whose key (the values of ``key_columns``) is already in the file, so an
interrupted run loses nothing it computed. Long computations that yield their rows only at
the end (a batch of learning runs) save their state between steps with ``save_pickle``.
"""

from __future__ import annotations

import os
import pickle
from typing import Any

import jax
import pandas as pd


TEXT_COLUMNS = {"scenario": str}
"""Columns read back as text: a content hash such as ``06172e414402`` would otherwise be read as
a number (inf here) and match nothing."""


def read_csv(path: str) -> pd.DataFrame:
    """A results CSV, its ``TEXT_COLUMNS`` as text."""
    return pd.read_csv(path, dtype=TEXT_COLUMNS)


def save_pickle(obj: Any, path: str) -> None:
    """Pickle ``obj`` (its JAX arrays as numpy) to ``path`` atomically: the file, once there, is
    whole, even if the process dies while writing."""
    os.makedirs(os.path.dirname(path) or ".", exist_ok=True)
    with open(path + ".tmp", "wb") as f:
        pickle.dump(jax.device_get(obj), f)
    os.replace(path + ".tmp", path)


def load_pickle(path: str) -> Any:
    """What ``save_pickle`` wrote to ``path``, or None if there is nothing there."""
    if not os.path.exists(path):
        return None
    with open(path, "rb") as f:
        return pickle.load(f)


class ResultTable:
    """The CSV at ``path``, keyed by ``key_columns``. Counts the rows this run found already
    written (``has``) and the ones it wrote (``append``): ``summary()`` says so."""

    def __init__(self, path: str, key_columns: list[str]):
        self.path = path
        self.key_columns = list(key_columns)
        os.makedirs(os.path.dirname(path) or ".", exist_ok=True)
        existing = self.read()
        self._columns = list(existing.columns) if os.path.exists(path) else None
        self._done = {self._key(row) for row in existing.to_dict("records")}
        self.reused = self.computed = 0

    def summary(self) -> str:
        """"computed N cells, reused M from PATH"."""
        return f"computed {self.computed} cells, reused {self.reused} from {self.path}"

    def _key(self, row: dict) -> tuple[str, ...]:
        missing = [c for c in self.key_columns if c not in row]
        if missing:
            raise ValueError(f"row lacks key columns {missing}")
        return tuple(str(row[c]) for c in self.key_columns)

    def read(self) -> pd.DataFrame:
        """Every row so far (an empty frame with the key columns if there is none)."""
        if os.path.exists(self.path):
            return read_csv(self.path)
        return pd.DataFrame(columns=self.key_columns)

    def has(self, key: dict) -> bool:
        """Whether a row with these key values is already written (counted as reused)."""
        found = self._key(key) in self._done
        self.reused += found
        return found

    def append(self, row: dict) -> None:
        """Write one row now (``extend``)."""
        self.extend([row])

    def extend(self, rows: list[dict]) -> None:
        """Write ``rows`` now, in one append (the header with the first rows; later rows in the
        header's column order, whatever the order of their keys). Rows with columns the file lacks
        (written by an older version) add them, empty in the older rows; a row lacking a column of
        the file's or of another row's is an error, and nothing is written."""
        if not rows:
            return
        names = list(dict.fromkeys(name for row in rows for name in row))
        known = self._columns or []
        columns = known + [name for name in names if name not in known]
        if lacking := [row for row in rows if set(columns) - set(row)]:
            raise ValueError(f"row columns {sorted(lacking[0])} lack {sorted(set(columns) - set(lacking[0]))} "
                             f"of {self.path}'s or of the other rows'; write these results to another --out folder")
        if self._columns is not None and columns != self._columns:
            self.read().reindex(columns=columns).to_csv(self.path, index=False)
        self._columns = columns
        text = pd.DataFrame(rows)[self._columns].to_csv(index=False, header=not os.path.exists(self.path))
        with open(self.path, "a") as f:
            f.write(text)
        self._done.update(self._key(row) for row in rows)
        self.computed += len(rows)
