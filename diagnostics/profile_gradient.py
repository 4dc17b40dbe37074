"""Where one gradient estimate's time goes: a JAX profiler trace of RP or TP on the bench's cart-pole GP, and
the time per XLA operation (the numbers behind docs/performance.md). Not part of the harness.

    pip install xprof        # reads the trace (a development tool, not a dependency of the project)
    taskset -c 0 python diagnostics/profile_gradient.py ROWS ESTIMATOR [TRACE_DIR]   # e.g. 300 rp

ROWS: the GP's training points (ROWS / 30 random episodes, as ``harness.bench``); P = 300, T = 30, float32
(the GP fitted in float64 and cast, as the learning runs' rollouts). Prints the operations by total time over
three calls, the number of operations run per time step, and the time in them.
"""

import collections
import dataclasses
import glob
import json
import sys

import jax
import jax.numpy as jnp

import estimators
from harness import bench
from harness.episodic import cast_floating

jax.config.update("jax_enable_x64", True)
CALLS, PARTICLES = 3, 300


def trace(rows: int, name: str, folder: str) -> str:
    _, problem, theta, _ = bench.bench_problem(bench.Args(trials=rows // 30, gp_steps=30))
    problem = dataclasses.replace(problem, model_params=cast_floating(problem.model_params, jnp.float32))
    theta = cast_floating(theta, jnp.float32)
    key = jax.random.key(1)
    compiled = jax.jit(estimators.make(name), static_argnums=3).lower(problem, theta, key, PARTICLES).compile()
    jax.block_until_ready(compiled(problem, theta, key))
    jax.profiler.start_trace(folder)
    for call in range(CALLS):
        jax.block_until_ready(compiled(problem, theta, jax.random.fold_in(key, call)))
    jax.profiler.stop_trace()
    return glob.glob(folder + "/**/*.xplane.pb", recursive=True)[-1]


def operation_times(path: str) -> dict[str, list[float]]:
    """Operation name -> [count, total microseconds] from the trace's complete events."""
    from xprof.convert.raw_to_tool_data import xspace_to_tool_data

    data, _ = xspace_to_tool_data([path], "trace_viewer@", {})
    events = json.loads(data.decode() if isinstance(data, bytes) else data)["traceEvents"]
    totals = collections.defaultdict(lambda: [0, 0.0])
    for event in events:
        if event.get("ph") == "X":
            totals[event["name"]][0] += 1
            totals[event["name"]][1] += event.get("dur", 0)
    return totals


def main(rows: str, name: str, folder: str = "/tmp/profile_gradient") -> None:
    totals = operation_times(trace(int(rows), name, folder))
    steps = CALLS * 30
    for op, (count, micros) in sorted(totals.items(), key=lambda item: -item[1][1])[:30]:
        print(f"{micros / 1e3 / CALLS:9.2f} ms per call  {count:6d}  {op[:100]}")
    per_step = [(count, micros) for op, (count, micros) in totals.items()
                if count % steps == 0 and not op.startswith("$") and "Thunk" not in op and "Threadpool" not in op]
    print(f"operations per time step: {sum(c // steps for c, _ in per_step)}, their time per call: "
          f"{sum(m for _, m in per_step) / 1e3 / CALLS:.1f} ms")


if __name__ == "__main__":
    main(*sys.argv[1:])
