"""The paper's whole learning grid in one command (PIPPS, the success-rate tables).

    python -m harness.sweep --repeats R [--preset quick|quick_p50|paper] [--workers N] [--engine local|ray]
        [--cells all|0,3,...] [--learn-args "--particles 50 ..."]

Cells: the cart-pole with the angle cost at k in {0.01, 1, 4, 9, 16} and the tip cost at
k in {0.01, 1}, and the unicycle (k = 1); each cell is one ``harness.learn`` run over every
method, writing its own CSV, so cells run in parallel without sharing a file. ``local`` uses a
process pool over this machine's cores (``workers`` processes, default one per core); ``ray`` hands the same cells to
a Ray cluster (``pip install -e ".[ray]"``): the one already initialised in this process, else
the one that ``RAY_ADDRESS`` names (``RAY_ADDRESS=<head-ip>:6379``, or ``auto`` on a node of
the cluster), else a new local one. Seeds depend only on the cell, the method and
the repeat, so both engines give the same results. Each cell resumes like ``harness.learn``.
"""

from __future__ import annotations

import concurrent.futures
import dataclasses
import multiprocessing
import os
import sys

from harness.cli import parse
from harness.learn import DEFAULT_METHODS

CELLS = [("cartpole", "angle", k) for k in (0.01, 1.0, 4.0, 9.0, 16.0)] + [
    ("cartpole", "tip", k) for k in (0.01, 1.0)] + [("unicycle", "", 1.0)]
ENGINES = ("local", "ray")
UNICYCLE_METHODS = ("pilco", "rp", "rp_fs", "gr", "gr_fs", "lr", "tp")
"""The paper's unicycle columns."""


@dataclasses.dataclass(frozen=True)
class Args:
    """The paper's learning grid, every cell with every method."""

    repeats: int = 10
    """Learning runs per method in every cell."""
    preset: str = "quick"
    """harness.learn settings preset of every cell."""
    methods: str = DEFAULT_METHODS
    """Comma-separated methods (the unicycle cell keeps the paper's columns)."""
    cells: str = "all"
    """all, or comma-separated indices into sweep.CELLS."""
    workers: int = 0
    """Cells run at once by the local engine (0: one per core)."""
    engine: str = "local"
    """local (process pool) or ray."""
    seed: int = 0
    """Seed of repeat 0 in every cell."""
    out: str = "reports"
    """Folder of every cell's CSV and report."""
    learn_args: str = ""
    """Extra harness.learn flags for every cell, as one string."""

    def __post_init__(self):
        if self.engine not in ENGINES:
            raise ValueError(f"unknown engine {self.engine!r}; valid engines: {list(ENGINES)}")
        self.chosen_cells()  # fails on a bad cell index

    def chosen_cells(self) -> list[tuple[str, str, float]]:
        """``cells``: "all" or comma-separated indices into CELLS."""
        if self.cells == "all":
            return CELLS
        try:
            return [CELLS[int(i)] for i in self.cells.split(",")]
        except (ValueError, IndexError):
            raise ValueError(f"cells must be 'all' or indices 0-{len(CELLS) - 1}, got {self.cells!r}") from None

    def learn_argv(self, cell: tuple[str, str, float]) -> list[str]:
        task, cost, k = cell
        methods = self.methods if task == "cartpole" else ",".join(
            m for m in self.methods.split(",") if m in UNICYCLE_METHODS)
        argv = ["--task", task, "--noise-k", str(k), "--methods", methods, "--repeats", str(self.repeats),
                "--preset", self.preset, "--seed", str(self.seed), "--out", self.out]
        return argv + (["--cost", cost] if cost else []) + self.learn_args.split()


def run_cell(argv: list[str]) -> str:
    """One cell in this process: ``harness.learn`` with ``argv``; returns its description."""
    from harness import learn

    learn.main(argv)
    return " ".join(argv)


def main(argv=None) -> None:
    args = parse(Args, argv)
    jobs = [args.learn_argv(cell) for cell in args.chosen_cells()]
    if args.engine == "ray":
        import ray  # optional extra: pip install -e ".[ray]"

        if not ray.is_initialized():
            ray.init()  # the cluster at RAY_ADDRESS, if set; else a new local one
        remote = ray.remote(run_cell)
        for done in ray.get([remote.remote(job) for job in jobs]):
            print(f"done: {done}", file=sys.stderr, flush=True)
        return
    workers = args.workers or min(len(jobs), os.cpu_count() or 1)
    # Several JAX processes on the same cores: LAPACK's OpenMP threads then spin against each
    # other (measured: a 200 x 200 Cholesky takes 250 ms instead of 0.3 ms). One thread each.
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    with concurrent.futures.ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context("spawn")) as pool:
        for done in pool.map(run_cell, jobs):
            print(f"done: {done}", file=sys.stderr, flush=True)


if __name__ == "__main__":
    main()
