"""sim_data.policies.degrade: each knob changes a base policy's actions exactly as documented."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from experiments.evaluate import chunk_policy
from sim_data.policies.bc import MixedPolicy, StackedPolicy, stack_params, stacked
from sim_data.policies.degrade import (
    KNOBS,
    MAX_DELAY,
    NEUTRAL,
    PERTURB_RANGES,
    DegradedPolicy,
    degrade_params,
    perturbation,
    perturbed_params,
)
from sim_data.policies.registry import PolicySource
from sim_data.sim import robot as R


@dataclasses.dataclass(frozen=True)
class Ramp:
    """A base policy whose action at step t is params["slope"] * (t + 1) in every dimension."""

    cfg: object = None

    def init_carry(self, params, obs, task_state, rng):
        return jnp.zeros((obs["proprio"].shape[0],), jnp.int32)

    def act(self, params, obs, carry, rng):
        a = jnp.broadcast_to(params["slope"] * (carry + 1.0)[:, None], (carry.shape[0], R.ACTION_DIM))
        return a, carry + 1


def _run(policy, params, steps=12, b=3):
    obs = {"image": jnp.zeros((b, 8, 8, 3), jnp.uint8), "proprio": jnp.zeros((b, R.PROPRIO_DIM))}
    carry = policy.init_carry(params, obs, None, jax.random.PRNGKey(0))
    out = []
    for t in range(steps):
        a, carry = policy.act(params, obs, carry, jax.random.PRNGKey(t))
        out.append(np.asarray(a))
    return np.stack(out, 1)  # (B, T, 20)


def test_neutral_knobs_leave_the_actions_unchanged():
    base = {"slope": jnp.float32(0.5)}
    np.testing.assert_array_equal(_run(DegradedPolicy(Ramp()), degrade_params(base)), _run(Ramp(), base))


def test_delay_grip_and_drive_by_hand():
    base = {"slope": jnp.float32(1.0)}
    got = _run(DegradedPolicy(Ramp()), degrade_params(base, delay=3))[0, :, 0]
    # the base sends 1, 2, 3, ...; three steps late, the first action is held until then
    np.testing.assert_array_equal(got, [1, 1, 1, 1, 2, 3, 4, 5, 6, 7, 8, 9])
    got = _run(DegradedPolicy(Ramp()), degrade_params(base, grip=0.25, drive=-2.0))[0, 1]
    np.testing.assert_allclose(got[R.HAND_CLOSURE], [0.5, 0.5])
    np.testing.assert_allclose(got[R.DRIVE], [-4.0, -4.0])
    np.testing.assert_allclose(got[:16], 2.0)


def test_noise_has_its_std_on_the_joints_only():
    base = {"slope": jnp.float32(0.0)}
    got = _run(DegradedPolicy(Ramp()), degrade_params(base, noise=0.3), steps=40, b=64)
    assert abs(got[..., :16].std() - 0.3) < 0.01 and abs(got[..., :16].mean()) < 0.01
    np.testing.assert_array_equal(got[..., 16:], 0.0)


def test_levels_stack_into_one_program_and_bad_levels_are_refused():
    base = {"slope": jnp.float32(1.0)}
    levels = [degrade_params(base, delay=d) for d in (0, 2, 5)]
    stacked = StackedPolicy(DegradedPolicy(Ramp()))
    got = _run(stacked, stack_params(levels), steps=8, b=6)  # 3 levels x 2 episodes
    for k, d in enumerate((0, 2, 5)):
        np.testing.assert_array_equal(got[2 * k:2 * k + 2], _run(DegradedPolicy(Ramp()), levels[k], steps=8, b=2))
        assert got[2 * k, 7, 0] == 8 - d
    with pytest.raises(ValueError, match="delay"):
        degrade_params(base, delay=MAX_DELAY + 1)
    with pytest.raises(ValueError, match="unknown degradation"):
        degrade_params(base, speed=2)


def test_a_mixed_batch_acts_as_its_policies_run_apart():
    """Noisy degraded ramps (2 levels x 2 episodes) beside plain ramps (3 levels x 2 episodes): every
    row's actions are those of its own policy run alone on its rows with the batch's key."""
    noisy = StackedPolicy(DegradedPolicy(Ramp()))
    noisy_params = stack_params([degrade_params({"slope": jnp.float32(s)}, noise=0.2, delay=2) for s in (1.0, 2.0)])
    plain = StackedPolicy(Ramp())
    plain_params = stack_params([{"slope": jnp.float32(s)} for s in (0.5, -1.0, 3.0)])
    mixed = MixedPolicy((noisy, plain), (4, 6))
    params = (noisy_params, plain_params)
    obs = {"image": jnp.zeros((10, 8, 8, 3), jnp.uint8),
           "proprio": jnp.arange(10.0)[:, None] * jnp.ones((10, R.PROPRIO_DIM))}
    carry = mixed.init_carry(params, obs, None, jax.random.PRNGKey(0))
    apart = [pol.init_carry(q, {k: v[s] for k, v in obs.items()}, None, jax.random.PRNGKey(0))
             for pol, q, s in zip((noisy, plain), params, (slice(0, 4), slice(4, 10)))]
    for t in range(5):
        rng = jax.random.PRNGKey(100 + t)
        action, carry = mixed.act(params, obs, carry, rng)
        want = []
        for k, (pol, q, s) in enumerate(zip((noisy, plain), params, (slice(0, 4), slice(4, 10)))):
            a, apart[k] = pol.act(q, {n: v[s] for n, v in obs.items()}, apart[k], rng)
            want.append(np.asarray(a))
        np.testing.assert_array_equal(np.asarray(action), np.concatenate(want))
    np.testing.assert_allclose(np.asarray(action)[4:6, 0], 0.5 * 5)  # plain ramp at slope 0.5, step 5
    with pytest.raises(ValueError, match="10 rows"):
        mixed.act(params, {k: v[:8] for k, v in obs.items()}, carry, rng)
    with pytest.raises(ValueError, match="one positive row count"):
        MixedPolicy((noisy, plain), (4,))


def test_a_salted_policy_draws_the_same_noise_wherever_it_stands_in_the_batch():
    """The evaluator's batches (experiments.evaluate.chunk_policy): a noisy policy alone, and the same
    policy behind a plain one and another noisy one, in a MixedPolicy: its rows get the same actions;
    unsalted, its place in the stack decides its draws."""
    n = 3
    level = lambda noise, slope: degrade_params({"slope": jnp.float32(slope)}, noise=noise)
    mine = PolicySource("mine~noise/0.2", "learned", "mug", DegradedPolicy(Ramp()), level(0.2, 1.0), {})
    other = PolicySource("other~noise/0.4", "learned", "mug", DegradedPolicy(Ramp()), level(0.4, 2.0), {})
    plain = PolicySource("plain", "plugin", None, Ramp(), {"slope": jnp.float32(0.5)}, {})
    alone = _run(*chunk_policy([mine], n), steps=6, b=n)
    beside = _run(*chunk_policy([plain, other, mine], n), steps=6, b=3 * n)
    np.testing.assert_array_equal(beside[2 * n:], alone)  # plain's rows, then the noisy stack's: other, mine
    assert np.abs(beside[n:2 * n, :, 0] - 2.0 * np.arange(1, 7)).max() > 0.05  # other's own noise
    assert not np.array_equal(beside[n:2 * n] - 2.0 * np.arange(1, 7)[:, None], alone - np.arange(1, 7)[:, None])
    unsalted = StackedPolicy(DegradedPolicy(Ramp()))
    first = _run(unsalted, stack_params([mine.params, other.params]), steps=6, b=2 * n)[:n]
    second = _run(unsalted, stack_params([other.params, mine.params]), steps=6, b=2 * n)[n:]
    assert not np.array_equal(first, second)
    with pytest.raises(ValueError, match="2 salts for 1"):
        stacked(Ramp(), [plain.params], [1, 2])


def test_every_policy_of_the_project_follows_the_protocol():
    from examples.plugin_policy import BackAway
    from sim_data.policies.bc import BCPolicy, PolicyNetConfig
    from sim_data.policies.registry import Policy
    from sim_data.policies.scripted import (
        ProgramPolicy,
        ScriptedPolicy,
        ScriptOrProgramPolicy,
    )

    bc = BCPolicy(PolicyNetConfig())
    mixed = MixedPolicy((bc, Ramp()), (2, 2))
    for policy in (bc, DegradedPolicy(bc), StackedPolicy(bc), mixed, BackAway(), Ramp()):
        assert isinstance(policy, Policy), type(policy).__name__
        hash(policy)
    for cls in (ScriptedPolicy, ProgramPolicy, ScriptOrProgramPolicy):
        assert callable(getattr(cls, "init_carry")) and callable(getattr(cls, "act")), cls.__name__
    assert not isinstance(object(), Policy)


def test_per_row_knobs_act_as_each_row_run_alone_and_perturbations_cover_their_ranges():
    base = {"slope": jnp.float32(1.0)}
    episodes = [1, 2, 3, 5, 6, 7]  # delay, grip, drive, delay, grip, drive: noise draws are a row's own
    rows = _run(DegradedPolicy(Ramp()), perturbed_params(base, episodes), steps=10, b=len(episodes))
    for k, i in enumerate(episodes):
        np.testing.assert_array_equal(rows[k], _run(DegradedPolicy(Ramp()), degrade_params(base, **perturbation(i)),
                                                    steps=10, b=1)[0])
    knobs = [perturbation(i) for i in range(400)]
    for j, knob in enumerate(KNOBS):
        levels = np.array([kn[knob] for kn in knobs[j::4]])
        lo, hi = PERTURB_RANGES[knob]
        assert levels.min() >= lo and levels.max() <= hi and np.ptp(levels) > 0.9 * (hi - lo)
        assert all(kn[other] == NEUTRAL[other] for kn in knobs[j::4] for other in KNOBS if other != knob)
    with pytest.raises(ValueError, match="whole control steps"):
        degrade_params(base, delay=np.array([1, 2.5]))
