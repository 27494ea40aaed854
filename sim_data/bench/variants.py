"""MJX speed of model-design variants of the full scene, side by side (GPU notes for the README).

    python -m sim_data.bench.variants --out runs/bench/mjx_variants.json --batch 8192 [--stages]

Each variant changes one thing about `home.xml` (contacts, limits, solver settings) and is
stepped exactly as `sim_data.bench.physics` steps the real model; the first design, v0, is composed
from home.xml in MuJoCo (`sim_data.sim.scene_v0`, an MjSpec). `--stages` also times each stage of
one MJX step (kinematics, collision, constraint rows, solver, integrator) on its own, so a
variant's gain can be traced to where the time goes; `--dump NAME` writes an MJCF variant's text
(to check its tasks with `sim_data.bench.success_table` after copying it over `home.xml`).
"""

from __future__ import annotations

import argparse
import json
import re
import sys
import tempfile
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

from sim_data.bench.physics import ready_controls, time_mjx
from sim_data.sim import scene as S
from sim_data.sim import scene_v0
from sim_data.sim.engines import MjxEngine, mjx
from sim_data.sim.tasks import TASKS, sample_initial
from sim_data.util import device_name, run_cli, write_json_atomic

ASSETS = S.MODEL_PATH.parent


def _edit(xml: str, **opt) -> str:
    """Sets attributes of the <option> element."""
    head, rest = xml.split("<option", 1)
    tag, tail = rest.split(">", 1)
    for k, v in opt.items():
        tag = re.sub(rf' {k}="[^"]*"', f' {k}="{v}"', tag) if f" {k}=" in tag else f' {k}="{v}"' + tag
    return head + "<option" + tag + ">" + tail


def _sphere_pads(xml: str) -> str:
    return re.sub(r'(<geom name="(?:left|right)_finger_[ab]" type=")capsule(" pos="[^"]*") zaxis="1 0 0" size="0.01 0.014"',
                  r'\1sphere\2 size="0.012"', xml)


def _no_left_pairs(xml: str) -> str:
    return re.sub(r'\s*<pair geom1="left_finger_[ab]"[^>]*/>', "", xml)


def variants(which: str = "all") -> dict[str, str | mujoco.MjSpec]:
    """name -> MJCF text, or an MjSpec for v0. Names say what each variant changes and, where it
    broke the tasks, how."""
    home = S.MODEL_PATH.read_text()
    out = {
        "v0: box fingers (4 contacts/pair), friction everywhere, limits on all joints, jointed legs, Newton 4/8":
            scene_v0.spec(),
        "home.xml: capsule pads, condim-1 buttons/counter, servo joints unlimited, static legs, Newton 3/6": home,
        "home.xml, Newton 4/8": _edit(home, iterations=4, ls_iterations=8),
        "home.xml, Newton 2/4 (breaks tasks: wipe 0/8, shelf 3/8 at skill 1)": _edit(home, iterations=2, ls_iterations=4),
        "home.xml without left-hand pairs (left hand cannot grasp)": _no_left_pairs(home),
        "home.xml, sphere pads (breaks shelf: the block pivots in the pinch)": _sphere_pads(home),
        "home.xml, CG 2/4 (unstable: the cloth sinks through the counter at rest)":
            _edit(home.replace('solver="Newton"', 'solver="CG"'), iterations=2, ls_iterations=4),
        "home.xml, elliptic cones, all condim 3": home.replace('cone="pyramidal"', 'cone="elliptic"').replace(' condim="1"', ""),
        "home.xml, Euler (damping explicit)": _edit(home, integrator="Euler"),
        "home.xml, Euler (damping implicit)": _edit(home, integrator="Euler").replace('eulerdamp="disable"', 'eulerdamp="enable"'),
        "home.xml, Newton 3/3": _edit(home, ls_iterations=3),
        "home.xml, sparse Jacobian": _edit(home, jacobian="sparse"),
        "home.xml without object-floor pairs": re.sub(r'\s*<pair geom1="(?:mug|block)" geom2="floor"/>', "", home),
    }
    if which != "all":
        out = {k: v for k, v in out.items() if any(w in k for w in which.split(","))}
    return out


def _carry_qpos(qpos, base: mujoco.MjModel, m: mujoco.MjModel):
    """Maps qpos (B, base.nq) onto a variant's joints by name; joints base lacks keep m.qpos0."""
    out = np.tile(np.asarray(m.qpos0, np.float32), (qpos.shape[0], 1))
    for j in range(m.njnt):
        width = {0: 7, 1: 4, 2: 1, 3: 1}[int(m.jnt_type[j])]
        try:
            src = base.joint(m.joint(j).name).qposadr[0]
        except KeyError:
            continue
        out[:, m.jnt_qposadr[j] : m.jnt_qposadr[j] + width] = np.asarray(qpos[:, src : src + width])
    return out


def compile_xml(xml: str | mujoco.MjSpec) -> mujoco.MjModel:
    """A variant's MjModel (MJCF text is compiled beside home.xml, whose relative paths it shares)."""
    if isinstance(xml, mujoco.MjSpec):
        return xml.compile()
    with tempfile.NamedTemporaryFile("w", suffix=".xml", dir=ASSETS, delete=False) as f:
        f.write(xml)
    try:
        return mujoco.MjModel.from_xml_path(f.name)
    finally:
        Path(f.name).unlink()


def _best_seconds(fn, x, repeats: int = 5) -> float:
    jax.block_until_ready(fn(x))
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(fn(x))
        times.append(time.perf_counter() - t0)
    return min(times)


def stage_times(mx, d) -> dict:
    """Seconds of each stage of one MJX step over a batch `d` (vmapped), each jitted on its own.

    The stages chain as `mjx.step` chains them (MJX 3.x internals), each fed its predecessor's
    output; their sum exceeds the fused step by what XLA saves across stage boundaries.
    """
    collision_driver, constraint, forward, smooth, solver = (
        mjx._src.collision_driver, mjx._src.constraint, mjx._src.forward, mjx._src.smooth, mjx._src.solver)

    def smooth_position(m, x):
        for f in (smooth.kinematics, smooth.com_pos, smooth.camlight, smooth.tendon, smooth.crb,
                  smooth.tendon_armature, smooth.factor_m):
            x = f(m, x)
        return x

    integrate = {mujoco.mjtIntegrator.mjINT_EULER: forward.euler,
                 mujoco.mjtIntegrator.mjINT_IMPLICITFAST: forward.implicit}[int(mx.opt.integrator)]
    stages = [("kinematics, inertia, factor M", smooth_position), ("collision", collision_driver.collision),
              ("constraint rows", constraint.make_constraint), ("transmission", smooth.transmission),
              ("velocity (passive, rne)", forward.fwd_velocity), ("actuation", forward.fwd_actuation),
              ("smooth acceleration", forward.fwd_acceleration), ("solver", solver.solve),
              ("integrator", integrate)]
    out = {}
    for name, f in stages:
        fn = jax.jit(jax.vmap(lambda x, f=f: f(mx, x)))
        out[name] = _best_seconds(fn, d)
        d = fn(d)
    out["whole step (fused)"] = _best_seconds(jax.jit(jax.vmap(lambda x: mjx.step(mx, x))), d)
    return out


def bench_xml(xml: str | mujoco.MjSpec, batch: int, nsteps: int = 100, stages: bool = False) -> dict:
    """Steps a variant's MJCF exactly as `sim_data.bench.physics` steps home.xml, from `mug` initial states."""
    m = compile_xml(xml)
    base = S.load_model()
    idx = S.scene_index(base)
    keys = jax.random.split(jax.random.PRNGKey(0), batch)
    sample = jax.vmap(lambda k: sample_initial(TASKS["mug"].id, k, idx, base.qpos0, S.default_mocap_pos(base), False))
    qpos, mocap, _ = jax.jit(sample)(keys)
    engine = MjxEngine(m, batch)
    physics = jax.jit(engine.init)(_carry_qpos(qpos, base, m), mocap)
    ctrl = ready_controls(idx.robot, batch)
    ctrl = jnp.pad(jnp.asarray(ctrl), ((0, 0), (0, m.nu - ctrl.shape[1])))  # v0's leg actuators come last
    best, _, d = time_mjx(engine, physics, ctrl, mocap, nsteps)
    out = {"batch": batch, "steps_per_s": batch * nsteps / best, "ncon_slots": int(d._impl.contact.dist.shape[1]),
           "nefc": int(d._impl.efc_J.shape[1]), "nv": m.nv, "npair": m.npair}
    if stages:
        out["stage_ms"] = {k: 1e3 * v for k, v in stage_times(engine.mx, d).items()}
    return out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--batch", type=int, default=8192)
    p.add_argument("--only", default="all", help="comma list of substrings of variant names")
    p.add_argument("--stages", action="store_true", help="also time each stage of one step")
    p.add_argument("--dump", metavar="NAME", help="write the MJCF of the one variant matching NAME to --out and stop")
    a = p.parse_args(argv)
    if a.dump:
        found = variants(a.dump)
        if len(found) != 1:
            p.error(f"--dump {a.dump!r} matches {len(found)} variants: {list(found) or list(variants())}")
        xml = next(iter(found.values()))
        if isinstance(xml, mujoco.MjSpec):
            # MjSpec.to_xml (mujoco 4.0) writes the default classes empty: its text compiles to another model
            p.error(f"--dump {a.dump!r}: v0 is composed in MuJoCo (sim_data.sim.scene_v0) and has no MJCF text of "
                    "its own; compile it with scene_v0.spec().compile()")
        a.out.write_text(xml)
        return 0
    report = {"device": device_name(), "what": "MJX physics substeps/s of scene variants", "results": {}}
    for name, xml in variants(a.only).items():
        r = bench_xml(xml, a.batch, stages=a.stages)
        report["results"][name] = r
        print(name, json.dumps(r), flush=True)
        write_json_atomic(a.out, report)
    return 0


if __name__ == "__main__":
    sys.exit(run_cli(main))
