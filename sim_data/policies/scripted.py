"""Scripted policies (inverse kinematics over MuJoCo's Jacobians + a timed state machine) with a
`skill` knob, and open-loop action programs for controllability studies.

Every policy follows the project's protocol, batched and jittable:

    carry = policy.init_carry(params, obs, rng)
    action, carry = policy.act(params, obs, carry, rng)

with `params = {"skill": (B,) float}` for the scripted policies, and optionally `"grip": (B,) float`, a
factor on every closure of the episode's script (1: as scripted; the data generator's weak grips). Scripted policies read
privileged simulator state (`obs["qpos"]`, `obs["time"]`) and each episode's task from its task
state at reset (`TaskState.task_id`), so one ScriptedPolicy (and one compiled rollout) serves every
task. ScriptOrProgramPolicy is both kinds in one, chosen per episode by its parameters, so that the
data generator's scripted, program and play episodes share one compiled rollout too.

How skill degrades a policy (u = 1 - skill, drawn once per episode from the policy's rng):
- noisy perception: object positions off by N(0, (0.05 u)^2) per horizontal axis, yaw by
  N(0, (0.6 u)^2); for the arcade, each press is off by another N(0, (0.035 u)^2) per axis and
  the cued order is swapped with probability 0.5 u;
- timing jitter: every phase of the script stretched by exp(N(0, (0.25 u)^2));
- missed grasps: with probability 0.45 u the gripper closes 4-8 cm above the object;
- early release: with probability 0.5 u the hand opens at a random moment of the transport;
- airfryer: pull distance 0.13 - 0.08 u + N(0, (0.12 u)^2) m (short pulls fail, long ones hit the
  tray's end stop and may drag the body);
- step_back: target distance 0.6 - 0.3 u + N(0, (0.55 u)^2) m and a yaw-rate bias N(0, (0.6 u)^2) rad/s.
"""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from sim_data.sim import robot as R
from sim_data.sim import scene as S
from sim_data.sim import tasks as T
from sim_data.sim.engines import mjx
from sim_data.sim.env import cached_env
from sim_data.sim.rollout import record_policies

IK_DAMPING = 0.05
IK_ITERS = 2
IK_MAX_STEP = 0.04  # m of task-space error corrected per IK iteration
GRIP_BELOW_FINGERTIP = 0.01  # the grip site sits this far above the finger pads' lower edge


@struct.dataclass
class ScriptCarry:
    """Per-episode state of a scripted policy (leading axis B).

    Attributes:
      q_cmd: (B, 14) commanded arm joints (left, right), the IK's own configuration.
      times: (B, K) keyframe times; pos: (B, K, 3) right-grip keyframes; yaw: (B, K) hand yaw;
      closure: (B, K) right-hand closure at each keyframe.
      release_at: (B,) time after which the hand opens (inf: never).
      drive: (B, 2) step_back: target distance, yaw-rate bias.
      task_id: (B,) int32, the episode's task (`sim_data.sim.tasks.TaskState.task_id`).
    """

    q_cmd: jax.Array
    times: jax.Array
    pos: jax.Array
    yaw: jax.Array
    closure: jax.Array
    release_at: jax.Array
    drive: jax.Array
    task_id: jax.Array


class Kinematics:
    """Site poses and Jacobians of the two grip sites from qpos, with MJX's kinematics.

    Hashed by identity: `kinematics(model)` gives one per model, so that policies built on it
    compare equal and share their compiled programs.
    """

    def __init__(self, model):
        self._mjx = mjx
        self.mx = mjx.put_model(model, impl="jax")
        self.d0 = mjx.make_data(self.mx, impl="jax")
        self.idx = S.scene_index(model)

    def grip(self, qpos, side: int):
        """Pose and arm Jacobian of one grip site (side 0 left, 1 right), unbatched.

        Returns position (3,), rotation matrix (3, 3) and Jacobian (6, 7) over that arm's joints.
        """
        mjx = self._mjx
        d = mjx.com_pos(self.mx, mjx.kinematics(self.mx, self.d0.replace(qpos=qpos)))
        site = int(self.idx.grip_site[side])
        p, rot = d.site_xpos[site], d.site_xmat[site].reshape(3, 3)
        jacp, jacr = mjx.jac(self.mx, d, p, int(self.idx.hand_body[side]))
        dofs = self.idx.robot.arm_qvel[7 * side : 7 * side + 7]
        return p, rot, jnp.concatenate([jacp[dofs].T, jacr[dofs].T], axis=0)


@functools.lru_cache(maxsize=8)
def kinematics(model) -> Kinematics:
    """The Kinematics of model, one per model object."""
    return Kinematics(model)


def _yaw_down(yaw):
    """Rotation (3, 3) of a hand pointing down, pinch axis (hand y) turned by yaw about world z."""
    c, s = jnp.cos(yaw), jnp.sin(yaw)
    return jnp.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def ik_step(kin: Kinematics, qpos, q_arm, target_p, target_yaw, side: int = 1):
    """One damped-least-squares IK update of one arm toward a hand-down pose; unbatched.

    Args:
      qpos: (nq,) measured configuration (base and everything but the arm).
      q_arm: (7,) the arm's current commanded joints.
      target_p: (3,) grip-site target; target_yaw: () hand yaw.
    Returns:
      (7,) updated arm joints, clipped to the joint ranges.
    """
    adr = kin.idx.robot.arm_qpos[7 * side : 7 * side + 7]
    p, rot, jac = kin.grip(qpos.at[adr].set(q_arm), side)
    e_pos = target_p - p
    e_pos = e_pos * jnp.minimum(1.0, IK_MAX_STEP / (jnp.linalg.norm(e_pos) + 1e-9))
    rot_t = _yaw_down(target_yaw)
    e_rot = 0.5 * jnp.sum(jnp.cross(rot.T, rot_t.T), axis=0)
    e = jnp.concatenate([e_pos, 0.5 * e_rot])
    jj = jac @ jac.T + IK_DAMPING**2 * jnp.eye(6)
    dq = jac.T @ jnp.linalg.solve(jj, e)
    low, high = kin.idx.robot.action_low[7 * side : 7 * side + 7], kin.idx.robot.action_high[7 * side : 7 * side + 7]
    return jnp.clip(q_arm + dq, low, high)


def _smoothstep(x):
    x = jnp.clip(x, 0.0, 1.0)
    return x * x * (3 - 2 * x)


def keyframe_target(t, times, pos, yaw, closure):
    """Interpolated (grip position (3,), yaw (), closure ()) at time t; unbatched."""
    k = jnp.clip(jnp.searchsorted(times, t, side="right") - 1, 0, times.shape[0] - 2)
    a = _smoothstep((t - times[k]) / jnp.maximum(times[k + 1] - times[k], 1e-6))
    lerp = lambda x: x[k] + (x[k + 1] - x[k]) * a
    return lerp(pos), lerp(yaw), lerp(closure)


def _pinch_yaw(obj_yaw):
    """Hand yaw for a pinch across a box's y faces: box faces repeat every pi/2, take the nearest to 0."""
    return jnp.mod(obj_yaw + jnp.pi / 4, jnp.pi / 2) - jnp.pi / 4


# keyframes of the longest script (wipe); a shorter one is led by copies of its first keyframe: they
# share its time 0, from which keyframe_target interpolates past the last of them, so the script
# plays exactly as unpadded, and every task's carry has one shape
MAX_KEYFRAMES = 11


def _script(task: str, qpos, ts: T.TaskState, noise, idx: S.SceneIndex, hand0):
    """Keyframes of one task's script for one episode.

    Args:
      task: a task name with a script (not step_back, which drives instead).
      qpos: (nq,) state at reset; ts: unbatched TaskState; noise: dict of this episode's
        perception and grasp errors; hand0: (3,) right grip at reset.
    Returns:
      times (K,), pos (K, 3), yaw (K,), closure (K,), and (t0, t1) of the transport phase.
    """
    ct = S.COUNTER_TOP
    dxy = noise["xy"]
    grasp_up = noise["grasp_up"]

    def obj(adr):
        p = qpos[adr : adr + 3]
        return p.at[:2].add(dxy), T.quat_yaw(qpos[adr + 3 : adr + 7]) + noise["yaw"]

    if task == "mug":
        p, y = obj(idx.mug_qpos)
        yaw = _pinch_yaw(y)
        g = jnp.array([p[0], p[1], p[2] + 0.01 + grasp_up])
        up = g.at[2].set(p[2] + 0.13)
        lift = g.at[2].set(p[2] + 0.17)
        keys = [(0.0, hand0, 0.0, 0.0), (1.0, up, yaw, 0.0), (1.8, g, yaw, 0.0), (2.3, g, yaw, 1.0),
                (3.3, lift, yaw, 1.0), (6.0, lift, yaw, 1.0)]
        transport = (2.6, 4.2)
    elif task == "shelf":
        p, y = obj(idx.block_qpos)
        yaw = _pinch_yaw(y)
        g = jnp.array([p[0], p[1], p[2] + 0.02 + grasp_up])
        up = g.at[2].set(p[2] + 0.15)
        carry_z = S.SHELF_BOARD[4] + 0.08 + 0.065
        place_z = S.SHELF_BOARD[4] + 0.008 + 0.065
        tx, ty = T.SHELF_TARGET_XY
        lifted = g.at[2].set(carry_z)
        over = jnp.array([tx, ty, carry_z]) + jnp.append(dxy, 0.0)
        keys = [(0.0, hand0, 0.0, 0.0), (1.0, up, yaw, 0.0), (1.7, g, yaw, 0.0), (2.1, g, yaw, 1.0),
                (3.1, lifted, yaw, 1.0), (4.6, over, 0.0, 1.0), (5.4, over.at[2].set(place_z), 0.0, 1.0),
                (5.8, over.at[2].set(place_z), 0.0, 0.0), (6.6, over.at[2].set(carry_z + 0.05), 0.0, 0.0),
                (9.0, over.at[2].set(carry_z + 0.05), 0.0, 0.0)]
        transport = (2.4, 5.2)
    elif task == "airfryer":
        f = qpos[idx.fryer_qpos : idx.fryer_qpos + 3].at[:2].add(dxy)
        h = jnp.array([f[0] - 0.206, f[1], f[2] - 0.02 + grasp_up])
        yaw = -jnp.pi / 2 + noise["yaw"] * 0.5
        pull = h.at[0].add(-noise["pull"])
        keys = [(0.0, hand0, 0.0, 0.0), (1.2, h.at[2].add(0.12), yaw, 0.35), (2.0, h, yaw, 0.35), (2.5, h, yaw, 1.0),
                (4.5, pull, yaw, 1.0), (5.0, pull, yaw, 0.3), (6.0, pull.at[2].add(0.1), yaw, 0.3),
                (7.0, pull.at[2].add(0.1), yaw, 0.3)]
        transport = (2.8, 4.4)
    elif task == "wipe":
        p, y = obj(idx.cloth_qpos)
        yaw = _pinch_yaw(y)
        g = jnp.array([p[0], p[1], ct + GRIP_BELOW_FINGERTIP + 0.004 + grasp_up])
        px, py = ts.patch[0] + noise["patch"][0], ts.patch[1] + noise["patch"][1]
        z = g[2]
        a0 = jnp.array([px - 0.035, py - 0.09, z])
        a1 = jnp.array([px - 0.035, py + 0.09, z])
        b1 = jnp.array([px + 0.035, py + 0.09, z])
        b0 = jnp.array([px + 0.035, py - 0.09, z])
        keys = [(0.0, hand0, 0.0, 0.0), (1.0, g.at[2].add(0.1), yaw, 0.0), (1.6, g, yaw, 0.0), (2.0, g, yaw, 1.0),
                (3.0, a0, yaw, 1.0), (4.8, a1, yaw, 1.0), (5.4, b1, yaw, 1.0), (7.2, b0, yaw, 1.0),
                (7.6, b0, yaw, 0.0), (8.4, b0.at[2].add(0.1), yaw, 0.0), (10.0, b0.at[2].add(0.1), yaw, 0.0)]
        transport = (2.2, 7.0)
    elif task == "arcade":
        seq = jnp.where(noise["swap"], ts.sequence[::-1], ts.sequence)
        btn = jnp.array(T.BUTTON_XY)
        top = ct + 0.024  # button tops
        press_z = top - 0.013 + GRIP_BELOW_FINGERTIP
        hover_z = top + 0.10

        def at(i, z):
            b = btn[seq[i]] + dxy + noise["press"][i]
            return jnp.array([b[0], b[1], z])

        keys = [(0.0, hand0, 0.0, 1.0), (1.2, at(0, hover_z), 0.0, 1.0), (1.8, at(0, press_z), 0.0, 1.0),
                (2.3, at(0, hover_z), 0.0, 1.0), (3.3, at(1, hover_z), 0.0, 1.0), (3.9, at(1, press_z), 0.0, 1.0),
                (4.4, at(1, hover_z), 0.0, 1.0), (8.0, at(1, hover_z), 0.0, 1.0)]
        transport = (jnp.inf, jnp.inf)
    else:
        raise ValueError(f"no script for task {task!r}")
    keys = [keys[0]] * (MAX_KEYFRAMES - len(keys)) + keys
    times = jnp.array([k[0] for k in keys]) * noise["stretch"]
    pos = jnp.stack([jnp.asarray(k[1], jnp.float32) for k in keys])
    yaw = jnp.stack([jnp.asarray(k[2], jnp.float32) for k in keys])
    closure = jnp.array([k[3] for k in keys], jnp.float32)
    t0, t1 = transport
    return times, pos, yaw, closure, (t0 * noise["stretch"], t1 * noise["stretch"])


@dataclasses.dataclass(frozen=True)
class ScriptedPolicy:
    """The scripted policies of every task, with the skill knob described in the module doc; each
    episode plays the script of its own task (its TaskState.task_id at reset).

    Args:
      kin: the Kinematics of the home scene (`kinematics(model)`).
    """

    kin: Kinematics

    @classmethod
    def create(cls, task: str | None = None, model=None):
        """The policy over model (default: `sim_data.sim.scene.load_model()`). task, if given, is only
        checked to be a task's name: the policy plays every task, each episode its own."""
        if task is not None:
            T.get_task(task)
        return cls(kinematics(model if model is not None else S.load_model()))

    def _noise(self, rng, skill):
        u = 1.0 - jnp.clip(skill, 0.0, 1.0)
        k = jax.random.split(rng, 10)
        n = lambda kk, shape=(): jax.random.normal(kk, shape)
        missed = jax.random.uniform(k[3]) < 0.45 * u
        return {
            "xy": 0.05 * u * n(k[0], (2,)),
            "yaw": 0.6 * u * n(k[1]),
            "stretch": jnp.exp(0.25 * u * n(k[2])),
            "grasp_up": jnp.where(missed, jax.random.uniform(k[4], minval=0.04, maxval=0.08), 0.0),
            "release": jax.random.uniform(k[5]) < 0.5 * u,
            "release_frac": jax.random.uniform(k[6]),
            "swap": jax.random.uniform(k[7]) < 0.5 * u,
            "press": 0.035 * u * n(jax.random.fold_in(rng, 3), (2, 2)),
            "patch": 0.04 * u * n(k[8], (2,)),
            "pull": jnp.maximum(0.0, 0.13 - 0.08 * u + 0.12 * u * n(k[9])),
            "distance": 0.6 - 0.3 * u + 0.55 * u * n(jax.random.fold_in(rng, 1)),
            "yaw_bias": 0.6 * u * n(jax.random.fold_in(rng, 2)),
        }

    def _plan(self, task_id, qpos, ts, noise, hand0):
        """Keyframes (times (K,), pos (K, 3), yaw (K,), closure (K,)) and the transport phase (t0, t1)
        of the script of task task_id (() int32); K = MAX_KEYFRAMES. Every task's script is planned
        and the episode's own selected (it compiles faster than a lax.switch, which vmap turns into
        the same selection)."""
        def plan(name):
            if name == "step_back":  # drives: the hand stays where it is
                still = jnp.zeros(MAX_KEYFRAMES)
                inf = jnp.float32(jnp.inf)
                return still, jnp.broadcast_to(hand0, (MAX_KEYFRAMES, 3)), still, still, (inf, inf)
            return _script(name, qpos, ts, noise, self.kin.idx, hand0)

        return T.select_task(task_id, [plan(name) for name in T.TASK_NAMES])

    def _init_one(self, skill, qpos, ts, rng, grip=None):
        idx = self.kin.idx
        noise = self._noise(rng, skill)
        q_cmd = qpos[idx.robot.arm_qpos]
        hand0, _, _ = self.kin.grip(qpos, 1)
        times, pos, yaw, closure, (t0, t1) = self._plan(ts.task_id, qpos, ts, noise, hand0)
        if grip is not None:
            closure = closure * grip
        release_at = jnp.where(noise["release"], t0 + (t1 - t0) * noise["release_frac"], jnp.inf)
        drive = jnp.stack([noise["distance"], noise["yaw_bias"]])
        return ScriptCarry(q_cmd=q_cmd, times=times, pos=pos, yaw=yaw, closure=closure, release_at=release_at,
                           drive=drive, task_id=ts.task_id)

    def init_carry(self, params, obs, task_state, rng):
        """Draws each episode's imperfections and plans its keyframes.

        Args:
          params: {"skill": (B,)}, optionally with "grip": (B,) (the module doc); obs: the
            environment's observation at reset; task_state: the env's TaskState at reset (task, cue
            order, patch); rng: one PRNG key.
        """
        b = obs["qpos"].shape[0]
        keys = jax.random.split(rng, b)
        grip = (params["grip"],) if "grip" in params else ()
        return jax.vmap(self._init_one)(params["skill"], obs["qpos"], task_state, keys, *grip)

    @staticmethod
    def _drive_action(t, c: ScriptCarry, action):
        """step_back: drive back the episode's distance at 0.3 m/s, arms held."""
        dist, bias = c.drive[0], c.drive[1]
        speed = jnp.where(t < jnp.abs(dist) / 0.3, -0.3 * jnp.sign(dist), 0.0)
        w = jnp.where(speed != 0.0, bias, 0.0)
        action = action.at[R.FORWARD_SPEED].set(speed).at[R.YAW_RATE].set(w)
        return action.at[R.ARMS].set(c.q_cmd)

    def _reach_action(self, qpos, t, c: ScriptCarry, action):
        """The scripted tasks: the right hand follows the keyframes through IK. Returns (action, q_cmd (14,))."""
        target, yaw, closure = keyframe_target(t, c.times, c.pos, c.yaw, c.closure)
        closure = jnp.where(t >= c.release_at, 0.0, closure)
        # a loop, not unrolled: each iteration is the whole scene's kinematics, which would compile once per copy
        q_right = jax.lax.fori_loop(0, IK_ITERS, lambda _, q: ik_step(self.kin, qpos, q, target, yaw, side=1),
                                    c.q_cmd[7:])
        q_cmd = c.q_cmd.at[7:].set(q_right)
        return action.at[R.ARMS].set(q_cmd).at[R.RIGHT_HAND].set(closure), q_cmd

    def _act_one(self, qpos, t, c: ScriptCarry):
        action = jnp.zeros(R.ACTION_DIM)
        action = action.at[R.NECK].set(jnp.array([0.0, S.READY_NECK_PITCH]))
        reach, q_cmd = self._reach_action(qpos, t, c, action)
        driving = c.task_id == T.TASK_NAMES.index("step_back")
        action = jnp.where(driving, self._drive_action(t, c, action), reach)
        return action, c.replace(q_cmd=jnp.where(driving, c.q_cmd, q_cmd))

    def act(self, params, obs, carry, rng):
        """Batched actions (B, 20) and the updated carry, from privileged observations."""
        del params, rng
        return jax.vmap(self._act_one)(obs["qpos"], obs["time"], carry)


# ---- open-loop action programs for controllability studies ---------------------------------------
PROGRAMS = ("reach_mug", "wipe_counter", "step_backwards", "air_guitar")


def action_program(name: str, num_steps: int) -> np.ndarray:
    """A fixed action sequence (num_steps, 20) float32 at the control rate, from the ready pose.

    `reach_mug`: the right hand reaches forward and down toward the mug's nominal place and closes;
    `wipe_counter`: the right hand sweeps left and right low over the counter; `step_backwards`:
    the base drives back 0.3 m/s for 2 s; `air_guitar`: both arms strum and fret, the head nods.
    """
    if name not in PROGRAMS:
        raise ValueError(f"unknown program {name!r}; choose one of {', '.join(PROGRAMS)}")
    t = np.arange(num_steps, dtype=np.float32) * T.CONTROL_DT
    a = np.zeros((num_steps, R.ACTION_DIM), np.float32)
    a[:, R.ARMS] = np.concatenate([S.READY_ARM, S.READY_ARM])
    a[:, R.NECK] = [0.0, S.READY_NECK_PITCH]
    ramp = np.clip(t / 1.5, 0, 1)[:, None]
    right = a[:, R.RIGHT_ARM]
    if name == "reach_mug":
        reach = np.array([-0.35, 0.0, 0.0, -1.2, 0.0, 1.1, 0.0], np.float32)
        a[:, R.RIGHT_ARM] = right + ramp * (reach - right)
        a[:, R.RIGHT_HAND] = np.clip((t - 2.0) / 0.5, 0, 1)
    elif name == "wipe_counter":
        low = np.array([-0.3, 0.0, 0.0, -1.3, 0.0, 1.3, 0.0], np.float32)
        a[:, R.RIGHT_ARM] = right + ramp * (low - right)
        a[:, R.RIGHT_ARM.start + 1] = ramp[:, 0] * 0.35 * np.sin(2 * np.pi * 0.5 * t)
        a[:, R.RIGHT_HAND] = 1.0
    elif name == "step_backwards":
        a[:, R.FORWARD_SPEED] = np.where(t < 2.0, -0.3, 0.0)
    elif name == "air_guitar":
        strum = 0.4 * np.sin(2 * np.pi * 2.0 * t)
        a[:, R.RIGHT_ARM.start + 3] = S.READY_ARM[3] + 0.3 + 0.3 * strum
        a[:, R.RIGHT_ARM.start + 4] = strum
        a[:, R.LEFT_ARM.start + 0] = -0.8
        a[:, R.LEFT_ARM.start + 1] = 0.5
        a[:, R.LEFT_ARM.start + 3] = -1.2 + 0.25 * np.sin(2 * np.pi * 0.7 * t)
        a[:, R.NECK.start + 1] = S.READY_NECK_PITCH + 0.15 * np.sin(2 * np.pi * 1.0 * t)
        a[:, R.LEFT_HAND] = 0.5 + 0.5 * np.sin(2 * np.pi * 1.5 * t)
    return a


# per-joint amplitude (rad) of play's arm targets around the ready pose: shoulder pitch, roll, yaw,
# elbow, wrist yaw, pitch, roll
PLAY_ARM_AMPLITUDE = np.array([0.9, 0.5, 0.6, 1.0, 0.8, 0.6, 0.6], np.float32)


PLAY_STYLES = ("eased", "stepped")


PLAY_NOD_HZ = (0.5, 2.0)  # a nodding play episode's neck oscillation: its frequency
PLAY_NOD_RAD = (0.05, 0.2)  # and its amplitude on each neck joint it moves


def play_program(seed: int, num_steps: int, style: str | None = None, nod: float = 0.0, bounds=None) -> np.ndarray:
    """Random "play" actions (num_steps, 20) float32 from the ready pose, a function of seed.

    Each arm either rests or moves through random joint targets (sometimes with a 0.5 to 2 Hz
    oscillation on one joint); hands open and close at random; the neck looks around; the base
    drives forward or back and turns in random segments. Style "eased" glides between knots 0.8 to
    2.5 s apart; "stepped" holds each knot and jumps to the next (knots half as far apart), so
    that motions start and stop at instants the past does not foretell and only the action
    explains. style None draws one from the seed. Play covers what the scripted tasks leave out,
    so a world model learns what every action does. nod: the chance that the neck also oscillates
    (PLAY_NOD_HZ, PLAY_NOD_RAD; the pitch, and the yaw half the time) over its knots, as a head that
    nods or shakes: eased knots never move it faster than one target a second, stepped ones two. Drawn
    after everything else, so an episode's other actions are those of nod 0. bounds: the actions' (low
    (20,), high (20,)), within which a nod's amplitude is kept (a sine clipped at the neck's limit would
    flatten into a plateau); None: uncapped.
    """
    rng = np.random.default_rng(seed)
    style = style or PLAY_STYLES[int(rng.integers(len(PLAY_STYLES)))]
    if style not in PLAY_STYLES:
        raise ValueError(f"style must be one of {PLAY_STYLES}, got {style!r}")
    stepped = style == "stepped"
    t = np.arange(num_steps, dtype=np.float32) * T.CONTROL_DT
    a = np.zeros((num_steps, R.ACTION_DIM), np.float32)

    def eased(values, gap):
        """Knot values (n, k), one every `gap` s from t=0, into (num_steps, k): held, or eased (smoothstep)."""
        u = t / gap
        if stepped:
            return values[np.minimum(u.astype(int), len(values) - 1)]
        i = np.minimum(u.astype(int), len(values) - 2)
        f = (u - i)[:, None]
        f = f * f * (3 - 2 * f)
        return values[i] * (1 - f) + values[i + 1] * f

    def knots(low, high):
        """A random knot spacing in [low, high] s (halved when stepped) and the number of knots that
        cover the episode."""
        gap = rng.uniform(low, high) * (0.5 if stepped else 1.0)
        return int(np.ceil(t[-1] / gap)) + 2, gap

    for arm in (R.LEFT_ARM, R.RIGHT_ARM):
        if rng.random() < 0.3:
            a[:, arm] = S.READY_ARM
            continue
        n, gap = knots(0.8, 2.0)
        offsets = rng.uniform(-1, 1, (n, 7)).astype(np.float32) * PLAY_ARM_AMPLITUDE
        offsets[0] = 0.0  # start from the ready pose
        a[:, arm] = S.READY_ARM + eased(offsets, gap)
        if rng.random() < 0.4:
            j = arm.start + int(rng.integers(7))
            a[:, j] += 0.3 * np.sin(2 * np.pi * rng.uniform(0.5, 2.0) * t + rng.uniform(0, 2 * np.pi))
    n, gap = knots(1.0, 2.5)
    neck = np.stack([rng.uniform(-0.5, 0.5, n), rng.uniform(-0.3, 0.25, n)], -1).astype(np.float32)
    neck[0] = 0.0
    a[:, R.NECK] = np.array([0.0, S.READY_NECK_PITCH], np.float32) + eased(neck * (rng.random() < 0.6), gap)
    n, gap = knots(0.6, 1.5)
    a[:, R.HAND_CLOSURE] = eased((rng.random((n, 2)) < 0.5).astype(np.float32), gap)
    n, gap = knots(1.0, 2.5)
    drive = rng.uniform(-1, 1, (n, 2)).astype(np.float32) * [0.35, 0.6] * (rng.random((n, 2)) < 0.5)
    drive[0] = 0.0
    a[:, R.DRIVE] = eased(drive * (rng.random() < 0.7), gap)
    if nod > 0.0 and rng.random() < nod:
        joints = [R.NECK.start + 1] + ([R.NECK.start] if rng.random() < 0.5 else [])
        for j in joints:
            # from the episode's first step, up or down: the neck still starts at its ready pose
            hz, amp, phase = rng.uniform(*PLAY_NOD_HZ), rng.uniform(*PLAY_NOD_RAD), np.pi * (rng.random() < 0.5)
            wave = np.sin(2 * np.pi * hz * t + phase)
            if bounds is not None:  # the largest amplitude at which no step passes a limit
                up, down = wave > 1e-6, wave < -1e-6
                room = np.concatenate([(bounds[1][j] - a[up, j]) / wave[up], (a[down, j] - bounds[0][j]) / -wave[down]])
                amp = float(np.clip(room.min(initial=amp), 0.0, amp))
            a[:, j] += amp * wave
    return a


def play_params(seeds, num_steps: int, low, high, nod: float = 0.0) -> dict:
    """ProgramPolicy parameters for one play episode per seed (play_program, its chance to nod), clipped to
    the action bounds (20,) (`RobotIndex.action_low`, `action_high`), so that the recorded actions are the
    ones applied."""
    bounds = (np.asarray(low), np.asarray(high))
    return {"table": np.clip(np.stack([play_program(int(s), num_steps, nod=nod, bounds=bounds) for s in seeds]),
                             low, high)}


@dataclasses.dataclass(frozen=True)
class ProgramPolicy:
    """Action programs as a policy of the project's protocol: it ignores the observation and plays
    row t of its episode's program at control step t (the last row after the end).

    params: {"table": (B, num_steps, 20)}, e.g. `program_params(names, num_steps)`; one compiled
    rollout serves every program, and, with the tables padded to one length (`pad_programs`, e.g.
    to `sim_data.sim.tasks.MAX_EPISODE_STEPS`), every task.
    """

    num_steps: int

    def init_carry(self, params, obs, task_state, rng):
        del params, task_state, rng
        return jnp.zeros((obs["qpos"].shape[0],), jnp.int32)

    def act(self, params, obs, carry, rng):
        del obs, rng
        table = params["table"]
        rows = jnp.arange(table.shape[0])
        return table[rows, jnp.minimum(carry, self.num_steps - 1)], carry + 1


def simulate_actions(task: str, actions, reset_keys, engine: str) -> np.ndarray:
    """The simulator's outcomes of given action sequences played open loop (ProgramPolicy): actions
    (P*n, T, 20), row i*n + e from initial state e of reset_keys (n, 2) (a batch's layout), T the
    task's episode steps. Returns (P, n) bool."""
    actions = np.asarray(actions, np.float32)
    env = cached_env(task, len(actions), engine, False)
    if actions.shape[1] != env.episode_steps:
        raise ValueError(f"{actions.shape[1]} actions an episode for {task}'s {env.episode_steps} steps")
    played = ProgramPolicy(env.episode_steps)
    outcome, _ = record_policies(env, played, {"table": jax.device_put(actions)}, reset_keys, jax.random.PRNGKey(0))
    return outcome


# ---- scripts and programs as one policy, chosen per episode by data ------------------------------

@dataclasses.dataclass(frozen=True)
class ScriptOrProgramPolicy:
    """The scripted policies and the action programs (and random play) as one policy whose behaviour
    each episode's parameters choose: row b plays action table `table[b]` (as ProgramPolicy) where
    `program[b]`, else the script of its task at skill `skill[b]` (as ScriptedPolicy). Both kinds
    then share one parameter structure, one carry and so one compiled rollout per engine and batch
    size, whichever kind or mixture of kinds a batch holds.

    params: {"program": (B,) bool, "skill": (B,) float32, "grip": (B,) float32, "table": (B,
    num_steps, 20) float32} (`script_or_program_params`). The scripted rows draw their imperfections exactly as
    ScriptedPolicy does from the same rng, and program rows play their tables as ProgramPolicy does,
    so each row's actions are those of its own kind's policy. A batch without scripted rows skips
    the script's inverse kinematics (a `lax.cond` on the batch, which compiles both branches).

    Args:
      script: the ScriptedPolicy. program: the ProgramPolicy (its num_steps: the tables' rows).
    """

    script: ScriptedPolicy
    program: ProgramPolicy

    @classmethod
    def create(cls, num_steps: int, model=None):
        """The policy over model (default: `sim_data.sim.scene.load_model()`) with tables of num_steps rows."""
        return cls(ScriptedPolicy.create(model=model), ProgramPolicy(num_steps))

    def init_carry(self, params, obs, task_state, rng):
        """{"script": ScriptCarry (leading axis B), "step": (B,) int32 the program's row}; the script's
        carry is planned for every row (the program rows' is never read), from rng as ScriptedPolicy's."""
        return {"script": self.script.init_carry(params, obs, task_state, rng),
                "step": self.program.init_carry(params, obs, task_state, rng)}

    def act(self, params, obs, carry, rng):
        """Batched actions (B, 20): each row's table row or scripted action; and the updated carry."""
        played, step = self.program.act(params, obs, carry["step"], rng)
        program = params["program"]
        scripted, script = jax.lax.cond(
            jnp.all(program), lambda: (played, carry["script"]),
            lambda: self.script.act(params, obs, carry["script"], rng))
        return jnp.where(program[:, None], played, scripted), {"script": script, "step": step}


def script_or_program_params(skill, table, program, grip=None) -> dict:
    """ScriptOrProgramPolicy parameters of B episodes from skill (B,), table (B, num_steps, 20),
    program (B,) bool (the rows that play their table rather than their task's script) and grip (B,),
    the factor on a scripted row's closures (default 1: as scripted)."""
    grip = np.ones(len(skill), np.float32) if grip is None else np.asarray(grip, np.float32)
    return {"program": np.asarray(program, bool), "skill": np.asarray(skill, np.float32), "grip": grip,
            "table": np.asarray(table, np.float32)}


def program_params(names, num_steps: int) -> dict:
    """ProgramPolicy parameters for one episode per program name."""
    return {"table": np.stack([action_program(n, num_steps) for n in names])}


def pad_programs(params: dict, rows: int) -> dict:
    """ProgramPolicy parameters with each table (B, n, 20) lengthened to (B, rows, 20) by repeating
    its last row, which the policy plays after the end anyway: episodes of any length up to `rows`
    then share one compiled rollout (`ProgramPolicy(rows)`)."""
    table = np.asarray(params["table"])
    if table.shape[1] > rows:
        raise ValueError(f"a program of {table.shape[1]} steps does not fit {rows} rows")
    tail = np.repeat(table[:, -1:], rows - table.shape[1], axis=1)
    return {**params, "table": np.concatenate([table, tail], axis=1)}
