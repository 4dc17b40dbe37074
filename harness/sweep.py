"""Learning tables from a plan file, split into units that any number of workers run.

    python -m harness.sweep --plan plans/paper_tables.toml [--workers N] [--engine local|ray]
    python -m harness.sweep --plan plans/paper_tables.toml --status

A plan (TOML, ``schema_version = 1``) holds ``[settings]``, the ``harness.learn`` flags every
cell shares, and a list of ``[[cells]]`` in priority order, each a (task, cost, noise_k) with a
table ``repeats = {method = R, ...}`` and optionally its own ``out`` (e.g. readings beside a
table) or other ``harness.learn`` flags. A cell listed twice with more repeats (first 5, later
10) runs its first repeats before anything listed between the two.

The plan splits into units: (cell, method, batch of ``batch`` repeats), each one
``harness.learn.run_experiments`` call. A unit saves its state after every trial in the plan's
checkpoint folder and resumes from it; a lock file beside the checkpoint marks it running, so
two sweeps (or one restarted beside another) never run the same unit. A unit returns its rows
to the sweep, which appends those not yet in the cell's CSV (``harness.learn``'s file and key),
deletes the unit's checkpoint and regenerates the cell's report (and, writing to the repository's reports/,
the claims table: ``harness.summary``): one CSV per cell, no row written twice, nothing finished lost by a kill. ``local`` runs units on a process pool (one XLA
thread each); ``ray`` hands them to a Ray cluster (``pip install -e ".[ray]"``: the cluster that
``RAY_ADDRESS`` names, else a new local one), one CPU per unit, so a cluster of any size stays
busy. Seeds depend only on the cell, method and repeat: both engines give the same rows.
"""

from __future__ import annotations

import concurrent.futures
import contextlib
import dataclasses
import fcntl
import functools
import multiprocessing
import os
import sys
import time
import tomllib

from harness.cli import parse, run_command

ENGINES = ("local", "ray")
PLAN_SCHEMA_VERSION = 1
SINGLE_THREAD_XLA = "--xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1"
"""Several JAX processes on the same cores: one XLA thread each (LAPACK's OpenMP threads would
otherwise spin against each other: a 200 x 200 Cholesky took 250 ms instead of 0.3 ms)."""


@dataclasses.dataclass(frozen=True)
class Args:
    """Run (or report on) the learning tables of a plan file."""

    plan: str = "plans/paper_tables.toml"
    """The plan file (TOML): [settings] and [[cells]] in priority order."""
    status: bool = False
    """Print every unit (done, running, partial, left) with hours spent and left, and exit."""
    workers: int = 0
    """Units run at once by the local engine (0: one per core; 1: in this process)."""
    engine: str = "local"
    """local (process pool) or ray."""
    max_units: int = 0
    """Stop after starting this many units (0: every unit left)."""

    def __post_init__(self):
        if self.engine not in ENGINES:
            raise ValueError(f"unknown engine {self.engine!r}; valid engines: {list(ENGINES)}")
        if self.workers < 0 or self.max_units < 0:
            raise ValueError("workers and max-units must be >= 0")


@dataclasses.dataclass(frozen=True)
class Unit:
    """One method's batch of repeats of one cell: ``harness.learn`` flags (``argv``), the
    method, and the repeats ``first..last`` (inclusive)."""

    argv: tuple[str, ...]
    method: str
    first: int
    last: int

    def learn_args(self):
        """The unit's ``harness.learn.Args`` (parsed once per unit and process)."""
        return _learn_args(self.argv, self.method, self.last)

    @property
    def repeats(self) -> list[int]:
        return list(range(self.first, self.last + 1))

    def describe(self) -> str:
        args = self.learn_args()
        return f"{os.path.basename(args.stem)} {self.method} repeats {self.first}-{self.last}"

    def checkpoint(self) -> str:
        from harness import learn

        return learn.checkpoint_path(self.learn_args(), self.method, self.repeats)


@functools.cache
def _learn_args(argv: tuple[str, ...], method: str, last: int):
    from harness import learn

    return learn.parse(learn.Args, list(argv) + ["--methods", method, "--repeats", str(last + 1)])


def flag(name: str, value) -> list[str]:
    """``harness.learn``'s flag for a plan entry: ``rollout_float32 = true`` -> ``--rollout-float32``."""
    option = "--" + name.replace("_", "-")
    if isinstance(value, bool):
        return [option if value else "--no-" + option[2:]]
    return [option, str(value)]


def load_plan(path: str) -> list[Unit]:
    """The plan's units in priority order, each once (``load_plan`` checks every flag and method
    by building its ``harness.learn.Args``)."""
    if not os.path.exists(path):
        raise ValueError(f"no plan file {path!r} (plans/ holds the project's plans)")
    with open(path, "rb") as f:
        try:
            plan = tomllib.load(f)
        except tomllib.TOMLDecodeError as error:
            raise ValueError(f"plan {path} is not valid TOML: {error}") from None
    if plan.get("schema_version") != PLAN_SCHEMA_VERSION:
        raise ValueError(f"plan {path}: schema_version must be {PLAN_SCHEMA_VERSION}, got {plan.get('schema_version')!r}")
    settings = plan.get("settings", {})
    if "batch" not in settings:
        raise ValueError(f"plan {path}: [settings] must give batch (repeats per unit)")
    units: list[Unit] = []
    for index, cell in enumerate(plan.get("cells", [])):
        options = {**settings, **{k: v for k, v in cell.items() if k != "repeats"}}
        if not isinstance(cell.get("repeats"), dict) or not cell["repeats"]:
            raise ValueError(f"plan {path}: cell {index} needs repeats = {{method = R, ...}}")
        argv = tuple(a for name, value in options.items() for a in flag(name, value))
        batch = int(options["batch"])
        for method, count in cell["repeats"].items():
            for first in range(0, int(count), batch):
                unit = Unit(argv, method, first, min(first + batch, int(count)) - 1)
                unit.learn_args()  # fails on an unknown method, task, flag or value
                if unit not in units:
                    units.append(unit)
    return units


def rows_written(unit: Unit):
    """The unit's rows already in its cell's CSV (``harness.learn.current_rows``), or None."""
    from harness import learn
    from harness.records import ResultTable

    args = unit.learn_args()
    if not os.path.exists(args.stem + ".csv"):
        return None
    rows = learn.current_rows(args, ResultTable(args.stem + ".csv", learn.KEY_COLUMNS))
    return rows[(rows.method == unit.method) & rows.repeat.isin(unit.repeats)]


def covers(rows, unit: Unit) -> bool:
    """Whether ``rows`` (a unit's ``rows_written``, or None) hold every repeat of the unit."""
    return rows is not None and set(rows.repeat) >= set(unit.repeats)


def is_done(unit: Unit) -> bool:
    return covers(rows_written(unit), unit)


@contextlib.contextmanager
def unit_lock(unit: Unit):
    """Hold the unit's lock (``CHECKPOINT.lock``) while it runs; yields False (and runs nothing)
    when another process holds it."""
    path = unit.checkpoint() + ".lock"
    os.makedirs(os.path.dirname(path), exist_ok=True)
    with open(path, "a") as handle:
        try:
            fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            yield False
            return
        try:
            yield True
        finally:
            fcntl.flock(handle, fcntl.LOCK_UN)


def is_running(unit: Unit) -> bool:
    """Whether another process holds the unit's lock (``unit_lock``)."""
    if not os.path.exists(unit.checkpoint() + ".lock"):
        return False
    with unit_lock(unit) as mine:
        return not mine


def run_unit(unit: Unit) -> list[dict] | None:
    """Run one unit in this process (resuming from its checkpoint) and return its rows with
    their keys; None if another process holds its lock."""
    import jax

    from harness import learn

    args = unit.learn_args()
    jax.config.update("jax_enable_x64", args.x64)
    jax.config.update("jax_cpu_enable_async_dispatch", False)  # harness.learn.main: jax-ml/jax#25861
    with unit_lock(unit) as mine:
        if not mine:
            return None
        print(f"start: {unit.describe()}", file=sys.stderr, flush=True)
        rows = learn.run_experiments(args, unit.method, unit.repeats)
    task = args.make_task()
    return [{**learn.row_key(args, task, unit.method, row["repeat"]), **row} for row in rows]


def merge(unit: Unit, rows: list[dict]) -> int:
    """Append the unit's rows whose (method, repeat) the cell's CSV lacks, delete the unit's
    checkpoint and regenerate the cell's report; returns the rows written."""
    from harness import learn, learn_report, summary
    from harness.records import ROOT, ResultTable

    args = unit.learn_args()
    table = ResultTable(args.stem + ".csv", learn.KEY_COLUMNS)
    new = [row for row in rows if not table.has(row)]
    table.extend(new)
    learn.remove_checkpoint(unit.checkpoint())
    learn_report.write(learn.current_rows(args, table), args.stem,
                       f"python -m harness.sweep (units of harness.learn {' '.join(unit.argv)})")
    if os.path.realpath(os.path.dirname(args.stem)) == os.path.realpath(os.path.join(ROOT, "reports")):
        summary.main([])  # the claims table (reports/SUMMARY.md, the README's) follows the repository's CSVs
    return len(new)


def worker_init() -> None:
    """A local worker: one XLA thread (``SINGLE_THREAD_XLA``) before JAX starts."""
    os.environ["XLA_FLAGS"] = (os.environ.get("XLA_FLAGS", "") + " " + SINGLE_THREAD_XLA).strip()
    os.environ.setdefault("OMP_NUM_THREADS", "1")


def unit_progress(unit: Unit) -> tuple[int, float]:
    """(trials done, seconds spent) of a unit's checkpoint, or (0, 0) without one."""
    from harness import learn

    saved = learn.load_checkpoint(unit.checkpoint(), unit.learn_args().make_task())
    if saved["state"] is None:
        return 0, 0.0
    return int(saved["state"].trials_done), float(max((r["seconds"] for r in saved["rows"]), default=0.0))


def status_lines(units: list[Unit]) -> list[str]:
    """A line per unit (state, trials, hours) and a total with the hours left: a unit left is
    estimated at the median hours of the finished units of its task (of all, if none)."""
    import numpy as np

    lines, hours_done, done_by_task, pending = [], 0.0, {}, []
    for unit in units:
        args = unit.learn_args()
        total = args.make_task().num_random_trials + args.settings["learned_trials"]
        rows = rows_written(unit)
        if covers(rows, unit):
            hours = float(rows.groupby("repeat").seconds.max().max()) / 3600
            hours_done += hours
            done_by_task.setdefault(args.task, []).append(hours)
            lines.append(f"done     {unit.describe()}: {hours:.2f} h")
            continue
        trials, seconds = unit_progress(unit)
        state = "running" if is_running(unit) else ("partial" if trials else "left")
        hours_done += seconds / 3600
        pending.append((args.task, 1.0 - trials / total, seconds / 3600))
        lines.append(f"{state:8s} {unit.describe()}: trial {trials}/{total}, {seconds / 3600:.2f} h")
    everything = [h for hs in done_by_task.values() for h in hs]
    left = 0.0
    for task, fraction, _ in pending:
        known = done_by_task.get(task) or everything
        left += fraction * float(np.median(known)) if known else np.nan
    finished = sum(line.startswith("done") for line in lines)
    estimate = "unknown (no finished unit yet)" if np.isnan(left) else f"about {left:.1f} h of one core"
    return lines + [f"{finished} of {len(units)} units done; {hours_done:.1f} h spent; left: {estimate}"]


def run_local(units: list[Unit], workers: int) -> None:
    """``workers`` spawned processes, or this process itself for one worker."""
    if workers == 1:
        for unit in units:
            report(unit, run_unit(unit))
        return
    context = multiprocessing.get_context("spawn")
    with concurrent.futures.ProcessPoolExecutor(workers, mp_context=context, initializer=worker_init) as pool:
        futures = {pool.submit(run_unit, unit): unit for unit in units}
        for future in concurrent.futures.as_completed(futures):
            report(futures[future], future.result())


def run_ray(units: list[Unit]) -> None:
    import ray  # optional extra: pip install -e ".[ray]"

    if not ray.is_initialized():
        ray.init()  # the cluster at RAY_ADDRESS, if set; else a new local one
    remote = ray.remote(num_cpus=1, runtime_env={"env_vars": {"XLA_FLAGS": SINGLE_THREAD_XLA}})(run_unit)
    pending = {remote.remote(unit): unit for unit in units}
    while pending:
        [ready], _ = ray.wait(list(pending), num_returns=1)
        report(pending.pop(ready), ray.get(ready))


def report(unit: Unit, rows: list[dict] | None) -> None:
    if rows is None:
        print(f"skipped (running elsewhere): {unit.describe()}", file=sys.stderr, flush=True)
        return
    written = merge(unit, rows)
    print(f"done: {unit.describe()} ({written} rows appended)", file=sys.stderr, flush=True)


def main(argv=None) -> None:
    args = parse(Args, argv)
    if args.engine == "local" and "jax" not in sys.modules:
        # before anything loads JAX or SciPy's LAPACK (load_plan imports harness.learn): one thread each, for the
        # units this process runs itself and for the spawned workers (which inherit the environment)
        worker_init()
    units = load_plan(args.plan)
    if args.status:
        print("\n".join(status_lines(units)))
        return
    left = [unit for unit in units if not is_done(unit) and not is_running(unit)]
    if args.max_units:
        left = left[:args.max_units]
    print(f"{args.plan}: {len(units)} units, {len(left)} to run", file=sys.stderr, flush=True)
    start = time.perf_counter()
    if args.engine == "ray":
        run_ray(left)
    else:
        run_local(left, args.workers or min(len(left), os.cpu_count() or 1) or 1)
    print(f"sweep finished in {(time.perf_counter() - start) / 3600:.2f} h", file=sys.stderr, flush=True)


if __name__ == "__main__":
    run_command(main)
