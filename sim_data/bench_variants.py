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
from pathlib import Path

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

from sim_data import scene as S
from sim_data.bench import device_name, ready_controls, time_mjx
from sim_data.engines import MjxEngine
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


def bench_xml(xml: str, batch: int, nsteps: int = 100) -> dict:
    """Steps a variant's MJCF exactly as `sim_data.bench` steps home.xml, from `mug` initial states."""
    with tempfile.NamedTemporaryFile("w", suffix=".xml", dir=ASSETS, delete=False) as f:
        f.write(xml)
    try:
        m = mujoco.MjModel.from_xml_path(f.name)
    finally:
        Path(f.name).unlink()
    base = S.load_model()
    idx = S.scene_index(base)
    keys = jax.random.split(jax.random.PRNGKey(0), batch)
    sample = jax.vmap(lambda k: sample_initial(TASKS["mug"], k, idx, base.qpos0, S.default_mocap_pos(base), False))
    qpos, mocap, _ = jax.jit(sample)(keys)
    engine = MjxEngine(m, batch)
    physics = jax.jit(engine.init)(_carry_qpos(qpos, base, m), mocap)
    ctrl = ready_controls(idx.robot, batch)
    ctrl = jnp.pad(jnp.asarray(ctrl), ((0, 0), (0, m.nu - ctrl.shape[1])))  # v0's leg actuators come last
    best, _, d = time_mjx(engine, physics, ctrl, mocap, nsteps)
    return {"batch": batch, "steps_per_s": batch * nsteps / best, "ncon_slots": int(d._impl.contact.dist.shape[1]),
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
