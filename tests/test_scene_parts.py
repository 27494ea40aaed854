"""The v0 scene composed from home.xml with MjSpec (sim_data.sim.scene_v0), against what the
retired copy of home.xml, variant_v0_box_fingers.xml, compiled to (every array, number and name of
the two compiled models were equal when the copy was retired; the figures below are that file's)."""

import mujoco
import numpy as np
import pytest

from sim_data.bench import variants as V
from sim_data.sim import robot as R
from sim_data.sim import scene_v0

PADS = tuple(f"{side}_finger_{f}" for side in R.SIDES for f in "ab")
LEG_JOINTS = tuple(f"{side}_{j}" for side in R.SIDES for _, j, _ in scene_v0.LEG_JOINTS)


@pytest.fixture(scope="module")
def v0() -> mujoco.MjModel:
    return scene_v0.spec().compile()


def test_sizes_are_the_retired_files(v0):
    assert (v0.nbody, v0.ngeom, v0.njnt, v0.nq, v0.nv, v0.nu, v0.npair) == (51, 77, 37, 61, 57, 29, 41)
    assert (v0.opt.iterations, v0.opt.ls_iterations, v0.opt.solver) == (4, 8, mujoco.mjtSolver.mjSOL_NEWTON)


def test_geoms_are_homes_with_box_pads(model, v0):
    kept = [g for g in range(model.ngeom) if model.geom(g).name not in {f"{p}_vis" for p in PADS}]
    assert len(kept) == v0.ngeom == model.ngeom - 4
    pads = np.array([v0.geom(p).id for p in PADS])
    others = np.setdiff1d(np.arange(v0.ngeom), pads)
    for field in ("geom_type", "geom_size", "geom_pos", "geom_quat", "geom_rgba", "geom_group", "geom_friction",
                  "geom_bodyid"):
        np.testing.assert_array_equal(getattr(v0, field)[others], getattr(model, field)[kept][others], err_msg=field)
    assert (v0.geom_type[pads] == mujoco.mjtGeom.mjGEOM_BOX).all() and (v0.geom_group[pads] == 0).all()
    np.testing.assert_allclose(v0.geom_size[pads], np.tile([0.018, 0.006, 0.032], (4, 1)))
    np.testing.assert_allclose(v0.geom_pos[pads], [[0, 0.006, -0.03], [0, -0.006, -0.03]] * 2)
    np.testing.assert_array_equal(v0.geom_quat[pads], np.tile([1.0, 0, 0, 0], (4, 1)))
    np.testing.assert_allclose(v0.body_mass[v0.geom_bodyid[pads]], 0.05)


def test_joints_limits_and_servos(model, v0):
    for j in range(model.njnt):
        name = model.joint(j).name
        assert v0.joint(name).type == model.joint(name).type, name
    ranges = dict(scene_v0.NECK_RANGES, **{f"{s}_{j}": r for s in R.SIDES for j, r in scene_v0.ARM_RANGES.items()})
    ranges.update({n: r for n, r in zip(LEG_JOINTS, [r for _ in R.SIDES for _, _, r in scene_v0.LEG_JOINTS])})
    assert len(ranges) == 16 + 6 and v0.njnt == model.njnt + 6
    for name, r in ranges.items():
        assert v0.jnt_limited[v0.joint(name).id], name
        np.testing.assert_allclose(v0.jnt_range[v0.joint(name).id], r, err_msg=name)
        np.testing.assert_allclose(v0.actuator_ctrlrange[v0.actuator(name).id], r, err_msg=name)
    assert [v0.actuator(a).name for a in range(model.nu)] == [model.actuator(a).name for a in range(model.nu)]
    assert [v0.actuator(a).name for a in range(model.nu, v0.nu)] == list(LEG_JOINTS)
    legs = np.arange(model.nu, v0.nu)
    np.testing.assert_allclose(v0.actuator_gainprm[legs, 0], 150.0)
    np.testing.assert_allclose(v0.actuator_biasprm[legs, :2], np.tile([0.0, -150.0], (6, 1)))
    np.testing.assert_allclose(v0.actuator_forcerange[legs], np.tile([-150.0, 150.0], (6, 1)))
    for name in LEG_JOINTS:  # the `leg` default class
        dof = v0.jnt_dofadr[v0.joint(name).id]
        np.testing.assert_allclose([v0.dof_damping[dof], v0.dof_armature[dof]], [5.0, 0.02], err_msg=name)


def _pairs(m):
    """Each contact pair's two geom names, in alphabetical order (the compiler may swap them)."""
    return [tuple(sorted((m.geom(int(a)).name, m.geom(int(b)).name))) for a, b in zip(m.pair_geom1, m.pair_geom2)]


def test_contact_pairs(model, v0):
    home = _pairs(model)
    extra = [("mug", "shelf_board"), ("cloth", "floor")]
    assert sorted(_pairs(v0)) == sorted(home + extra)
    assert _pairs(v0).index(("mug", "shelf_board")) == _pairs(v0).index(("floor", "mug")) + 1
    assert _pairs(v0).index(("cloth", "floor")) == _pairs(v0).index(("cloth", "counter")) + 1
    assert (v0.pair_dim == 3).all() and (model.pair_dim == 1).sum() == 16


def test_benchmark_variant_is_the_composed_scene(v0):
    (spec,) = V.variants("v0:").values()
    m = V.compile_xml(spec)
    for field in ("geom_size", "jnt_range", "actuator_ctrlrange", "pair_geom1", "body_mass"):
        np.testing.assert_array_equal(getattr(m, field), getattr(v0, field))
    with pytest.raises(SystemExit):
        V.main(["--out", "/dev/null", "--dump", "v0:"])
