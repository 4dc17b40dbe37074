"""The method catalogue: every name a learning CSV can hold, with what it runs and how it is judged.

A method is an estimator (``estimators.REGISTRY``) with problem overrides, an optimiser (PILCO's
L-BFGS on its deterministic objective, or the paper's SGD), and how its noise is fixed. Beside
the paper's columns the catalogue holds readings (another reading of one of the paper's
conventions: run into their own CSV and judged at the table's cut, ``harness.success``) and
invalid names (rows kept for the record that measure no method of the paper). A new estimator
becomes a learning method with one entry in ``METHODS``.

Decode a name once per run with ``method(name)``; it fails with the valid names.
"""

from __future__ import annotations

import dataclasses

import numpy as np


@dataclasses.dataclass(frozen=True)
class Method:
    """One learning method.

    estimator: its ``estimators.REGISTRY`` name; override_pairs: ``estimators.base.Problem`` fields
    it changes, as (name, value) pairs (``overrides`` as a dict); reads: the paper's method that this one reads otherwise
    (a reading), or ""; noise_fixed_per_run: the fixed-noise estimators keep one optimisation key
    for the whole run instead of one per trial; quasi_newton: a fixed-noise estimator optimised by
    L-BFGS with a line search on its fixed-noise objective (the paper's "Deterministic optimizer",
    ``harness.episodic.fixed_noise_lbfgs_optimiser``) instead of the paper's SGD; invalid: why rows of this name measure no method of
    the paper ("" for a valid method; an invalid name cannot be run)."""

    estimator: str
    override_pairs: tuple[tuple[str, float], ...] = ()
    reads: str = ""
    noise_fixed_per_run: bool = False
    quasi_newton: bool = False
    invalid: str = ""

    @property
    def overrides(self) -> dict[str, float]:
        """The ``estimators.base.Problem`` fields it changes, as keyword arguments."""
        return dict(self.override_pairs)

    @property
    def optimiser(self) -> str:
        """"lbfgs" (PILCO's deterministic objective), "lbfgs_fixed_noise" (``quasi_newton``) or
        "pipps_sgd" (the paper's optimiser)."""
        if self.estimator == "pilco":
            return "lbfgs"
        return "lbfgs_fixed_noise" if self.quasi_newton else "pipps_sgd"

    def steps(self, settings: dict) -> int:
        """Its optimiser's budget per trial in a learning preset's ``settings``: PILCO's
        ``pilco_steps`` L-BFGS steps, else ``optimiser_steps`` (SGD steps, or evaluations of the
        fixed-noise objective under L-BFGS)."""
        return settings["pilco_steps"] if self.optimiser == "lbfgs" else settings["optimiser_steps"]

    @property
    def is_reading(self) -> bool:
        return bool(self.reads)


METHODS: dict[str, Method] = {
    "pilco": Method("pilco"),
    "rp": Method("rp"),
    "rp_fs": Method("rp_fs"),
    "gr": Method("gr"),
    "gr_fs": Method("gr_fs"),
    "lr": Method("biw_lr"),
    "lr_plain": Method("lr"),
    "tp": Method("tp"),
    "tp-sigma_f": Method("tp", (("model_var_scale", 0.0),)),
    "tp+sigma_n": Method("tp", (("noise_var_scale", 100.0),)),
    "pilco-sigma_n": Method("pilco", (("noise_var_scale", 0.0),), reads="pilco"),
    "rp_fs_run": Method("rp_fs", reads="rp_fs", noise_fixed_per_run=True),
    "gr_fs_run": Method("gr_fs", reads="gr_fs", noise_fixed_per_run=True),
    "rp_fs_lbfgs": Method("rp_fs", reads="rp_fs", quasi_newton=True),
    "gr_fs_lbfgs": Method("gr_fs", reads="gr_fs", quasi_newton=True),
    "rp_fs_seed0": Method("rp_fs", invalid="every repeat and trial optimised on the same particles (noise seed 0: "
                                           "the fixed-seed bug fixed in issue 18); not the paper's RP_FS"),
    "gr_fs_seed0": Method("gr_fs", invalid="every repeat and trial optimised on the same particles (noise seed 0: "
                                           "the fixed-seed bug fixed in issue 18), and resampled with xi = eps as "
                                           "`gr_xi_eq_eps`; not the paper's GR_FS"),
    "gr_xi_eq_eps": Method("gr", invalid="each resampled particle reused the noise that had sampled it (xi = eps: "
                                         "the resampling-key bug fixed on 2026-12-06); not the paper's GR"),
    "gr_fs_xi_eq_eps": Method("gr_fs", invalid="GR_FS with xi = eps as `gr_xi_eq_eps`; not the paper's GR_FS"),
}
"""Method name -> Method. The paper's learning column "LR" is its "model-based batch importance
weighted likelihood ratio", so ``lr`` is the ``biw_lr`` estimator; ``lr_plain`` is LR without the
batch importance weights. The paper's TP variants change the model's variances, not the
estimator. ``pilco-sigma_n`` is pilco-matlab's reading of PILCO's step: the latent function's
variance propagated without the learned noise sn^2 (``gp/gp0d.m``, ``base/propagate.m``), where
``pilco`` adds sn^2 to every next state as the particle methods sample it. The paper's RP_FS and
GR_FS fix "the random seed" without saying for how long: ``rp_fs`` and ``gr_fs`` fix the noise
for one trial's policy optimisation (``estimators.base.FixedNoise``), ``rp_fs_run`` and
``gr_fs_run`` for the whole learning run (``learning_run(optimisation_key_per_run=True)``). The paper
optimises them by "quasi-Newton optimizers, such as BFGS" with "600 policy evaluations between each
trial": ``rp_fs_lbfgs`` and ``gr_fs_lbfgs`` (per-trial noise, L-BFGS, float64 as PILCO's)."""

DEFAULT_METHODS = "pilco,rp,rp_fs,gr,gr_fs,lr,tp,tp-sigma_f,tp+sigma_n"
"""The paper's columns."""
PAPER_METHODS = ("pilco", "rp", "rp_fs", "gr", "gr_fs", "lr", "tp")
"""The methods of every column of the paper's tables, the ones the orderings compare."""
READINGS = tuple(name for name, m in METHODS.items() if m.is_reading)
INVALID = {name: m.invalid for name, m in METHODS.items() if m.invalid}
"""Names of rows kept for the record that measure no method of the paper, and why."""

PAPER_RATES = {  # PIPPS (Parmas et al. 2018), Tables 1-2: success rates over 100 repeats
    ("cartpole", "angle", 0.01): dict(pilco=0.88, rp=0.69, rp_fs=0.24, gr=0.63, gr_fs=0.74, lr=0.57, tp=0.82,
                                      **{"tp+sigma_n": 0.96}),
    ("cartpole", "angle", 1.0): dict(pilco=0.79, rp=0.74, rp_fs=0.23, gr=0.89, gr_fs=0.71, lr=0.96, tp=0.99,
                                     **{"tp-sigma_f": 0.93}),
    ("cartpole", "angle", 4.0): dict(pilco=0.70, rp=0.58, rp_fs=0.08, gr=0.62, gr_fs=0.41, lr=0.94, tp=0.95),
    ("cartpole", "angle", 9.0): dict(pilco=0.37, rp=0.44, rp_fs=0.04, gr=0.34, gr_fs=0.25, lr=0.86, tp=0.83),
    ("cartpole", "angle", 16.0): dict(pilco=0.01, rp=0.11, rp_fs=0.00, gr=0.08, gr_fs=0.02, lr=0.45, tp=0.40),
    ("cartpole", "tip", 0.01): dict(pilco=0.92, rp=0.44, rp_fs=0.20, gr=0.47, gr_fs=0.78, lr=0.36, tp=0.54),
    ("cartpole", "tip", 1.0): dict(pilco=0.73, rp=0.15, rp_fs=0.08, gr=0.68, gr_fs=0.50, lr=0.28, tp=0.48),
    ("unicycle", "default", 1.0): dict(pilco=0.91, rp=0.80, rp_fs=0.39, gr=0.96, gr_fs=0.63, lr=0.47, tp=0.94),
}
"""(task, cost, k) -> method -> the paper's success rate."""


def method(name: str) -> Method:
    """The catalogue's record of ``name``; a ValueError naming the valid methods otherwise."""
    if name not in METHODS:
        raise ValueError(f"unknown method {name!r}; valid methods: {runnable()} (a new estimator becomes a method "
                         "with an entry in harness.methods.METHODS)")
    return METHODS[name]


def runnable() -> list[str]:
    """The names a learning run accepts (every method that is not invalid)."""
    return [name for name, m in METHODS.items() if not m.invalid]


def paper_rate(name: str, task: str, cost: str, k: float) -> float:
    """The paper's rate of ``name`` (of the method a reading reads) in a cell; NaN where it has none."""
    entry = METHODS.get(name)
    return PAPER_RATES.get((task, cost, float(k)), {}).get(entry.reads if entry and entry.reads else name, np.nan)
