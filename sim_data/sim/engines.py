"""Two physics engines over one MJCF: MuJoCo's C engine (`cpu`) and MJX (`mjx`, impl="jax").

An engine turns initial positions into its physics state and advances a batch of simulations by
a number of substeps under constant controls. Everything else (tasks, actions, observations)
is shared JAX code in `sim_data.sim.env`.
"""

from __future__ import annotations

import contextlib
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


class MjxEngine:
    """MJX (impl="jax"): vmapped over simulations, substeps in `lax.scan`; `advance` is jittable."""

    name = "mjx"

    def __init__(self, model: mujoco.MjModel, batch_size: int):
        self._mjx = mjx
        self.model = model
        self.batch_size = batch_size
        self.mx = mjx.put_model(model, impl="jax")

    def init(self, qpos, mocap_pos) -> Any:
        """Data at rest at qpos (B, nq) with mocap bodies at mocap_pos (B, nmocap, 3), its poses and
        cameras computed. Only the position stages that place bodies, geoms and cameras run: a step
        recomputes everything else from qpos, qvel, controls and the warm start (zero until a step),
        so the episode is the same as after a full mjx.forward, whose collision and constraint
        stages would compile a second time beside the step's."""
        mjx, mx = self._mjx, self.mx

        def one(q, mp):
            d = mjx.make_data(mx, impl="jax")
            d = d.replace(qpos=q, mocap_pos=mp)
            return mjx.camlight(mx, mjx.com_pos(mx, mjx.kinematics(mx, d)))

        return jax.vmap(one)(jnp.asarray(qpos, jnp.float32), jnp.asarray(mocap_pos, jnp.float32))

    def advance(self, physics, ctrl, mocap_pos, nsub: int):
        mjx, mx = self._mjx, self.mx
        d = physics.replace(ctrl=jnp.asarray(ctrl, physics.ctrl.dtype), mocap_pos=mocap_pos)

        def substep(dd, _):
            return jax.vmap(lambda x: mjx.step(mx, x))(dd), None

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
