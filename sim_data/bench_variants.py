"""MJX speed of model-design variants of the full scene, side by side (GPU notes for the README).

    python -m sim_data.bench_variants --out runs/bench/mjx_variants.json --batch 8192

Each variant changes one thing about `home.xml` (contacts, limits, solver settings) and is
stepped exactly as `sim_data.bench` steps the real model.
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

from sim_data import robot as R
from sim_data import scene as S
from sim_data.bench import device_name
from sim_data.success_table import write_json_atomic
from sim_data.tasks import TASKS, sample_initial

ASSETS = Path(__file__).parent / "assets"


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


def variants(which: str = "all") -> dict[str, str]:
    """name -> MJCF text. Names say what each variant changes and, where it broke the tasks, how."""
    home = S.MODEL_PATH.read_text()
    out = {
        "v0: box fingers (4 contacts/pair), friction everywhere, limits on all joints, jointed legs, Newton 4/8":
            (ASSETS / "variant_v0_box_fingers.xml").read_text(),
        "home.xml: capsule pads, condim-1 buttons/counter, servo joints unlimited, static legs, Newton 3/6": home,
        "home.xml, Newton 4/8": _edit(home, iterations=4, ls_iterations=8),
        "home.xml, Newton 2/4 (breaks tasks: wipe 0/8, shelf 3/8 at skill 1)": _edit(home, iterations=2, ls_iterations=4),
        "home.xml without left-hand pairs (left hand cannot grasp)": _no_left_pairs(home),
        "home.xml, sphere pads (breaks shelf: the block pivots in the pinch)": _sphere_pads(home),
        "home.xml, CG 2/4 (unstable: the cloth sinks through the counter at rest)":
            _edit(home.replace('solver="Newton"', 'solver="CG"'), iterations=2, ls_iterations=4),
        "home.xml, elliptic cones, all condim 3": home.replace('cone="pyramidal"', 'cone="elliptic"').replace(' condim="1"', ""),
    }
    if which != "all":
        out = {k: v for k, v in out.items() if any(w in k for w in which.split(","))}
    return out


def bench_xml(xml: str, batch: int, nsteps: int = 100) -> dict:
    with tempfile.NamedTemporaryFile("w", suffix=".xml", dir=ASSETS, delete=False) as f:
        f.write(xml)
    try:
        m = mujoco.MjModel.from_xml_path(f.name)
    finally:
        Path(f.name).unlink()
    from mujoco import mjx

    base = S.load_model()
    mx = mjx.put_model(m, impl="jax")
    idx = S.scene_index(base)
    qpos0 = np.asarray(base.qpos0, np.float32)
    mocap0 = np.asarray(m.body_pos[m.body_mocapid >= 0][np.argsort(m.body_mocapid[m.body_mocapid >= 0])], np.float32)
    keys = jax.random.split(jax.random.PRNGKey(0), batch)
    qpos, mocap, _ = jax.jit(jax.vmap(lambda k: sample_initial(TASKS["mug"], k, idx, qpos0, mocap0, False)))(keys)

    def one(q, mp):
        return mjx.forward(mx, mjx.make_data(mx, impl="jax").replace(qpos=q, mocap_pos=mp))

    if m.nq != base.nq:  # a variant with other joints: carry positions over by joint name
        cols = np.tile(np.asarray(m.qpos0, np.float32), (batch, 1))
        for j in range(m.njnt):
            name, width = m.joint(j).name, {0: 7, 1: 4, 2: 1, 3: 1}[int(m.jnt_type[j])]
            try:
                src = base.joint(name).qposadr[0]
            except KeyError:
                continue
            dst = m.jnt_qposadr[j]
            cols[:, dst : dst + width] = np.asarray(qpos[:, src : src + width])
        qpos = jnp.asarray(cols)
    d = jax.jit(jax.vmap(one))(qpos, mocap)
    a = np.zeros((batch, R.ACTION_DIM), np.float32)
    a[:, R.ARMS] = np.concatenate([S.READY_ARM, S.READY_ARM]) + 0.1 * np.random.default_rng(0).standard_normal((batch, 14))
    ctrl = R.action_to_ctrl(jnp.asarray(a), jnp.zeros(batch), idx.robot)
    d = d.replace(ctrl=jnp.pad(ctrl, ((0, 0), (0, m.nu - ctrl.shape[1]))))  # v0's leg actuators come last
    run = jax.jit(lambda dd: jax.lax.scan(lambda x, _: (jax.vmap(lambda y: mjx.step(mx, y))(x), None), dd, None, length=nsteps)[0])
    d = jax.block_until_ready(run(d))
    t0 = time.perf_counter()
    d = jax.block_until_ready(run(d))
    dt = time.perf_counter() - t0
    return {"batch": batch, "steps_per_s": batch * nsteps / dt, "ncon_slots": int(d._impl.contact.dist.shape[1]),
            "nefc": int(d._impl.efc_J.shape[1]), "nv": m.nv, "npair": m.npair}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--batch", type=int, default=8192)
    p.add_argument("--only", default="all", help="comma list of substrings of variant names")
    a = p.parse_args(argv)
    report = {"device": device_name(), "what": "MJX physics substeps/s of scene variants", "results": {}}
    for name, xml in variants(a.only).items():
        r = bench_xml(xml, a.batch)
        report["results"][name] = r
        print(name, json.dumps(r), flush=True)
        write_json_atomic(a.out, report)
    return 0


if __name__ == "__main__":
    sys.exit(main())
