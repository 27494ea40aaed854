"""The JAX renderer against MuJoCo's renderer (geom ids, depth), across engines, and its errors."""

import jax
import mujoco
import numpy as np
import pytest

from sim_data.bench.render_check import (
    ID_TARGET,
    compare,
    mujoco_reference,
    random_states,
)
from sim_data.sim import scene as S
from sim_data.sim import tasks as T
from sim_data.sim.env import HomeEnv
from sim_data.sim.render import (
    RenderConfig,
    Renderer,
    camera_poses,
    episode_rgb,
    floor_hits,
    grip_pixels,
    pixel_rays,
    poses_from_arrays,
    poses_of,
    project_points,
    reproject,
    rides_with_camera,
    riding_pixels,
)
from sim_data.sim.tasks import TASK_NAMES

PRIMITIVES_XML = """
<mujoco>
  <visual><map znear="0.01" zfar="50"/></visual>
  <asset>
    <texture name="t" type="2d" builtin="checker" rgb1="0.8 0.8 0.8" rgb2="0.3 0.3 0.3" width="64" height="64"/>
    <material name="m" texture="t" texrepeat="4 4"/>
  </asset>
  <worldbody>
    <light pos="0 0 3" dir="0 0 -1" directional="true" castshadow="true"/>
    <camera name="cam" pos="0 -1.6 1.0" xyaxes="1 0 0 0 0.55 0.83" fovy="60"/>
    <geom name="floor" type="plane" size="3 3 0.1" material="m"/>
    <geom name="box" type="box" size="0.1 0.15 0.08" pos="-0.45 0 0.3" euler="10 20 30" rgba="1 0 0 1"/>
    <geom name="sphere" type="sphere" size="0.12" pos="-0.15 0.2 0.2" rgba="0 1 0 1"/>
    <geom name="capsule" type="capsule" size="0.05 0.15" pos="0.15 -0.1 0.25" euler="60 0 30" rgba="0 0 1 1"/>
    <geom name="cylinder" type="cylinder" size="0.08 0.1" pos="0.45 0.1 0.2" euler="0 40 0" rgba="1 1 0 1"/>
    <geom name="ellipsoid" type="ellipsoid" size="0.12 0.06 0.09" pos="0.0 0.3 0.5" euler="0 30 45" rgba="0 1 1 1"/>
    <geom name="hidden" type="box" size="0.3 0.3 0.3" pos="0 0 0.3" group="3"/>
  </worldbody>
</mujoco>
"""


def _ours(model, data, cfg):
    poses = poses_from_arrays(data.geom_xpos[None], data.geom_xmat[None], data.cam_xpos[None], data.cam_xmat[None])
    out = Renderer(model, cfg).render(poses)
    return {k: np.asarray(v) for k, v in out.items()}


@pytest.mark.parametrize("tile", [0, 8])
def test_every_primitive_matches_mujoco(tile):
    model = mujoco.MjModel.from_xml_string(PRIMITIVES_XML)
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    cfg = RenderConfig(height=64, width=64, camera="cam", tile=tile)
    out = _ours(model, data, cfg)
    ref_ids, ref_depth = mujoco_reference(model, data.qpos[None], data.mocap_pos[None], "cam", 64, 64)
    res = compare(out["geom_id"], out["depth"], ref_ids, ref_depth)
    assert res["id_agreement"] >= 0.99, res
    assert res["depth_within_1pct"] >= 0.99, res
    names = {model.geom(i).name for i in np.unique(out["geom_id"]) if i >= 0}
    assert names == {"floor", "box", "sphere", "capsule", "cylinder", "ellipsoid"}  # the group-3 box stays hidden


def test_hand_computed_depth_and_shadow():
    """A camera 1 m above the floor looking down sees the floor at depth 1 wherever a sphere of radius
    0.05 m, 0.5 m above the floor, does not hide it, and the sphere's top at depth 0.45; under a sun
    slanted 1:2 the sphere casts its shadow 0.25 m along the slant."""
    xml = PRIMITIVES_XML.replace('xyaxes="1 0 0 0 0.55 0.83"', 'xyaxes="1 0 0 0 1 0"').replace('pos="0 -1.6 1.0"', 'pos="2 2 1"')
    model = mujoco.MjModel.from_xml_string(xml)
    data = mujoco.MjData(model)
    sphere = model.geom("sphere").id
    model.geom_pos[sphere] = [2.0, 2.0, 0.5]  # right under the camera and the light
    model.geom_size[sphere] = [0.05, 0, 0]
    model.light_dir[0] = np.array([0.5, 0.0, -1.0]) / np.sqrt(1.25)
    mujoco.mj_forward(model, data)
    cfg = RenderConfig(height=32, width=32, camera="cam")
    lit = _ours(model, data, RenderConfig(height=32, width=32, camera="cam", shadows=False))
    shaded = _ours(model, data, cfg)
    assert set(np.unique(lit["geom_id"]).tolist()) == {0, sphere}
    np.testing.assert_allclose(lit["depth"][lit["geom_id"] == 0], 1.0, rtol=1e-5)
    # the central pixels' rays pass 0.013 m off the sphere's centre: depth 0.451 there, by hand
    on_sphere = lit["depth"][lit["geom_id"] == sphere]
    assert 0.45 <= on_sphere.min() < 0.455 and on_sphere.max() <= 0.5
    floor_shadowed = (lit["rgb"].sum(-1) > shaded["rgb"].sum(-1)) & (shaded["geom_id"] == 0)
    assert floor_shadowed.sum() > 0
    _, ys, xs = np.nonzero(floor_shadowed)
    half_width = np.tan(np.deg2rad(30))  # fovy 60 at 1 m: the frame spans +-0.577 m
    assert abs(ys.mean() - 15.5) < 1.0
    assert abs(xs.mean() - (15.5 + 0.25 / half_width * 16)) < 1.0


@pytest.mark.parametrize("camera", ["head_cam", "ext_cam"])
def test_home_scene_matches_mujoco_on_every_task(camera):
    model = S.load_model()
    cfg = RenderConfig(camera=camera)
    renderer = Renderer(model, cfg)
    for task in TASK_NAMES:
        qpos, mocap, colors = random_states(task, 2, seed=1)
        out = renderer.render(poses_of(model, qpos, mocap), episode_rgb(renderer.geometry, colors))
        ref_ids, ref_depth = mujoco_reference(model, qpos, mocap, camera, cfg.height, cfg.width)
        res = compare(np.asarray(out["geom_id"]), np.asarray(out["depth"]), ref_ids, ref_depth)
        assert res["id_agreement_min_frame"] >= ID_TARGET, (task, res)
        assert res["depth_within_1pct"] >= 0.995, (task, res)


@pytest.mark.slow
def test_both_engines_give_the_same_frames():
    """The same initial states on the cpu and mjx engines render to the same frames."""
    cpu, mjx = HomeEnv("mug", 2, engine="cpu"), HomeEnv("mug", 2, engine="mjx")
    key = jax.random.PRNGKey(3)
    s_cpu, s_mjx = cpu.reset(key), mjx.reset(key)
    renderer = Renderer(cpu.model, RenderConfig(camera="head_cam"))
    rgb = episode_rgb(renderer.geometry, s_cpu.task.colors)
    a, b = renderer.render(cpu.poses(s_cpu), rgb), renderer.render(mjx.poses(s_mjx), rgb)
    assert np.mean(np.asarray(a["geom_id"]) == np.asarray(b["geom_id"])) >= 0.999
    diff = np.abs(np.asarray(a["rgb"], int) - np.asarray(b["rgb"], int))
    assert np.mean(diff.max(-1) <= 1) >= 0.999
    assert np.asarray(a["rgb"]).shape == (2, 64, 64, 3) and np.asarray(a["rgb"]).dtype == np.uint8


def test_bad_configuration_is_refused():
    with pytest.raises(ValueError, match="tile"):
        RenderConfig(height=64, width=64, tile=7)
    with pytest.raises(ValueError, match="unknown camera"):
        Renderer(S.load_model(), RenderConfig(camera="nose_cam"))


def _drawn(renderer, model, qpos, mocap, colors, rides):
    poses = poses_of(model, qpos, mocap)
    out = {k: np.asarray(v) for k, v in renderer.render(poses, episode_rgb(renderer.geometry, colors)).items()}
    cam = renderer.geometry.cam_names.index(renderer.cfg.camera)
    out["rides"] = riding_pixels(rides, out["geom_id"])
    return out, np.asarray(poses.cam_xpos[:, cam]), np.asarray(poses.cam_xmat[:, cam])


def test_reprojection_redraws_the_scene_as_the_renderer_does_after_the_robot_moves():
    """The head camera's frame carried through its depth to the pose after the base backs 0.3 m and
    turns 0.1 rad matches the renderer's frame there in colour wherever a point of the scene landed,
    far better than the first frame held; at the same pose it is the frame itself."""
    model = S.load_model()
    renderer = Renderer(model, RenderConfig(camera="head_cam"))
    cam = renderer.geometry.cam_names.index("head_cam")
    fovy = renderer.geometry.fovy[cam]
    rides = rides_with_camera(model, "head_cam")
    assert rides.any() and not rides.all()
    env = HomeEnv("step_back", 2, engine="cpu")
    st = env.reset(jax.random.PRNGKey(3))
    qpos, mocap, colors = np.array(st.qpos), np.asarray(st.mocap_pos), np.asarray(st.task.colors)
    a, pos0, mat0 = _drawn(renderer, model, qpos, mocap, colors, rides)

    same, covered = reproject(a["rgb"], a["depth"], a["rides"], pos0, mat0, pos0, mat0, fovy)
    np.testing.assert_array_equal(same, a["rgb"])
    assert covered.all()
    _, covered = reproject(a["rgb"], a["depth"], a["rides"], pos0, mat0, pos0, mat0, fovy, keep_rides=False)
    np.testing.assert_array_equal(covered, ~a["rides"])  # the robot's own pixels left for a drawing of it

    moved = qpos.copy()
    bx, by, byaw = env.idx.robot.base_qpos
    yaw = moved[:, byaw]
    moved[:, bx] -= 0.3 * np.cos(yaw)
    moved[:, by] -= 0.3 * np.sin(yaw)
    moved[:, byaw] += 0.1
    b, pos1, mat1 = _drawn(renderer, model, moved, mocap, colors, rides)
    warped, covered = map(np.asarray, reproject(a["rgb"], a["depth"], a["rides"], pos0, mat0, pos1, mat1, fovy))
    np.testing.assert_array_equal(warped[a["rides"]], a["rgb"][a["rides"]])  # the robot's own pixels stay put
    scene = covered & ~b["rides"] & (b["geom_id"] >= 0)
    assert scene.mean() > 0.3
    err = np.abs(warped.astype(float) - b["rgb"]).mean(-1)[scene].mean()
    still = np.abs(a["rgb"].astype(float) - b["rgb"]).mean(-1)[scene].mean()
    assert err < 0.35 * still, (err, still)
    assert err < 12.0, err


def test_reprojection_lets_the_nearer_point_win_and_leaves_what_was_hidden_empty():
    """A red square at 1 m before a blue wall at 3 m, the camera moved 0.25 m to its right (90 degree
    field of view, 32 px: 16 px per metre of shift at 1 m): the square moves 4 px left, the wall 1 px
    (1.33 rounded), so where both land the square must show, and the wall's strip the square hid (3 px)
    stays uncovered until filled."""
    h = w = 32
    depth = np.full((1, h, w), 3.0)
    depth[0, 12:20, 12:20] = 1.0
    rgb = np.zeros((1, h, w, 3), np.uint8)
    rgb[..., 2] = 255
    rgb[0, 12:20, 12:20] = (255, 0, 0)
    eye = np.eye(3)[None]
    moved, covered = map(np.asarray, reproject(rgb, depth, np.zeros((1, h, w), bool), np.zeros((1, 3)), eye,
                                               np.array([[0.25, 0.0, 0.0]]), eye, 90.0))
    np.testing.assert_array_equal(moved[0, 12:20, 8:16], np.broadcast_to([255, 0, 0], (8, 8, 3)))
    assert not covered[0, 12:20, 16:19].any() and covered[0, 12:20, 19:31].all()
    assert (moved[0, 12:20, 19:31] == [0, 0, 255]).all()


def test_floor_hits_are_where_the_renderer_draws_the_floor():
    """For the pixels the renderer draws as floor after the robot backs away from the counter, the
    floor point from the camera's pose alone is the point its depth puts there (to a millimetre), and
    the rays are unit vectors; a camera looking up meets no floor."""
    model = S.load_model()
    renderer = Renderer(model, RenderConfig(camera="head_cam"))
    cam = renderer.geometry.cam_names.index("head_cam")
    fovy = renderer.geometry.fovy[cam]
    env = HomeEnv("step_back", 2, engine="cpu")
    st = env.reset(jax.random.PRNGKey(5))
    qpos = np.array(st.qpos)
    bx, by, _ = env.idx.robot.base_qpos
    qpos[:, bx] -= 1.0  # far enough back that the floor shows
    out, pos, mat = _drawn(renderer, model, qpos, np.asarray(st.mocap_pos), np.asarray(st.task.colors),
                           rides_with_camera(model, "head_cam"))
    floor = out["geom_id"] == mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, "floor")
    assert floor.mean() > 0.05
    local = pixel_rays(64, 64, fovy)[None] * out["depth"][..., None]
    world = pos[:, None, None] + np.einsum("bij,bhwj->bhwi", mat, local)
    xy, ray = map(np.asarray, floor_hits(pos, mat, fovy, 64, 64))
    np.testing.assert_allclose(xy[floor], world[floor][:, :2], atol=1e-3)
    np.testing.assert_allclose(np.abs(world[floor][:, 2]), 0.0, atol=1e-3)
    np.testing.assert_allclose(np.linalg.norm(ray, axis=-1), 1.0, atol=1e-6)
    up = np.diag([1.0, -1.0, -1.0])[None]  # the camera's -z (its view) along the world's +z
    xy_up, _ = floor_hits(np.array([[0.0, 0.0, 1.0]]), up, 60.0, 8, 8)
    assert (np.asarray(xy_up) == 0).all()


def test_camera_poses_are_the_engines_own():
    """The head camera's pose from a state's qpos by camera_poses is the one the cpu engine computed for
    that state; a camera the model lacks is refused."""
    env = HomeEnv("step_back", 2, engine="cpu")
    st = env.reset(jax.random.PRNGKey(7))
    poses = env.poses(st)
    cam = mujoco.mj_name2id(env.model, mujoco.mjtObj.mjOBJ_CAMERA, "head_cam")
    pos, mat = camera_poses(env.model, np.asarray(st.qpos), np.asarray(st.mocap_pos))
    np.testing.assert_allclose(pos, np.asarray(poses.cam_xpos)[:, cam], atol=1e-5)
    np.testing.assert_allclose(mat, np.asarray(poses.cam_xmat)[:, cam], atol=1e-5)
    with pytest.raises(ValueError, match="unknown camera"):
        camera_poses(env.model, np.asarray(st.qpos), np.asarray(st.mocap_pos), "nose_cam")


def test_a_frame_shows_the_dirt_cells_its_step_wiped():
    """The step that lays the cloth on the dirt sinks the cells it covers, and the frame of that step shows
    them sunk: the dirt geoms where MuJoCo's forward kinematics puts them at the state's qpos and mocap
    positions, as the recording stores them, not where the physics' last substep left them."""
    env = HomeEnv("wipe", 1, engine="cpu")
    st = env.reset(jax.random.PRNGKey(0))
    q = np.asarray(st.qpos).copy()
    a = env.idx.cloth_qpos
    q[0, a : a + 2] = np.asarray(T.dirt_cell_xy(st.task.patch))[0, 7]  # flat on a cell inside the patch
    q[0, a + 3 : a + 7] = [1, 0, 0, 0]
    st = st.replace(qpos=q, physics=env.core.engine.init(q, np.asarray(st.mocap_pos)))
    st = env.step(st, np.zeros((1, 20), np.float32))
    wiped = np.asarray(st.task.wiped[0])
    assert 0 < wiped.sum() < len(wiped)
    dirt = env.idx.dirt_geom
    shown = np.asarray(env.poses(st).geom_xpos)[0, dirt]
    reference = np.asarray(poses_of(env.model, st.qpos, st.mocap_pos).geom_xpos)[0, dirt]
    np.testing.assert_allclose(shown, reference, atol=1e-6)
    np.testing.assert_allclose(shown[wiped, 2], S.COUNTER_TOP - 0.01, atol=1e-6)
    np.testing.assert_allclose(shown[~wiped, 2], S.COUNTER_TOP + 0.0005, atol=1e-6)
    # the physics alone still holds them up: the step sank them after its last substep
    assert np.all(np.asarray(st.physics.poses["geom_xpos"])[0, dirt, 2] > S.COUNTER_TOP)


def test_projected_points_land_on_the_pixels_whose_rays_reach_them():
    """project_points inverts pixel_rays: a point on pixel (i, j)'s ray, at any depth in front of a camera
    at any pose, projects to that pixel's centre; a point behind the camera is NaN."""
    rng = np.random.default_rng(0)
    size, fovy = 64, 58.0
    rays = np.asarray(pixel_rays(size, size, fovy))
    mats = np.zeros((3, 9))
    for m, q in zip(mats, rng.normal(size=(3, 4))):
        mujoco.mju_quat2Mat(m, q / np.linalg.norm(q))
    mats = mats.reshape(3, 3, 3)
    pos = rng.normal(size=(3, 3))
    pix = rng.integers(0, size, (3, 5, 2))
    depth = rng.uniform(0.2, 5.0, (3, 5))
    local = rays[pix[..., 0], pix[..., 1]] * depth[..., None]  # camera frame
    world = pos[:, None] + np.einsum("bij,bkj->bki", mats, local)
    want = (pix[..., ::-1] + 0.5) / size  # (x = column, y = row)
    np.testing.assert_allclose(project_points(world, pos, mats, fovy), want, atol=1e-5)
    behind = pos[:, None] - np.einsum("bij,bkj->bki", mats, local)
    assert np.isnan(project_points(behind, pos, mats, fovy)).all()


def test_the_grip_pixels_show_each_hand():
    """Where grip_pixels puts the left and right grip sites of the robot standing ready, the renderer draws
    that hand (its geom ids within a pixel of the spot); an unknown camera is refused."""
    env = HomeEnv("mug", 2, engine="cpu")
    st = env.reset(jax.random.PRNGKey(0))
    grips = grip_pixels(env.model, st.qpos, st.mocap_pos)
    assert grips.shape == (2, 2, 2) and np.all((grips > 0) & (grips < 1))
    renderer = Renderer(env.model, RenderConfig(camera="head_cam"))
    drawn = np.asarray(renderer.render(env.poses(st), episode_rgb(renderer.geometry, st.task.colors))["geom_id"])
    for b in range(2):
        for hand, body in enumerate(("left_hand", "right_hand")):
            col, row = (grips[b, hand] * 64).astype(int)
            ids = drawn[b, max(row - 1, 0):row + 2, max(col - 1, 0):col + 2].ravel()
            bodies = {env.model.body(env.model.geom_bodyid[g]).name for g in ids if g >= 0}
            assert body in bodies, (b, hand, bodies)
    with pytest.raises(ValueError, match="unknown camera"):
        grip_pixels(env.model, st.qpos, st.mocap_pos, "nose_cam")


def test_reprojection_refuses_an_unknown_camera():
    with pytest.raises(ValueError, match="unknown camera"):
        rides_with_camera(S.load_model(), "nose_cam")
