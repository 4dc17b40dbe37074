"""Results that survive interruption: one CSV row per finished measurement, and saved states.

Every experiment appends a row as soon as a measurement is done, and on a rerun skips the
measurements whose key (the values of ``key_columns``) is already in the file, so an
interrupted run loses nothing it computed. Long computations that yield their rows only at
the end (a batch of learning runs) save their state between steps with ``save_state``: plain
arrays and JSON in one ``.npz``, never a pickle of the project's classes. Each report's
``{stem}.json`` (``write_metadata``) says, as plain data, what made it.
"""

from __future__ import annotations

import contextlib
import fcntl
import functools
import hashlib
import importlib.metadata
import json
import os
import pickle
import shlex
import subprocess
from collections.abc import Sequence
from typing import Any, NamedTuple

import jax
import numpy as np
import pandas as pd


TEXT_COLUMNS = {"scenario": str, "code_version": str}
"""Columns read back as text: a content hash such as ``06172e414402`` or a commit such as
``1e23456`` would otherwise be read as a number (inf here) and match nothing."""


ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
"""The repository (or installation) root: the folder of the code packages."""
CODE_PACKAGES = ("numerics", "tasks", "models", "estimators", "harness")
"""The folders whose code computes results (pyproject's packages)."""


def source_digest(entries: tuple[str, ...]) -> str:
    """A hash (12 hex digits) of the source files (``.py``, ``.xml``) of ``entries``, packages or
    modules relative to ``ROOT``: their names and bytes, in sorted order."""
    files = []
    for entry in entries:
        path = os.path.join(ROOT, entry)
        if os.path.isdir(path):
            files += [os.path.join(path, name) for name in os.listdir(path) if name.endswith((".py", ".xml"))]
        else:
            files.append(path)
    digest = hashlib.sha256()
    for path in sorted(files):
        digest.update(os.path.relpath(path, ROOT).encode())
        with open(path, "rb") as f:
            digest.update(f.read())
    return digest.hexdigest()[:12]


@functools.cache
def code_version() -> str:
    """The code this process runs, as written into every result row's ``code_version``: the checkout's git commit
    (``a1b2c3d``; ``a1b2c3d-dirty`` when the code packages hold uncommitted changes or new files), or, where the
    code is not a git checkout, ``source a1b2c3d4e5f6``, the ``source_digest`` of the code packages.
    Cached at the first call (``ResultTable`` makes it when an experiment starts): the code a process loaded is
    the code it runs, whatever is committed later."""
    if os.path.exists(os.path.join(ROOT, ".git")):  # a folder, or a file in a git worktree
        try:
            commit = subprocess.run(["git", "-C", ROOT, "rev-parse", "--short", "HEAD"], capture_output=True,
                                    text=True, check=True, timeout=30).stdout.strip()
            changed = subprocess.run(["git", "-C", ROOT, "status", "--porcelain", "--",
                                      *CODE_PACKAGES], capture_output=True, text=True, check=True, timeout=30)
            return commit + ("-dirty" if changed.stdout.strip() else "")
        except (OSError, subprocess.SubprocessError):
            pass
    return "source " + source_digest(CODE_PACKAGES)


def read_csv(path: str) -> pd.DataFrame:
    """A results CSV, its ``TEXT_COLUMNS`` as text; a corrupt one raises a ValueError that names it and
    what is wrong (the file is left as it is)."""
    try:
        return pd.read_csv(path, dtype=TEXT_COLUMNS)
    except (pd.errors.ParserError, pd.errors.EmptyDataError, UnicodeDecodeError) as error:
        raise ValueError(f"{path} is not a readable results CSV ({' '.join(str(error).split())}); it is left as it "
                         "is: repair it, or move it away to start afresh") from None


STATE_SCHEMA_VERSION = 1
"""Version of ``save_state``'s layout."""


def save_state(path: str, arrays: dict[str, Any], meta: dict) -> None:
    """``arrays`` (name -> array) and ``meta`` (JSON-able; stored as the JSON text ``meta`` with its
    ``schema_version``) in one ``.npz`` at ``path``, written atomically: the file, once there, is
    whole, even if the process dies while writing. Read with ``load_state``, or with numpy alone."""
    os.makedirs(os.path.dirname(path) or ".", exist_ok=True)
    text = json.dumps(dict(meta, schema_version=STATE_SCHEMA_VERSION), sort_keys=True)
    with open(path + ".tmp", "wb") as f:
        np.savez(f, meta=np.array(text), **{name: np.asarray(value) for name, value in jax.device_get(arrays).items()})
    os.replace(path + ".tmp", path)


def load_state(path: str) -> tuple[dict[str, np.ndarray], dict] | None:
    """(arrays, meta) as ``save_state`` wrote them at ``path``, or None if there is nothing there."""
    if not os.path.exists(path):
        return None
    with np.load(path, allow_pickle=False) as f:
        arrays = dict(f)
    meta = json.loads(str(arrays.pop("meta")))
    if meta.get("schema_version") != STATE_SCHEMA_VERSION:
        raise ValueError(f"{path}: saved state of schema_version {meta.get('schema_version')!r}, this code reads "
                         f"{STATE_SCHEMA_VERSION}")
    return arrays, meta


METADATA_SCHEMA_VERSION = 1
"""Version of ``write_metadata``'s layout."""
LIBRARIES = ("jax", "jaxlib", "numpy", "mujoco", "mujoco-mjx")
"""The libraries whose versions a report's metadata records (those installed)."""


class Command(NamedTuple):
    """A report's command, ``python -m MODULE ARGV...``: its markdown prints ``text``, its metadata the list."""

    module: str
    argv: list[str]

    @property
    def text(self) -> str:
        return f"python -m {self.module} {shlex.join(self.argv)}"


def library_versions() -> dict[str, str]:
    """``LIBRARIES`` name -> installed version, for those installed."""
    versions = {}
    for name in LIBRARIES:
        with contextlib.suppress(importlib.metadata.PackageNotFoundError):
            versions[name] = importlib.metadata.version(name)
    return versions


OBJECTIVE_DIGITS = 6
"""Significant digits of the J values in a report's metadata: their round-off differs across machines."""


def write_metadata(stem: str, command: Command, scenario: str | None, objective: Sequence[dict]) -> None:
    """``{stem}.json`` beside the report ``{stem}.{csv,md}``, what made it as plain data (``harness.reproduce``
    reads it): ``schema_version``, ``command`` {module, argv}, ``scenario`` (the content hash of the rows
    shown; null where the experiment has none), ``objective`` (the J the report prints: [{model,
    delta_theta, value, ci}], ci the 95 % half-width, to ``OBJECTIVE_DIGITS`` digits), ``code_version`` and
    ``libraries`` (name -> version) of the process that first wrote this content: a rerun that reuses the
    rows and finds the same command, scenario and J leaves the file as it is. Written atomically, sorted keys."""
    content = dict(command=command._asdict(), scenario=scenario,
                   objective=[{name: float(f"{v:.{OBJECTIVE_DIGITS}g}") if name in ("value", "ci") else v
                               for name, v in o.items()} for o in objective])
    path = stem + ".json"
    if os.path.exists(path):
        with contextlib.suppress(ValueError):
            old = read_metadata(path)
            if {name: old[name] for name in content} == json.loads(json.dumps(content)):
                return
    meta = dict(schema_version=METADATA_SCHEMA_VERSION, **content, code_version=code_version(),
                libraries=library_versions())
    with open(path + ".tmp", "w") as f:
        f.write(json.dumps(meta, sort_keys=True, indent=1) + "\n")
    os.replace(path + ".tmp", path)


def read_metadata(path: str) -> dict:
    """The metadata ``write_metadata`` wrote at ``path``; a missing or unreadable file, another
    schema_version or a missing entry raises a one-line ValueError."""
    try:
        with open(path) as f:
            meta = json.load(f)
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as error:
        raise ValueError(f"{path} is not readable report metadata ({' '.join(str(error).split())})") from None
    version = meta.get("schema_version") if isinstance(meta, dict) else None
    if version != METADATA_SCHEMA_VERSION:
        raise ValueError(f"{path}: report metadata of schema_version {version!r}, this code reads "
                         f"{METADATA_SCHEMA_VERSION}")
    if missing := sorted({"command", "scenario", "objective"} - set(meta)):
        raise ValueError(f"{path}: report metadata lacks {', '.join(missing)}")
    return meta


def load_legacy_pickle(path: str) -> Any:
    """A learning checkpoint pickled before checkpoints were plain data (``save_state``), or None. Only
    batches begun before 2026-12-07 have one: delete this reader once reports/learn_checkpoints holds
    no ``.pkl``."""
    if not os.path.exists(path):
        return None
    with open(path, "rb") as f:
        return pickle.load(f)


class ResultTable:
    """The CSV at ``path``, keyed by ``key_columns``. Counts the rows this run found already
    written (``has``) and the ones it wrote (``append``): ``summary()`` says so. Every row it
    writes carries ``code_version`` (unless the row brings its own), which is not part of the key:
    a rerun after a code change reuses the old rows, and this column says which code made them."""

    def __init__(self, path: str, key_columns: list[str]):
        self.path = path
        self.key_columns = list(key_columns)
        os.makedirs(os.path.dirname(path) or ".", exist_ok=True)
        self._done = {self._key(row): row.get("code_version") for row in self.read().to_dict("records")}
        self.reused = self.computed = 0
        self._reused_versions: set[str] = set()
        code_version()  # fixed now, while the code this process loaded is the checkout's

    def summary(self) -> str:
        """"computed N cells, reused M from PATH", and the code that wrote the reused rows where it is not this
        run's (a code change since then may have changed their numbers: delete such rows to recompute them)."""
        text = f"computed {self.computed} cells, reused {self.reused} from {self.path}"
        if others := sorted(self._reused_versions - {code_version()}):
            text += f" (written by code {', '.join(others)}; this run's is {code_version()})"
        return text

    def _key(self, row: dict) -> tuple[str, ...]:
        missing = [c for c in self.key_columns if c not in row]
        if missing:
            raise ValueError(f"row lacks key columns {missing}")
        return tuple(str(row[c]) for c in self.key_columns)

    def _written(self) -> bool:
        """Whether the file holds a header (it may exist empty)."""
        return os.path.exists(self.path) and os.path.getsize(self.path) > 0

    def read(self) -> pd.DataFrame:
        """Every row so far (an empty frame with the key columns if there is none). Needs no lock:
        a rewrite replaces the file whole (``extend``)."""
        return read_csv(self.path) if self._written() else pd.DataFrame(columns=self.key_columns)

    @contextlib.contextmanager
    def _writing(self):
        """One writer at a time, across processes: an exclusive ``flock`` on ``PATH.lock``."""
        with open(self.path + ".lock", "a") as lock:
            fcntl.flock(lock, fcntl.LOCK_EX)
            yield

    def has(self, key: dict) -> bool:
        """Whether a row with these key values is already written (counted as reused)."""
        found = (cell := self._key(key)) in self._done
        if found:
            version = self._done[cell]  # NaN or "" in rows written before the column existed
            self._reused_versions.add(version if isinstance(version, str) and version else "unrecorded")
        self.reused += found
        return found

    def append(self, row: dict) -> None:
        """Write one row now (``extend``)."""
        self.extend([row])

    def extend(self, rows: list[dict]) -> None:
        """Write ``rows`` now, in one append (the header with the first rows; later rows in the
        header's column order, whatever the order of their keys). Rows with columns the file lacks
        (written by an older version) add them, empty in the older rows; a row lacking a column of
        the file's or of another row's is an error, and nothing is written. Writers take turns
        (``_writing``), and read the header at each append, so two processes may append to one
        file. The rewrite that adds a column goes to a temporary file that then replaces the CSV:
        a crash in it loses nothing, and a reader sees the old file or the new one."""
        if not rows:
            return
        rows = [{**row, "code_version": row.get("code_version", code_version())} for row in rows]
        names = list(dict.fromkeys(name for row in rows for name in row))
        with self._writing():
            known = list(pd.read_csv(self.path, nrows=0).columns) if self._written() else []
            columns = known + [name for name in names if name not in known]
            if lacking := [row for row in rows if set(columns) - set(row)]:
                raise ValueError(f"row columns {sorted(lacking[0])} lack {sorted(set(columns) - set(lacking[0]))} "
                                 f"of {self.path}'s or of the other rows'; write these results to another --out "
                                 "folder")
            if known and columns != known:
                self.read().reindex(columns=columns).to_csv(self.path + ".tmp", index=False)
                os.replace(self.path + ".tmp", self.path)
            with open(self.path, "a") as f:
                f.write(pd.DataFrame(rows)[columns].to_csv(index=False, header=not known))
        self._done.update((self._key(row), row["code_version"]) for row in rows)
        self.computed += len(rows)
