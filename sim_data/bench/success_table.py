"""Success rates of the scripted policies for every task at several skills.

    python -m sim_data.bench.success_table --backend cpu --episodes 100 --skills 0.2,0.6,1.0 --out runs/success.json

writes `{"engine", "episodes", "grip", "seed", "tray_spring", "rates": {task: {skill: success_rate}}, "intervals":
{task: {skill: [low, high]}}, "failed_progress": {task: {skill: [mean, max] or null}}}` (skill keys as
given; 95% Wilson intervals over the episodes; the task's progress, `sim_data.sim.tasks.task_progress`,
at the end of the episodes that failed, null where none did: how near the failures came to the success
line, 1) and prints the table. Episodes of one task share their initial states across skills (same seed), so the
skills are compared on the same scenes. `--grip F` scales every closure of the scripts by F (the data
generator's weak grips; 1: as scripted): at which grip a task's grasp still holds. `--tray-spring K,X`
runs a scene whose air fryer tray is two-state (`sim_data.sim.scene.with_tray_spring`: K N/m away from X m
of its travel), a design whose outcomes this table measures against the plain slide's.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from tqdm import tqdm

from sim_data.policies.scripted import ScriptedPolicy
from sim_data.sim import scene as S
from sim_data.sim.engines import ENGINES, default_engine
from sim_data.sim.env import HomeEnv
from sim_data.sim.rollout import run_episodes
from sim_data.sim.tasks import TASK_NAMES
from sim_data.util import run_cli, wilson_interval, write_json_atomic


def parse_skills(text: str) -> list[str]:
    """The skills of a comma list as given (strings, the table's keys); exits with a message (SystemExit) where
    one is not a number in [0, 1] or none is given."""
    skills = [s.strip() for s in text.split(",") if s.strip()]
    for s in skills:
        try:
            v = float(s)
        except ValueError:
            raise SystemExit(f"--skills: {s!r} is not a number") from None
        if not 0.0 <= v <= 1.0:
            raise SystemExit(f"--skills: {s} is outside [0, 1]")
    if not skills:
        raise SystemExit("--skills: give at least one skill, e.g. 0.2,0.6,1.0")
    return skills


def parse_tray_spring(text: str) -> tuple[float, float]:
    """(stiffness, centre) of "K,X"; exits with a message (SystemExit) where it is not two numbers, a
    stiffness > 0 and a centre inside the tray's travel."""
    try:
        k, x = (float(v) for v in text.split(","))
    except ValueError:
        raise SystemExit(f"--tray-spring: {text!r} is not K,X (N/m, m), e.g. 100,0.07") from None
    try:
        S.load_model(tray_spring=(k, x))  # the scene's own checks; the envs reuse the compiled model
    except ValueError as e:
        raise SystemExit(f"--tray-spring: {e}") from None
    return k, x


def success_table(tasks, skills, episodes: int, engine: str, batch: int, seed: int, show_progress: bool = True,
                  grip: float = 1.0, tray_spring: tuple | None = None):
    """Runs `episodes` scripted episodes per (task, skill), every closure scaled by grip, in the scene
    with tray_spring (HomeEnv's; None: the plain slide).

    Returns ({task: {skill: rate}}, {task: {skill: successes}}, {task: {skill: [mean, max] of the failed
    episodes' final progress, or None}}, seconds).
    """
    rates, counts, near = {}, {}, {}
    total = len(tasks) * len(skills) * episodes
    bar = tqdm(total=total, unit="ep", desc="success table", disable=not show_progress, file=sys.stderr)
    t0 = time.time()
    for ti, task in enumerate(tasks):
        rates[task], counts[task], near[task] = {}, {}, {}
        chunks = [min(batch, episodes - s) for s in range(0, episodes, batch)]
        envs = {b: HomeEnv(task, b, engine=engine, tray_spring=tray_spring) for b in set(chunks)}
        policy = ScriptedPolicy.create(task, envs[chunks[0]].model)
        for skill in skills:
            wins, failed = 0, []
            for ci, b in enumerate(chunks):
                rng = jax.random.fold_in(jax.random.fold_in(jax.random.PRNGKey(seed), ti), ci)
                params = {"skill": jnp.full((b,), float(skill), jnp.float32), "grip": jnp.full((b,), grip, jnp.float32)}
                state, _ = run_episodes(envs[b], policy, params, rng)
                success = np.asarray(state.success)
                wins += int(np.sum(success))
                failed += np.asarray(state.progress)[~success].tolist()
                bar.update(b)
                bar.set_postfix(task=task, skill=skill)
            rates[task][skill] = wins / episodes
            counts[task][skill] = wins
            near[task][skill] = [float(np.mean(failed)), float(np.max(failed))] if failed else None
    bar.close()
    return rates, counts, near, time.time() - t0


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--backend", choices=ENGINES, default=None, help="physics engine (default: mjx on GPU, else cpu)")
    p.add_argument("--episodes", type=int, default=100, help="episodes per task and skill")
    p.add_argument("--skills", default="0.2,0.6,1.0", help="comma-separated skills in [0, 1]")
    p.add_argument("--tasks", default=",".join(TASK_NAMES), help="comma-separated task names")
    p.add_argument("--batch", type=int, default=None, help="episodes simulated together (default: 50 cpu, 1024 mjx)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--grip", type=float, default=1.0, help="factor on every closure of the scripts (1: as scripted)")
    p.add_argument("--tray-spring", default=None, metavar="K,X",
                   help="the air fryer's tray two-state: pushed K N/m away from X m of its travel (default: the plain slide)")
    p.add_argument("--out", type=Path, required=True, help="JSON file to write")
    a = p.parse_args(argv)
    if a.episodes < 1:
        raise SystemExit("--episodes must be >= 1")
    if not 0.0 <= a.grip <= 1.0:
        raise SystemExit(f"--grip: {a.grip} is outside [0, 1]")
    tasks = [t.strip() for t in a.tasks.split(",") if t.strip()]
    unknown = [t for t in tasks if t not in TASK_NAMES]
    if unknown:
        raise SystemExit(f"--tasks: unknown {unknown}; choose from {', '.join(TASK_NAMES)}")
    skills = parse_skills(a.skills)
    spring = parse_tray_spring(a.tray_spring) if a.tray_spring else None
    engine = a.backend or default_engine()
    batch = min(a.batch or (50 if engine == "cpu" else 1024), a.episodes)
    rates, counts, near, secs = success_table(tasks, skills, a.episodes, engine, batch, a.seed, grip=a.grip,
                                              tray_spring=spring)
    intervals = {t: {s: list(wilson_interval(counts[t][s], a.episodes)) for s in skills} for t in tasks}
    write_json_atomic(a.out, {"engine": engine, "episodes": a.episodes, "grip": a.grip, "seed": a.seed,
                              "tray_spring": list(spring) if spring else None,
                              "rates": rates, "intervals": intervals, "failed_progress": near})
    print(f"engine={engine} episodes={a.episodes} per point, grip {a.grip:g}, {secs:.0f} s; 95% Wilson intervals")
    print(f"{'task':<10}" + "".join(f"{'skill ' + s:>22}" for s in skills))
    for task in tasks:
        cells = [f"{rates[task][s]:.2f} [{intervals[task][s][0]:.2f},{intervals[task][s][1]:.2f}]" for s in skills]
        print(f"{task:<10}" + "".join(f"{c:>22}" for c in cells))
    print("the failures' final progress, mean / max (1: the success line)")
    for task in tasks:
        cells = [("-" if near[task][s] is None else f"{near[task][s][0]:.3f} / {near[task][s][1]:.3f}") for s in skills]
        print(f"{task:<10}" + "".join(f"{c:>22}" for c in cells))
    print(f"wrote {a.out}")
    return 0


if __name__ == "__main__":
    sys.exit(run_cli(main))
