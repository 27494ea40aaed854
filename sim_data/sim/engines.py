"""Two physics engines over one MJCF: MuJoCo's C engine (`cpu`) and MJX (`mjx`, impl="jax").

An engine turns initial positions into its physics state and advances a batch of simulations by
a number of substeps under constant controls. Everything else (tasks, actions, observations)
is shared JAX code in `sim_data.sim.env`.
"""

from __future__ import annotations

import contextlib
import functools
import io
import os
from typing import Any

import jax
import jax.numpy as jnp
import mujoco
import mujoco.batch  # noqa: F401  (a submodule, not imported by `import mujoco`)
import numpy as np
from flax import struct

# mujoco.mjx prints two lines when its optional Warp backend is absent; the project runs MJX's JAX
# implementation, for which Warp plays no part
with contextlib.redirect_stdout(io.StringIO()):
    from mujoco import mjx

ENGINES = ("cpu", "mjx")
# raised whenever an engine's physics or a rollout's record changes what it simulates or holds (the `mjx`
# engine's implicit gyroscopic term of free bodies is revision 2; actions recorded as the robot applies
# them, a NaN as 0, revision 3): outcomes cached under an older revision are simulated again
PHYSICS_REVISION = 3
POSE_FIELDS = ("geom_xpos", "geom_xmat", "cam_xpos", "cam_xmat")


def default_engine() -> str:
    """`mjx` where JAX sees a GPU, `cpu` otherwise."""
    return "mjx" if any(d.platform == "gpu" for d in jax.devices()) else "cpu"


@struct.dataclass
class CpuPhysics:
    """The `cpu` engine's state.

    Attributes:
      rows: (B, nstate) float64, one mjSTATE_INTEGRATION row per simulation.
      poses: {"geom_xpos", "geom_xmat", "cam_xpos", "cam_xmat"} copied from MjData after the last
        step (the kinematics of its last substep, as `mjx.Data` holds them), for the renderer.
    """

    rows: np.ndarray
    poses: dict


class CpuEngine:
    """MuJoCo's C engine, threaded over simulations with `mujoco.batch.Batch`.

    Results are bit-identical at any thread count (a property of `mujoco.batch`).
    """

    name = "cpu"

    def __init__(self, model: mujoco.MjModel, batch_size: int, nthread: int | None = None):
        self.model = model
        self.batch_size = batch_size
        nthread = nthread or min(os.cpu_count() or 1, batch_size)
        self.batch = mujoco.batch.Batch(model, nsim=batch_size, nthread=nthread)
        self._qpos, self._qvel = self.batch.bind("qpos"), self.batch.bind("qvel")
        self._ctrl, self._mocap = self.batch.bind("ctrl"), self.batch.bind("mocap_pos")
        self._poses = {k: self.batch.bind(k) for k in POSE_FIELDS}

    def _state(self) -> CpuPhysics:
        return CpuPhysics(rows=self.batch.state.copy(), poses={k: v.copy() for k, v in self._poses.items()})

    def init(self, qpos: np.ndarray, mocap_pos: np.ndarray) -> CpuPhysics:
        """Physics at rest at qpos (B, nq) with mocap bodies at mocap_pos (B, nmocap, 3)."""
        self.batch.reset(stage=mujoco.mjtStage.mjSTAGE_NONE)
        self._qpos[:] = np.asarray(qpos, np.float64)
        self._mocap[:] = np.asarray(mocap_pos, np.float64)
        self.batch.forward()
        return self._state()

    def advance(self, physics: CpuPhysics, ctrl, mocap_pos, nsub: int):
        """Steps every simulation nsub times with constant ctrl (B, nu).

        Returns (CpuPhysics, qpos (B, nq), qvel (B, nv)) after the last substep.
        """
        self.batch.state[:] = physics.rows
        self._ctrl[:] = np.asarray(ctrl, np.float64)
        self._mocap[:] = np.asarray(mocap_pos, np.float64)
        self.batch.step(nstep=nsub)
        return self._state(), self._qpos.copy(), self._qvel.copy()

    @staticmethod
    def poses(physics: CpuPhysics) -> dict:
        """Geom and camera poses (B, ...) of a physics state, as MjData lays them out (traceable)."""
        return physics.poses


def standalone_free_bodies(model: mujoco.MjModel) -> tuple[tuple[int, int], ...]:
    """(body id, first dof address) of every body that is a tree of its own, one free joint and no
    child bodies: the bodies whose gyroscopic term MuJoCo's C `implicitfast` integrates implicitly."""
    out = []
    for j in np.flatnonzero(model.jnt_type == mujoco.mjtJoint.mjJNT_FREE):
        b = int(model.jnt_bodyid[j])
        if model.body_jntnum[b] == 1 and not np.any(model.body_parentid[1:] == b):
            out.append((b, int(model.jnt_dofadr[j])))
    return tuple(out)


def _free_bias(omega, mass, inertia, s):
    """Velocity-dependent bias force (6,) of a free body in its body frame: [force; torque about
    the body origin], the terms of qfrc_bias on a free joint's dofs (qfrc_bias holds the force in
    the world frame). omega: (3,) angular velocity; mass: (); inertia: (3, 3) about the centre of
    mass; s: (3,) centre of mass from the body origin; all in the body frame."""
    f = mass * jnp.cross(omega, jnp.cross(omega, s))
    return jnp.concatenate([f, jnp.cross(omega, inertia @ omega) + jnp.cross(s, f)])


def _free_block(mx, d, mass_matrix, qderiv, body: int, adr: int):
    """(6, 6) M - h * d(qfrc_smooth)/d(qvel) of one standalone free body, gyroscopic term included
    (MuJoCo's mjd_freeMhat), and its (6, 6) block without it (what `mjx.implicit` solves with).
    mass_matrix: (nv, nv) M; qderiv: (nv, nv) d(qfrc_smooth)/d(qvel)."""
    h = mx.opt.timestep
    rot, irot = d.xmat[body], d.ximat[body]  # body -> world, inertia frame -> world
    inertia = rot.T @ irot @ jnp.diag(mx.body_inertia[body]) @ irot.T @ rot
    s = rot.T @ (d.xipos[body] - d.xpos[body])
    dbias = jax.jacfwd(_free_bias)(d.qvel[adr + 3:adr + 6], mx.body_mass[body], inertia, s)  # (6, 3)
    dbias = dbias.at[:3].set(rot @ dbias[:3])
    sl = slice(adr, adr + 6)
    plain = mass_matrix[sl, sl] - h * qderiv[sl, sl]
    return plain.at[:, 3:].add(h * dbias), plain


def _implicitfast(mx, free: tuple, d):
    """One `implicitfast` integration of forward-computed Data d (one simulation), with the
    gyroscopic term of standalone free bodies implicit, as in MuJoCo's C engine.

    MJX's `implicit` drops every Coriolis and centrifugal derivative, so a light, flat body spinning
    fast (the cloth, knocked off the counter at tens of rad/s) integrates its Euler equations
    explicitly: each substep adds h^2 |L x w|^2 to |L|^2, and the tumble grows until the state is
    non-finite. The C engine solves each such body's 6 x 6 block with that derivative included;
    here the same block solve replaces those rows of the force that `mjx.implicit` solves with.
    The body's block of M - h*qDeriv is decoupled from every other dof (its own tree), so
    (M - h*qDeriv) qacc = qfrc' gives the block solve's qacc there and the usual one elsewhere.
    """
    qderiv = mjx.deriv_smooth_vel(mx, d)
    mass_matrix = mjx.full_m(mx, d)  # (nv, nv), once for every free body's block
    qfrc = d.qfrc_smooth + d.qfrc_constraint
    smooth = d.qfrc_smooth
    for body, adr in free:
        full, plain = _free_block(mx, d, mass_matrix, qderiv, body, adr)
        qacc = jnp.linalg.solve(full, qfrc[adr:adr + 6])
        smooth = smooth.at[adr:adr + 6].set(plain @ qacc - d.qfrc_constraint[adr:adr + 6])
    return mjx.implicit(mx, d.replace(qfrc_smooth=smooth))


class MjxEngine:
    """MJX (impl="jax"): vmapped over simulations, substeps in `lax.scan`; `advance` is jittable.

    A substep is `mjx.step`, except with the `implicitfast` integrator, whose gyroscopic term of
    standalone free bodies is integrated implicitly as MuJoCo's C engine does (`_implicitfast`).
    """

    name = "mjx"

    def __init__(self, model: mujoco.MjModel, batch_size: int):
        self._mjx = mjx
        self.model = model
        self.batch_size = batch_size
        self.mx = mjx.put_model(model, impl="jax")
        self._free = standalone_free_bodies(model)

    def step(self, d):
        """One physics substep of one simulation's Data (traceable)."""
        if self.model.opt.integrator != mujoco.mjtIntegrator.mjINT_IMPLICITFAST or not self._free:
            return self._mjx.step(self.mx, d)
        return _implicitfast(self.mx, self._free, self._mjx.forward(self.mx, d))

    def init(self, qpos, mocap_pos) -> Any:
        """Data at rest at qpos (B, nq) with mocap bodies at mocap_pos (B, nmocap, 3), its poses and
        cameras computed. Only the position stages that place bodies, geoms and cameras run: a step
        recomputes everything else from qpos, qvel, controls and the warm start (zero until a step),
        so the episode is the same as after a full mjx.forward, whose collision and constraint
        stages would compile a second time beside the step's."""
        return self._placed(jnp.asarray(qpos, jnp.float32), jnp.asarray(mocap_pos, jnp.float32))

    @functools.cached_property
    def _placed(self):
        # jitted: called eagerly (a camera's pose, an object's place), the vmapped kinematics would
        # otherwise compile each of its hundreds of primitives on its own
        mjx, mx = self._mjx, self.mx

        def one(q, mp):
            d = mjx.make_data(mx, impl="jax")
            d = d.replace(qpos=q, mocap_pos=mp)
            return mjx.camlight(mx, mjx.com_pos(mx, mjx.kinematics(mx, d)))

        return jax.jit(jax.vmap(one))

    def advance(self, physics, ctrl, mocap_pos, nsub: int):
        """Steps every simulation nsub substeps with constant ctrl (B, nu) and mocap bodies at mocap_pos
        (B, nmocap, 3) (traceable). Returns (Data, qpos (B, nq), qvel (B, nv)) after the last substep."""
        d = physics.replace(ctrl=jnp.asarray(ctrl, physics.ctrl.dtype), mocap_pos=mocap_pos)

        def substep(dd, _):
            return jax.vmap(self.step)(dd), None

        d, _ = jax.lax.scan(substep, d, None, length=nsub)
        return d, d.qpos, d.qvel

    def poses(self, physics) -> dict:
        """Geom and camera poses (B, ...) of a physics state (traceable)."""
        return {k: getattr(physics, k) for k in POSE_FIELDS}


def make_engine(name: str, model: mujoco.MjModel, batch_size: int, nthread: int | None = None):
    """The engine called `name` (`cpu` or `mjx`) for batch_size simulations of model."""
    if name == "cpu":
        return CpuEngine(model, batch_size, nthread)
    if name == "mjx":
        return MjxEngine(model, batch_size)
    raise ValueError(f"unknown engine {name!r}; choose one of {', '.join(ENGINES)}")
