"""Where the recorded rollout's compile time goes: its pieces lowered and compiled one by one; writes JSON.

    python -m sim_data.bench.compile --out runs/bench/compile.json [--batch 8] [--pieces scan,env_step,...]

The data, rollouts and evaluation stages each compile the `mjx` engine's recorded rollout
(`sim_data.sim.rollout._scan_recorded`: the policy, 10 physics substeps, the task checks and the
renderer in one scanned body). Each piece below is jitted alone at `--batch` simulations of the mug
task, with the data generator's scripted policy and the head camera, and timed from its lowered
program: StableHLO lines (the program's size) and compile seconds on the default JAX device. Every
compile is fresh (the persistent compilation cache is switched off for the run).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from mujoco import mjx
from mujoco.mjx._src import collision_driver, constraint, smooth

from sim_data.bench.policy import identity_norm
from sim_data.policies import bc
from sim_data.policies.scripted import (
    ScriptOrProgramPolicy,
    pad_programs,
    script_or_program_params,
)
from sim_data.sim import robot as R
from sim_data.sim import rollout as RO
from sim_data.sim.env import HomeEnv
from sim_data.sim.render import HEAD_CAMERA, cached_renderers, episode_rgb
from sim_data.sim.tasks import MAX_EPISODE_STEPS, PHYSICS_SUBSTEPS
from sim_data.util import device_name, run_cli, write_json_atomic


def compile_cost(fn, *args) -> dict:
    """{"lines": StableHLO lines of jit(fn) lowered at args, "lower_s", "compile_s"}."""
    t0 = time.perf_counter()
    lowered = jax.jit(fn).lower(*args)
    t1 = time.perf_counter()
    lines = lowered.as_text().count("\n")
    t2 = time.perf_counter()
    lowered.compile()
    return {"lines": lines, "lower_s": t1 - t0, "compile_s": time.perf_counter() - t2}


def _rollout_inputs(batch: int):
    """(env, scripted policy, its params, renderers, reset state, policy carry, observation, colours)."""
    env = HomeEnv("mug", batch, engine="mjx")
    policy = ScriptOrProgramPolicy.create(MAX_EPISODE_STEPS, model=env.model)
    params = jax.tree_util.tree_map(jnp.asarray, pad_programs(script_or_program_params(
        [1.0] * batch, np.zeros((batch, 1, R.ACTION_DIM), np.float32), [False] * batch), MAX_EPISODE_STEPS))
    renderers = cached_renderers(64, (HEAD_CAMERA,))
    rng = jax.random.PRNGKey(0)
    state = env.reset(rng)
    rgb = episode_rgb(renderers[0].geometry, state.task.colors)
    carry = jax.jit(policy.init_carry)(params, state.obs, state.task, rng)
    obs, _, _ = RO._observe_mjx(env.core, renderers, state, rgb)
    return env, policy, params, renderers, state, carry, obs, rgb


def _bc_params(encoder: str):
    cfg = bc.PolicyNetConfig(encoder=encoder)
    return bc.BCPolicy(cfg), bc.init_params(cfg, jax.random.PRNGKey(0), identity_norm(), True)


def piece_programs(batch: int) -> dict:
    """{piece name: (description, fn, args)} of every piece the module's docstring names."""
    env, policy, params, renderers, state, carry, obs, rgb = _rollout_inputs(batch)
    core, rng, zero = env.core, jax.random.PRNGKey(1), jnp.zeros((batch, R.ACTION_DIM))
    ctrl, mocap = jax.jit(core.pre_step)(state, zero)
    _, qpos, qvel = core.engine.advance(state.physics, ctrl, mocap, 1)
    mx = core.engine.mx
    one = mjx.make_data(mx, impl="jax")
    many = jax.tree_util.tree_map(lambda x: jnp.broadcast_to(x, (batch,) + x.shape), one)
    image = {"image": obs["image"], "proprio": obs["proprio"]}
    steps = jnp.zeros((batch,), jnp.int32)
    conv, conv_params = _bc_params("conv")
    vit, vit_params = _bc_params("vit")
    return {
        "scan": ("the whole scanned recorded step (_scan_recorded)",
                 lambda st, c, o: RO._scan_recorded(core, policy, renderers, params, st, c, o, rng, jnp.int32(0), rgb),
                 (state, carry, obs)),
        "env_step": ("the environment's step: controls, the substeps, the task checks (EnvCore.mjx_step)",
                     core.mjx_step, (state, zero)),
        "substeps": (f"the {PHYSICS_SUBSTEPS} physics substeps alone (MjxEngine.advance)",
                     lambda p, c, m: core.engine.advance(p, c, m, PHYSICS_SUBSTEPS), (state.physics, ctrl, mocap)),
        "task_checks": ("the task checks (EnvCore.post_step)", core.post_step, (state, zero, qpos, qvel)),
        "mjx_step_one": ("MuJoCo's mjx.step, one simulation", lambda d: mjx.step(mx, d), (one,)),
        "mjx_step_vmap": ("mjx.step vmapped over the batch", jax.vmap(lambda d: mjx.step(mx, d)), (many,)),
        "position_stages": ("kinematics, com, crb and factor_m of one simulation",
                            lambda d: smooth.factor_m(mx, smooth.crb(mx, smooth.com_pos(mx, smooth.kinematics(mx, d)))),
                            (one,)),
        "collision": ("collision of one simulation", lambda d: collision_driver.collision(mx, d), (one,)),
        "constraints": ("constraint rows of one simulation", lambda d: constraint.make_constraint(mx, d), (one,)),
        "scripted_act": ("the scripted policy's act (every task's script and its IK)",
                         lambda p, o, c: policy.act(p, o, c, rng), (params, obs, carry)),
        "observation": ("the observation: renderer and proprioception",
                        lambda st: RO._observation(core.poses(st), st, renderers, rgb), (state,)),
        "bc_act_conv": ("a behaviour-cloning policy's act, conv encoder",
                        lambda p, o, t: conv.act(p, o, t, None), (conv_params, image, steps)),
        "bc_act_vit": ("a behaviour-cloning policy's act, ViT encoder",
                       lambda p, o, t: vit.act(p, o, t, None), (vit_params, image, steps)),
    }


PIECES = ("scan", "env_step", "substeps", "task_checks", "mjx_step_one", "mjx_step_vmap", "position_stages",
          "collision", "constraints", "scripted_act", "observation", "bc_act_conv", "bc_act_vit")


def profile(batch: int, pieces=PIECES, progress: bool = True) -> list[dict]:
    """compile_cost of each named piece at `batch` simulations, as rows {"piece", "what", "lines",
    "lower_s", "compile_s"}."""
    unknown = [p for p in pieces if p not in PIECES]
    if unknown:
        raise ValueError(f"unknown pieces {unknown}: choose among {', '.join(PIECES)}")
    if batch < 1:
        raise ValueError(f"batch must be >= 1, got {batch}")
    programs = piece_programs(batch)
    rows = []
    for name in pieces:
        what, fn, args = programs[name]
        rows.append({"piece": name, "what": what, **compile_cost(fn, *args)})
        if progress:
            print(json.dumps(rows[-1]), flush=True)
    return rows


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--batch", type=int, default=8)
    p.add_argument("--pieces", default=",".join(PIECES), help=f"comma-separated, among {', '.join(PIECES)}")
    a = p.parse_args(argv)
    cached = jax.config.jax_enable_compilation_cache
    jax.config.update("jax_enable_compilation_cache", False)  # every compile timed from scratch
    try:
        rows = profile(a.batch, tuple(x for x in a.pieces.split(",") if x))
    finally:
        jax.config.update("jax_enable_compilation_cache", cached)
    write_json_atomic(a.out, {"device": device_name(), "batch": a.batch, "jax": jax.__version__, "pieces": rows})
    print(f"wrote {a.out}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(run_cli(main))
