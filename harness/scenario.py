"""The scenario the gradient experiments start from, built reproducibly and cached.

From a seed: the task's random trial(s), then ``learned_trials`` trials of the paper's loop
(fit the GP to all data, optimise the policy on it with ``estimator`` for
``optimiser_steps`` steps of the paper's optimiser, run the policy once on the real system,
add the data); finally the GP is refitted to all data. The result is theta0 (the policy after
the last trial) and the GP posterior. The cache file's name is a hash of the settings, the
task's options and the code that builds it.

A build is not reproducible across machines: the trials' optimisers amplify round-off, and
XLA's round-off depends on its threading and on the machine (the same settings and code gave
different theta0 on two machines of one kind with the same flags, and on one machine under two
XLA thread settings). So a scenario the reports quote is **pinned**: kept in
the repository's ``scenarios/`` (``--pin-scenario``), keyed by the settings and the task's
options alone, and used, whatever the code or machine, unless ``--rebuild-scenario``. Every
report prints its content hash and where it came from.

Every gradient experiment (variance, landscape, compare) starts from the same ``Setting``: the
scenario's theta0, a fixed random unit direction d in parameter space (from the seed), and the
problem under the chosen model (the scenario's GP, or the true dynamics in JAX or MJX).
"""

from __future__ import annotations

import dataclasses
import datetime
import hashlib
import json
import os
import sys
from typing import Any, Callable, NamedTuple

import jax
import jax.flatten_util
import jax.numpy as jnp
import numpy as np

import estimators
import tasks
from estimators.base import Problem, draw_noise, per_particle, rollout, task_problem, theta_dtype
from estimators.pilco import Pilco, check_task
from harness import keys
from harness.cli import check_sizes
from harness.episodic import learning_run, policy_optimiser
from harness.records import ROOT, source_digest
from models import gp
from models.simulator import SimulatorModel
from tasks.base import Task

class ModelSpec(NamedTuple):
    """A model an experiment can roll out: ``problem(task, scenario)`` makes the task's problem
    under it; ``learned``: fitted to the scenario's data (``harness.compare`` sets it against the
    true dynamics), else the true dynamics (a reference gradient may be computed on it)."""

    problem: Callable[[Task, "Scenario"], Problem]
    learned: bool


MODELS: dict[str, ModelSpec] = {
    "gp": ModelSpec(lambda task, scenario: task_problem(task, gp.GPModel(task), scenario.posterior), learned=True),
    "jax": ModelSpec(lambda task, scenario: task_problem(task, SimulatorModel(task, backend="jax")), learned=False),
    "mjx": ModelSpec(lambda task, scenario: task_problem(task, SimulatorModel(task, backend="mjx")), learned=False),
}
"""The models an experiment can roll out (``--model``), by name: the scenario's fitted GP, or the
true dynamics in plain JAX or MJX."""


@dataclasses.dataclass(frozen=True)
class ScenarioArgs:
    """How the scenario is built (recorded in every report that uses it)."""

    task: str = "cartpole"
    """Task name."""
    seed: int = 0
    """Seed of the scenario's trials."""
    learned_trials: int = 4
    """Learned trials after the random one(s)."""
    estimator: str = "pilco"
    """Estimator (or pilco) that optimises the policy in each trial."""
    particles: int = 100
    """Particles per gradient estimate."""
    optimiser_steps: int = 150
    """Optimiser steps per trial (L-BFGS steps for pilco)."""
    gp_steps: int = 100
    """L-BFGS steps of each GP fit."""

    def describe(self) -> str:
        how = (f"PILCO ({self.optimiser_steps} L-BFGS steps)" if self.estimator == "pilco" else
               f"{self.estimator} ({self.particles} particles, {self.optimiser_steps} steps of the paper's optimiser)")
        return (f"task {self.task}, seed {self.seed}: the preset's random trial(s), then "
                f"{self.learned_trials} learned trial(s), each optimising the policy on the GP "
                f"with {how}; GP refitted to all data ({self.gp_steps} L-BFGS steps)")


class Scenario(NamedTuple):
    """data: the GP's training buffer; posterior: the GP fitted to it; theta: theta0 (the
    policy after the last learned trial); returns: (trials,) real-system return per trial."""

    data: gp.GPData
    posterior: gp.GPPosterior
    theta: Any
    returns: np.ndarray


def build(args: ScenarioArgs) -> Scenario:
    """Run the scenario's trials (progress on stderr)."""
    task = tasks.make(args.task)
    optimise = policy_optimiser(args.estimator, args.optimiser_steps, args.particles)
    returns = []

    def on_trial(record, data):
        returns.append(float(record.episode.total_cost))
        if record.trial + 1 < task.num_random_trials + args.learned_trials:
            print(f"scenario: trial {record.trial + 1} done ({int(data.num_valid)} training points)", file=sys.stderr,
                  flush=True)

    problem = task_problem(task, gp.GPModel(task))
    run_key = keys.stream(jax.random.key(args.seed), "scenario_run")
    theta, data = learning_run(task, problem, run_key, args.learned_trials, optimise, args.gp_steps, on_trial)
    posterior = gp.fit(data, num_steps=args.gp_steps)
    return Scenario(data, posterior, theta, np.asarray(returns))


SCENARIO_CODE = ("numerics", "tasks", "models", "estimators", "harness/episodic.py", "harness/optim.py",
                 "harness/scenario.py")
"""The code a scenario's theta0 and GP depend on (packages and modules, relative to the root)."""


def code_digest() -> str:
    """A hash of the source files of ``SCENARIO_CODE`` (``records.source_digest``)."""
    return source_digest(SCENARIO_CODE)


PINNED_DIR = os.path.join(ROOT, "scenarios")
"""The repository's pinned scenarios (see the module docstring)."""


SCENARIO_SCHEMA_VERSION = 1
"""Version of the scenario files' layout (``save_scenario``)."""


def policy_structure(task: Task):
    """The tree structure of ``task``'s default policy parameters (theta)."""
    return jax.tree.structure(jax.eval_shape(task.default_policy().init, jax.random.key(0)))


def theta_arrays(theta) -> dict[str, np.ndarray]:
    """theta's leaves as named arrays, ``theta.I`` the I-th (none for theta None)."""
    return {f"theta.{i}": np.asarray(leaf) for i, leaf in enumerate(jax.tree.leaves(theta))}


def theta_from_arrays(arrays: dict, structure):
    """theta rebuilt on ``structure`` from ``theta_arrays``'s entries of ``arrays``."""
    return jax.tree.unflatten(structure, [arrays[f"theta.{i}"] for i in range(structure.num_leaves)])


def save_scenario(saved: dict, path: str) -> None:
    """Write ``saved`` (``scenario``: a Scenario, ``provenance``: a dict) as plain data: ``PATH.npz`` (the
    arrays: ``data.*`` and ``posterior.*`` by field, ``theta.I`` the I-th leaf of theta0, ``returns``) and
    ``PATH.json`` (schema version, the task, theta0's tree structure and the provenance), each atomically."""
    scn = jax.device_get(saved["scenario"])
    arrays = {f"data.{k}": np.asarray(v) for k, v in scn.data._asdict().items()}
    arrays |= {f"posterior.{k}": np.asarray(v) for k, v in scn.posterior._asdict().items()}
    arrays |= theta_arrays(scn.theta)
    arrays["returns"] = np.asarray(scn.returns)
    os.makedirs(os.path.dirname(path) or ".", exist_ok=True)
    with open(path + ".npz.tmp", "wb") as f:
        np.savez(f, **arrays)
    os.replace(path + ".npz.tmp", path + ".npz")
    meta = dict(schema_version=SCENARIO_SCHEMA_VERSION, theta_structure=str(jax.tree.structure(scn.theta)),
                provenance=saved["provenance"], **saved.get("meta", {}))
    with open(path + ".json.tmp", "w") as f:
        json.dump(meta, f, indent=1, sort_keys=True)
    os.replace(path + ".json.tmp", path + ".json")


def load_scenario(path: str, task: str) -> dict | None:
    """What ``save_scenario`` wrote at ``path`` (a dict with ``scenario`` and ``provenance``, and the JSON's
    other entries under ``meta``), or None if there is nothing; theta0's tree comes from the task's
    default policy, and a file that does not fit it, or of another schema version, is named."""
    if not (os.path.exists(path + ".npz") and os.path.exists(path + ".json")):
        return None
    with open(path + ".json") as f:
        meta = json.load(f)
    if meta.get("schema_version") != SCENARIO_SCHEMA_VERSION:
        raise ValueError(f"{path}.json: scenario schema_version {meta.get('schema_version')!r}, this code reads "
                         f"{SCENARIO_SCHEMA_VERSION}")
    with np.load(path + ".npz") as f:
        arrays = dict(f)
    structure = policy_structure(tasks.make(task))
    if str(structure) != meta["theta_structure"]:
        raise ValueError(f"{path}: theta0 is a {meta['theta_structure']}, task {task!r}'s policy takes a "
                         f"{structure}")
    theta = theta_from_arrays(arrays, structure)
    scenario = Scenario(gp.GPData(**{k: arrays[f"data.{k}"] for k in gp.GPData._fields}),
                        gp.GPPosterior(**{k: arrays[f"posterior.{k}"] for k in gp.GPPosterior._fields}),
                        theta, arrays["returns"])
    return dict(scenario=scenario, provenance=meta["provenance"],
                meta={k: v for k, v in meta.items() if k not in ("provenance", "schema_version", "theta_structure")})


def settings_file(args: ScenarioArgs, folder: str, with_code: bool) -> str:
    """``folder/scenario_{task}_{hash}`` (``.npz`` and ``.json``: ``save_scenario``), the hash of ``args``, the precision, every option of
    the task (``tasks.describe``: a change of a task's default, e.g. its cost, makes a new one)
    and, ``with_code``, the code that builds it (``code_digest``)."""
    settings = {**dataclasses.asdict(args), "x64": jax.config.jax_enable_x64,
                "task_options": tasks.describe(tasks.make(args.task))}
    if with_code:
        settings["code"] = code_digest()
    digest = hashlib.sha256(json.dumps(settings, sort_keys=True).encode()).hexdigest()[:12]
    return os.path.join(folder, f"scenario_{args.task}_{digest}")


def cache_path(args: ScenarioArgs, cache_dir: str) -> str:
    """The cache file of ``args``, keyed by the code too, so that a stale build is never reused."""
    return settings_file(args, cache_dir, with_code=True)


def pinned_path(args: ScenarioArgs, pinned_dir: str = PINNED_DIR) -> str:
    """The pinned file of ``args``: keyed by the settings and task options, not the code."""
    return settings_file(args, pinned_dir, with_code=False)


def provenance() -> dict:
    """How a scenario was built: the code, the library, XLA's flags, the CPUs, the date."""
    return dict(code=code_digest(), jax=jax.__version__, xla_flags=os.environ.get("XLA_FLAGS", ""),
                cpus=len(os.sched_getaffinity(0)), built=datetime.datetime.now(datetime.timezone.utc).isoformat(
                    timespec="seconds"))


def describe_provenance(saved: dict) -> str:
    """``provenance()`` of a saved scenario, as a phrase for reports and logs."""
    how = saved["provenance"]
    return (f"built {how['built']} by code {how['code']}, jax {how['jax']}, {how['cpus']} CPU(s), "
            f"XLA_FLAGS={how['xla_flags'] or '(none)'}")


def load_or_build(args: ScenarioArgs, cache_dir: str, pinned_dir: str = PINNED_DIR, rebuild: bool = False,
                  pin: bool = False) -> tuple[Scenario, str]:
    """The pinned scenario for ``args`` unless ``rebuild``; else the cached build under the
    current code, building and caching it if there is none. ``pin``: write what is used to
    the pinned file (replacing one there). Says on stderr which it used, and returns it with
    where it came from, as a phrase for reports."""
    pinned = pinned_path(args, pinned_dir)
    shown = (os.path.relpath(pinned, ROOT) if pinned.startswith(ROOT + os.sep) else pinned) + ".{npz,json}"
    saved = None if rebuild else load_scenario(pinned, args.task)
    if saved is not None:
        print(f"scenario: the pinned {pinned}.{{npz,json}} ({describe_provenance(saved)}); --rebuild-scenario builds one "
              "under the current code", file=sys.stderr, flush=True)
        source = f"the pinned {shown}, {describe_provenance(saved)}"
    else:
        path = cache_path(args, cache_dir)
        saved = load_scenario(path, args.task)
        if saved is None:
            saved = dict(scenario=build(args), provenance=provenance())
            save_scenario(saved, path)
        source = "built under the current code, not pinned"
        if pin:
            save_scenario(saved, pinned)
            print(f"scenario: pinned to {pinned}.{{npz,json}} ({describe_provenance(saved)})", file=sys.stderr, flush=True)
            source = f"built under the current code and pinned to {shown}, {describe_provenance(saved)}"
    return jax.tree.map(jax.numpy.asarray, saved["scenario"]), source


def from_file(path: str, task: str) -> tuple[Scenario, str]:
    """The scenario saved at ``path`` (``save_scenario``), with where it came from as a phrase for reports
    (the file, its ``description`` if it has one, and its provenance)."""
    saved = load_scenario(path, task)
    if saved is None:
        raise ValueError(f"no scenario file {path}.npz and {path}.json (harness.learn --keep-final writes a "
                         "learning run's final state as one)")
    made_under = saved["meta"].get("task_options")
    if made_under is not None and made_under != tasks.describe(tasks.make(task)):
        raise ValueError(f"{path}: made under task options {made_under}, but the gradient experiments run task "
                         f"{task!r} with its defaults, {tasks.describe(tasks.make(task))}")
    described = f"{saved['meta']['description']}; " if "description" in saved["meta"] else ""
    return (jax.tree.map(jax.numpy.asarray, saved["scenario"]),
            f"{described}the scenario file {path}.{{npz,json}}, {describe_provenance(saved)}")


TASK_SCENARIOS = {
    "cartpole": dict(scenario_trials=4, scenario_steps=150, scenario_particles=100, scenario_estimator="pilco"),
    "unicycle": dict(scenario_trials=2, scenario_steps=200, scenario_particles=100, scenario_estimator="tp"),
}
"""Each task's default scenario: the settings of its pinned one in scenarios/, so that every task's default
gradient experiment loads it instead of building one (a task without an entry takes the cart-pole's)."""

FLAT_SCENARIO_FLAGS = "--scenario-estimator tp --scenario-trials 2 --scenario-steps 200 --scenario-particles 100"
"""The flags of the scenario before issue 20 (a flat plateau: the policy never swings up)."""


@dataclasses.dataclass(frozen=True)
class ExperimentArgs:
    """The options every gradient experiment shares (their CLIs extend this dataclass).

    The default scenario is the task's pinned one (``TASK_SCENARIOS``); the cart-pole's (issue 20) is PILCO
    after 4 learned trials, a policy that has begun to
    swing the pole up (the criterion: J at theta0 between 10 and 25 of 30 on the cart-pole's GP;
    every report prints J at theta0 and at delta theta = 1.5). The earlier one, TP after 2
    learned trials with 100 particles and 200 steps, where every particle hangs down (J about
    29.7), is ``FLAT_SCENARIO_FLAGS``."""

    task: str = "cartpole"
    """Task name (a tasks.REGISTRY name: cartpole, unicycle)."""
    seed: int = 0
    """Seed of the scenario, the random direction and the estimates' keys."""
    out: str = "reports"
    """Folder for the CSV, markdown and figure (and .cache/ for scenarios)."""
    x64: bool = True
    """Compute in float64 (--no-x64: float32)."""
    scenario_trials: int = 0
    """Learned trials that build the scenario's theta0 and GP (0: the task's pinned scenario's,
    harness.scenario.TASK_SCENARIOS)."""
    scenario_steps: int = 0
    """Optimiser steps per scenario trial, L-BFGS steps for pilco (0: the task's pinned scenario's)."""
    scenario_particles: int = 0
    """Particles per gradient estimate while building the scenario, particle estimators only (0: the task's
    pinned scenario's)."""
    scenario_estimator: str = ""
    """Estimator (or pilco) that optimises the policy while building the scenario (empty: the task's pinned
    scenario's)."""
    rebuild_scenario: bool = False
    """Build the scenario under the current code (cached under out/.cache) instead of using the
    pinned one in scenarios/."""
    pin_scenario: bool = False
    """Pin the scenario used: write it to scenarios/, where every later run, on any machine,
    finds it (commit the file)."""
    scenarios_dir: str = PINNED_DIR
    """Folder of the pinned scenarios."""
    scenario_file: str = ""
    """Start from this scenario file (PATH of PATH.npz and PATH.json, e.g. a learning run's final state kept
    by ``harness.learn --keep-final``) instead of the task's pinned or built scenario."""

    def __post_init__(self):
        tasks.make(self.task)  # fails with the list of tasks
        for name, value in TASK_SCENARIOS.get(self.task, TASK_SCENARIOS["cartpole"]).items():
            if not getattr(self, name):  # unset: the task's pinned scenario's setting
                object.__setattr__(self, name, value)
        check_estimators([self.scenario_estimator], self.task)
        check_sizes(scenario_particles=(self.scenario_particles, 2), scenario_trials=(self.scenario_trials, 1))

    @property
    def scenario(self) -> ScenarioArgs:
        return ScenarioArgs(task=self.task, seed=self.seed, learned_trials=self.scenario_trials,
                            optimiser_steps=self.scenario_steps, particles=self.scenario_particles,
                            estimator=self.scenario_estimator)

    @property
    def scenario_name(self) -> str:
        """The scenario's name in every result row: its file's name, or its cache name (a hash of its
        settings)."""
        return os.path.basename(self.scenario_file or cache_path(self.scenario, ""))

    def scenario_lines(self, where: dict[str, "Setting"], rows, objective: list[dict], note: str = "") -> list[str]:
        """The report's lines on the scenario: how it was built, where it came from (pinned or
        built under the current code), the content hash of the rows shown; then J under each
        model of ``where`` (``objective``: ``objective_values``)."""
        hashes = ", ".join(sorted(map(str, rows.scenario.unique())))
        source = next(iter(where.values())).source
        built = "" if self.scenario_file else f"{self.scenario.describe()}{note}; "
        return [f"- Scenario: {built}{source}. Content hash {hashes} (theta0, the "
                "direction and the GP posterior, at float32 precision): every row shown was computed on it.",
                *[objective_line(model, objective, setting.problem.horizon) for model, setting in where.items()]]

    def scenario_flags(self) -> list[str]:
        """The flags that name the scenario, as a command's arguments."""
        if self.scenario_file:
            return ["--scenario-file", self.scenario_file]
        return (["--scenario-trials", str(self.scenario_trials), "--scenario-steps", str(self.scenario_steps),
                 "--scenario-particles", str(self.scenario_particles), "--scenario-estimator", self.scenario_estimator]
                + (["--rebuild-scenario"] if self.rebuild_scenario else []))


class Setting(NamedTuple):
    """Where an experiment measures: ``problem`` under the chosen model, ``theta0`` and the unit
    ``direction`` d (both pytrees like theta), the scenario they come from, ``content``, the
    ``content_hash`` of what is computed on (every result row is keyed by it), and ``source``,
    where the scenario came from (``load_or_build``)."""

    problem: Problem
    theta0: Any
    direction: Any
    scenario: Scenario
    content: str
    source: str

    def theta(self, delta: float):
        """``theta0 + delta * d``."""
        return jax.tree.map(lambda t, d: t + delta * d, self.theta0, self.direction)


def particle_returns(problem: Problem, theta, key: jax.Array, num_particles: int) -> jax.Array:
    """Each particle's return ``sum_t c(s_t)`` under the noise drawn with ``key``, (P,)."""
    s0, eps = draw_noise(problem, key, num_particles, theta_dtype(theta))
    return rollout(problem, per_particle(problem.policy.prepare(theta), num_particles), s0, eps).returns


OBJECTIVE_DELTAS = (0.0, 1.5)
OBJECTIVE_PARTICLES = 2000


def objective_values(where: dict[str, Setting], seed: int) -> list[dict]:
    """J under each model of ``where`` at theta0 + delta d, delta in ``OBJECTIVE_DELTAS``: [{model, delta_theta,
    value, ci}], the mean return of ``OBJECTIVE_PARTICLES`` particles (the seed's "objective" stream) and its 95 %
    half-width ``1.96 sd / sqrt(P)``."""
    returns = jax.jit(particle_returns, static_argnums=3)
    key = keys.stream(jax.random.key(seed), "objective")
    found = []
    for model, setting in where.items():
        for delta in OBJECTIVE_DELTAS:
            r = np.asarray(returns(setting.problem, setting.theta(delta), key, OBJECTIVE_PARTICLES))
            found.append(dict(model=model, delta_theta=float(delta), value=float(r.mean()),
                              ci=float(1.96 * r.std(ddof=1) / np.sqrt(len(r)))))
    return found


def objective_line(model: str, objective: list[dict], horizon: int) -> str:
    """A report line with J under ``model`` (``objective_values``' entries of that model) and the maximum J (the
    horizon: the cost is at most 1 per step). Issue 20's criterion for a scenario that swings up: J at theta0
    between 10 and 25 of 30 on the cart-pole's GP."""
    parts = [f"{o['value']:.2f} +- {o['ci']:.2f} at delta theta = {o['delta_theta']:g}" for o in objective
             if o["model"] == model]
    return (f"- J under the {model} model ({OBJECTIVE_PARTICLES} particles, 95 % interval; at most "
            f"{horizon}): {'; '.join(parts)}.")


def unit_direction(theta, key: jax.Array):
    """A random direction in parameter space with unit Euclidean norm, shaped like theta."""
    flat, unravel = jax.flatten_util.ravel_pytree(theta)
    d = jax.random.normal(key, flat.shape, flat.dtype)
    return unravel(d / jnp.linalg.norm(d))


def model_problem(task_name: str, model: str, scenario: Scenario) -> Problem:
    """The task's problem under ``model`` (a ``MODELS`` name)."""
    check_model(model)
    return MODELS[model].problem(tasks.make(task_name), scenario)


def model_labels(task_name: str, models: list[str]) -> list[str]:
    """Report lines that label an approximate MuJoCo model (``task.mjcf_label``) when "mjx" is
    among ``models``; none otherwise."""
    task = tasks.make(task_name)
    if task.mjcf_label is None or "mjx" not in models:
        return []
    return [f"- **mjx: {task.mjcf_label}** (see {os.path.basename(task.mjcf)}).", ""]


def check_estimators(names: list[str], task: str, models: list[str] = ()) -> None:
    """Fail now on an unknown estimator (with the list), or on the pilco estimator for a task
    without forms or with a model that is not learned (it moment-matches the GP)."""
    for name in names:
        if isinstance(estimators.make(name), Pilco):
            check_task(tasks.make(task))
            if unlearned := [m for m in models if not MODELS[m].learned]:
                raise ValueError(f"the pilco estimator moment-matches the learned GP; it cannot run on the "
                                 f"{', '.join(unlearned)} model")


def check_model(model: str) -> None:
    if model not in MODELS:
        raise ValueError(f"unknown model {model!r}; valid models: {list(MODELS)}")


def content_hash(theta0, direction, posterior: gp.GPPosterior) -> str:
    """A hash of theta0, the direction and the GP posterior's valid training inputs, targets'
    weights alpha and hyperparameters, each rounded to float32 (about 7 significant digits):
    equal for the same scenario computed twice, different when any of them changes."""
    mask = np.asarray(posterior.mask)
    arrays = [*jax.tree.leaves(theta0), *jax.tree.leaves(direction), np.asarray(posterior.inputs)[mask],
              np.asarray(posterior.alpha)[:, mask], posterior.log_hyp]
    digest = hashlib.sha256()
    for array in arrays:
        digest.update(np.ascontiguousarray(np.asarray(array, np.float32)).tobytes())
    return digest.hexdigest()[:12]


def settings(args: ExperimentArgs, models: list[str]) -> dict[str, Setting]:
    """The Setting of ``args`` under each of ``models``, from one load (or build, cached under
    ``args.out``) of the scenario."""
    if args.scenario_file:
        scn, source = from_file(args.scenario_file, args.task)
    else:
        scn, source = load_or_build(args.scenario, os.path.join(args.out, ".cache"), args.scenarios_dir,
                                    args.rebuild_scenario, args.pin_scenario)
    direction = unit_direction(scn.theta, keys.stream(jax.random.key(args.seed), "direction"))
    content = content_hash(scn.theta, direction, scn.posterior)
    return {model: Setting(model_problem(args.task, model, scn), scn.theta, direction, scn, content, source)
            for model in models}


def setting(args: ExperimentArgs, model: str) -> Setting:
    """The Setting of ``args`` under ``model`` (``settings``)."""
    return settings(args, [model])[model]
