"""The base's motion from the driving commands (wm.egomotion)."""

import numpy as np
import pytest

from sim_data.sim.robot import ACTION_DIM, FORWARD_SPEED, YAW_RATE
from wm import egomotion as E

# a lagged response: forward 0.6 of the last step's plus 0.02 s of the command, turning likewise, and a
# sideways drift while turning (a base turning about a point off its centre)
TRUE_A = np.array([[0.6, 0.0, 0.0, 0.02, 0.0, 0.0],
                   [0.0, 0.5, 0.0, 0.0, 0.01, 0.0],
                   [0.0, 0.0, 0.6, 0.0, 0.03, 0.001]])


def _episodes(n, steps, seed):
    rng = np.random.default_rng(seed)
    actions = np.zeros((n, steps, ACTION_DIM))
    actions[..., FORWARD_SPEED] = rng.uniform(-0.5, 0.5, (n, steps))
    actions[..., YAW_RATE] = rng.uniform(-1.0, 1.0, (n, steps))
    start = np.column_stack([rng.uniform(-2, 2, (n, 2)), rng.uniform(-np.pi, np.pi, n)])
    return E.roll_base(TRUE_A, start, actions), actions


def test_displacements_are_in_the_base_frame():
    """A base facing +y that moves 0.1 m along +y and turns 0.2 rad went 0.1 m forward, none left; one
    facing +x that slides 0.05 m along +y went 0.05 m left; a turn across pi is the short way round."""
    base = np.array([[0.0, 0.0, np.pi / 2], [0.0, 0.1, np.pi / 2 + 0.2], [0.0, 0.1, np.pi / 2 + 0.2]])
    np.testing.assert_allclose(E.displacements(base), [[0.1, 0.0, 0.2], [0.0, 0.0, 0.0]], atol=1e-12)
    np.testing.assert_allclose(E.displacements(np.array([[0, 0, 0.0], [0, 0.05, 0.0]])), [[0, 0.05, 0]], atol=1e-12)
    np.testing.assert_allclose(E.displacements(np.array([[0, 0, 3.1], [0, 0, -3.1]]))[0, 2], 2 * np.pi - 6.2)


def test_the_fit_recovers_the_model_and_rolls_out_its_episodes():
    bases, actions = _episodes(8, 50, 0)
    coef = E.fit_egomotion(list(bases), list(actions))
    np.testing.assert_allclose(coef, TRUE_A, atol=1e-5)  # the episodes rolled in float32, as imagination runs
    test_bases, test_actions = _episodes(3, 80, 1)
    np.testing.assert_allclose(E.roll_base(coef, test_bases[:, 0], test_actions), test_bases, atol=1e-5)
    assert np.abs(test_bases[:, -1, :2] - test_bases[:, 0, :2]).max() > 0.05  # the episodes do move


def test_a_saved_model_reads_back_and_bad_inputs_are_refused(tmp_path):
    E.save_egomotion(tmp_path, TRUE_A, {"note": "hand-set"})
    np.testing.assert_array_equal(E.load_egomotion(tmp_path), TRUE_A)
    with pytest.raises(FileNotFoundError, match="experiments.fill"):
        E.load_egomotion(tmp_path / "none")
    with pytest.raises(ValueError, match="one pose more"):
        E.fit_egomotion([np.zeros((5, 3))], [np.zeros((5, ACTION_DIM))])
    with pytest.raises(ValueError, match="no episodes"):
        E.fit_egomotion([], [])


def test_the_joints_model_recovers_a_lagged_servo():
    """Joints driven toward random targets by dq = 0.4 (u - q) + 0.3 dq_prev (+ 0.01 on the last): the fit
    finds those coefficients and step_joints replays the joints from their start alone."""
    rng = np.random.default_rng(2)
    true = np.tile([0.4, 0.3, 0.0], (E.JOINTS, 1))
    true[-1, 2] = 0.01
    qs, actions = [], []
    for _ in range(3):
        u = np.zeros((60, ACTION_DIM))
        u[:, :E.JOINTS] = np.repeat(rng.uniform(-1, 1, (4, E.JOINTS)), 15, axis=0)  # a new target every 15 steps
        q, prev, path = rng.uniform(-1, 1, (1, E.JOINTS)), np.zeros((1, E.JOINTS)), []
        path.append(q[0])
        for t in range(60):
            q, prev = E.step_joints(true, q, prev, u[None, t])
            path.append(np.asarray(q[0], np.float64))
        qs.append(np.stack(path))
        actions.append(u)
    coef = E.fit_joints(qs, actions)
    np.testing.assert_allclose(coef, true, atol=1e-5)  # the joints stepped in float32
    with pytest.raises(ValueError, match="one state"):
        E.fit_joints([qs[0][:-1]], [actions[0]])


def test_a_model_without_joints_is_refused_where_they_are_needed(tmp_path):
    E.save_egomotion(tmp_path, TRUE_A, {})
    with pytest.raises(ValueError, match="joints"):
        E.load_egomotion(tmp_path, joints=True)
    E.save_egomotion(tmp_path, TRUE_A, {}, np.zeros((E.JOINTS, 3)))
    base, joints = E.load_egomotion(tmp_path, joints=True)
    np.testing.assert_array_equal(base, TRUE_A)
    np.testing.assert_array_equal(joints, 0.0)
