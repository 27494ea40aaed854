"""The scene's first design ("v0"), composed from `home.xml` with MuJoCo's own `mujoco.MjSpec`: the
home scene with the edits that the MJX speed work undid, kept so that `sim_data.bench.variants`
can time it beside the current design.

What v0 has that home.xml does not:

- box finger pads (4 contact points per pair) in place of the capsule pads and their visual boxes,
  drawn (group 0) rather than hidden;
- joint limits on the arms and the neck, the servos' control ranges inherited from them
  (neck pitch 1.0 rad instead of 1.2);
- jointed legs (hip, knee, ankle pitch; position servos appended after the base's);
- friction (condim 3) on the pads' contacts with the buttons and the counter, and two more support
  pairs (mug on the shelf board, cloth on the floor), each after its object's other supports;
- Newton with 4 iterations and 8 line-search iterations instead of 3 and 6.

    m = scene_v0.spec().compile()     # an MjModel; bodies, joints and actuators keep their names
"""

from __future__ import annotations

import mujoco

from sim_data.sim import robot as R
from sim_data.sim.scene import MODEL_PATH

SOLVER_ITERATIONS = (4, 8)  # iterations, ls_iterations
ARM_RANGES = {  # rad, in robot.ARM_JOINTS order
    "shoulder_pitch": (-3.1, 1.2), "shoulder_roll": (-1.6, 1.6), "shoulder_yaw": (-2.0, 2.0),
    "elbow": (-2.6, 0.05), "wrist_yaw": (-2.8, 2.8), "wrist_pitch": (-1.8, 1.8), "wrist_roll": (-1.6, 1.6),
}
NECK_RANGES = {"neck_yaw": (-1.2, 1.2), "neck_pitch": (-0.4, 1.0)}
# (body, joint, range in rad) of each leg, hip to ankle; every joint pitches about y
LEG_JOINTS = (("thigh", "hip_pitch", (-1.2, 1.2)), ("shin", "knee", (0.0, 2.0)), ("foot", "ankle", (-0.8, 0.8)))
LEG_KP = 150.0  # N m / rad, with forces within +-LEG_KP
BOX_PAD_HALF = (0.018, 0.006, 0.032)
BOX_PAD_Z = -0.03
BOX_PAD_Y = 0.006  # toward the finger's closing side: +y for finger a, -y for finger b
# object -> the support after whose pair v0 adds one more
EXTRA_SUPPORTS = {("mug", "floor"): ("mug", "shelf_board"), ("cloth", "counter"): ("cloth", "floor")}


def _box_pads(spec: mujoco.MjSpec) -> None:
    for side in R.SIDES:
        for finger, sign in (("a", 1.0), ("b", -1.0)):
            spec.delete(spec.geom(f"{side}_finger_{finger}_vis"))
            pad = spec.geom(f"{side}_finger_{finger}")
            pad.type = mujoco.mjtGeom.mjGEOM_BOX
            pad.size = BOX_PAD_HALF
            pad.pos = (0.0, sign * BOX_PAD_Y, BOX_PAD_Z)
            pad.alt.type = mujoco.mjtOrientation.mjORIENTATION_QUAT  # the capsule's zaxis no longer applies
            pad.group = 0


def _limited_servos(spec: mujoco.MjSpec) -> None:
    ranges = dict(NECK_RANGES, **{f"{side}_{j}": r for side in R.SIDES for j, r in ARM_RANGES.items()})
    for name, r in ranges.items():
        spec.joint(name).range = r
        spec.actuator(name).inheritrange = 1.0


def _jointed_legs(spec: mujoco.MjSpec) -> None:
    leg = spec.find_default("leg")
    for side in R.SIDES:
        for body, joint, r in LEG_JOINTS:
            spec.body(f"{side}_{body}").add_joint(default=leg, name=f"{side}_{joint}", axis=(0, 1, 0), range=r)
    for side in R.SIDES:
        for _, joint, _ in LEG_JOINTS:
            servo = spec.add_actuator(name=f"{side}_{joint}", target=f"{side}_{joint}", trntype=mujoco.mjtTrn.mjTRN_JOINT)
            servo.set_to_position(kp=LEG_KP)
            servo.forcerange = (-LEG_KP, LEG_KP)
            servo.inheritrange = 1.0


def _contacts(spec: mujoco.MjSpec) -> None:
    for pair in spec.pairs:
        pair.condim = 3
    # a pair is added at the end of the list: the supports are added again, in v0's order
    supports = [(p.geomname1, p.geomname2) for p in spec.pairs if "_finger_" not in p.geomname1]
    for pair in [p for p in spec.pairs if "_finger_" not in p.geomname1]:
        spec.delete(pair)
    for pair in supports:
        spec.add_pair(geomname1=pair[0], geomname2=pair[1])
        if pair in EXTRA_SUPPORTS:
            spec.add_pair(geomname1=EXTRA_SUPPORTS[pair][0], geomname2=EXTRA_SUPPORTS[pair][1])


def spec() -> mujoco.MjSpec:
    """A fresh MjSpec of the v0 scene (`.compile()` gives its MjModel)."""
    s = mujoco.MjSpec.from_file(str(MODEL_PATH))
    s.option.iterations, s.option.ls_iterations = SOLVER_ITERATIONS
    _box_pads(s)
    _limited_servos(s)
    _jointed_legs(s)
    _contacts(s)
    return s
