"""A user's own policy at the plug-in point: checked against the protocol before it runs, its actions
clipped as the simulator applies them, grouped only with policies it can be stacked with, and
fingerprinted so that an evaluation's output is never read back for other code."""

import dataclasses
import importlib
import json
import math
import re
import sys
import textwrap

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from examples.plugin_policy import BackAway, make, ready_pose
from experiments import evaluate as E
from experiments import report as RP
from experiments import stats as S
from sim_data.dataset import generate as G
from sim_data.policies import registry as REG
from sim_data.policies.bc import BCPolicy, PolicyNetConfig, stacked, stand_in_params
from sim_data.policies.degrade import DegradedPolicy, degrade_params
from sim_data.policies.registry import (
    ClippedPolicy,
    PolicySource,
    applied_policy,
    fingerprint,
    group_by_policy,
    is_project_policy,
    load_plugin,
    resolve,
    stacked_sources,
    used_fingerprints,
    used_policies,
)
from sim_data.sim import robot as R
from sim_data.sim.robot import robot_index
from sim_data.sim.scene import load_model
from sim_data.sim.tasks import CONTROL_DT

USER_MODULE = '''
import dataclasses
import jax.numpy as jnp

class Counting:
    """The carry counts steps (B,) int32."""
    def init_carry(self, params, obs, task_state, rng):
        return jnp.zeros((obs["proprio"].shape[0],), jnp.int32)

@dataclasses.dataclass(frozen=True)
class Constant(Counting):
    """Every action entry the same value, params["value"]."""
    def act(self, params, obs, carry, rng):
        return jnp.full((carry.shape[0], 20), params["value"], jnp.float32), carry + 1

@dataclasses.dataclass(frozen=True)
class Mlp:
    """Proprio -> action through one hidden layer whose width the params choose."""
    def init_carry(self, params, obs, task_state, rng):
        return {"t": jnp.zeros((obs["proprio"].shape[0],), jnp.int32)}
    def act(self, params, obs, carry, rng):
        h = jnp.tanh(obs["proprio"] @ params["w1"])
        return h @ params["w2"], {"t": carry["t"] + 1}

@dataclasses.dataclass(frozen=True)
class Narrow(Counting):
    """Actions of 19 entries: one short."""
    def act(self, params, obs, carry, rng):
        return jnp.zeros((carry.shape[0], 19)), carry + 1

@dataclasses.dataclass(frozen=True)
class Drifting(Counting):
    """Its carry comes back as float32 where it went in as int32."""
    def act(self, params, obs, carry, rng):
        return jnp.zeros((carry.shape[0], 20)), carry + 0.5

@dataclasses.dataclass(frozen=True)
class NeedsTaskState:
    """Reads the simulator's task state, which the world model does not have."""
    def init_carry(self, params, obs, task_state, rng):
        return task_state["phase"]
    def act(self, params, obs, carry, rng):
        return jnp.zeros((obs["proprio"].shape[0], 20)), carry

def fast():
    return Constant(), {"value": jnp.float32(5.0)}

def calm():
    return Constant(), {"value": jnp.float32(0.1)}

def mlp(width):
    return Mlp(), {"w1": jnp.full((37, width), 0.01), "w2": jnp.full((width, 20), 0.01)}

def narrow_mlp():
    return mlp(8)

def wide_mlp():
    return mlp(32)

def short():
    return Narrow(), {}

def drifting():
    return Drifting(), {}

def needs_task_state():
    return NeedsTaskState(), {}

def broken():
    return float("abc"), {}

@dataclasses.dataclass(frozen=True)
class HostSpeed(Counting):
    """Asks the host for its speed (a numpy model) without saying how to vectorise the call."""
    def act(self, params, obs, carry, rng):
        import jax
        import numpy as np
        b = carry.shape[0]
        speed = jax.pure_callback(lambda c: np.full(c.shape, -0.3, np.float32),
                                  jax.ShapeDtypeStruct((b,), jnp.float32), carry)
        return jnp.zeros((b, 20)).at[:, 18].set(speed), carry + 1

def host_speed():
    return HostSpeed(), {}

@dataclasses.dataclass(frozen=True)
class Smoothed:
    """A bfloat16 moving average of the proprioception, its decay a plain Python number."""
    def init_carry(self, params, obs, task_state, rng):
        return jnp.zeros(obs["proprio"].shape, jnp.bfloat16)
    def act(self, params, obs, carry, rng):
        ema = params["decay"] * carry + (1 - params["decay"]) * obs["proprio"].astype(jnp.bfloat16)
        return jnp.zeros((carry.shape[0], 20)), ema

def smoothed():
    return Smoothed(), {"decay": 0.9}

def sixty_four():
    import jax
    jax.config.update("jax_enable_x64", True)
    return Constant(), {"value": 0.1}

def sixty_four_then_fails():
    import jax
    jax.config.update("jax_enable_x64", True)
    raise RuntimeError("no model file")

class Plain(Counting):
    """A hashable policy that is no dataclass: its default repr holds a memory address."""
    def act(self, params, obs, carry, rng):
        from user_helper import shaped
        return shaped(carry.shape[0]), carry + 1

def plain():
    return Plain(), {}
'''

USER_HELPER = '''
import jax.numpy as jnp
import numpy as np

TABLE = np.full(20, 0.25, np.float32)  # a constant array: the traced program names it, not its values

def shaped(b):
    return jnp.broadcast_to(jnp.asarray(TABLE), (b, 20))
'''


@pytest.fixture
def user_module(tmp_path, monkeypatch):
    """A user's module of plug-ins, importable as `user_pols` (written in tmp_path); its file path."""
    path = tmp_path / "user_pols.py"
    path.write_text(textwrap.dedent(USER_MODULE))
    (tmp_path / "user_helper.py").write_text(textwrap.dedent(USER_HELPER))
    monkeypatch.syspath_prepend(str(tmp_path))
    for name in ("user_pols", "user_helper"):
        sys.modules.pop(name, None)
    importlib.invalidate_caches()
    yield path
    for name in ("user_pols", "user_helper"):
        sys.modules.pop(name, None)


def test_a_zoo_folder_named_like_a_call_is_read_as_a_zoo(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "zoo:v2(old)").mkdir()
    with pytest.raises(FileNotFoundError, match=r"policies.json is missing"):
        resolve(["zoo:v2(old)"])


REFUSED = [  # (plug-in, error, what the message says)
    ("short", ValueError, r"shape \(2, 20\).*\(2, 19\)"),
    ("drifting", ValueError, r"carry.*int32.*float32"),
    ("needs_task_state", RuntimeError, r"task_state None"),
    # as the rollouts and imagination run it: stacked, under vmap, its parameters arrays
    ("host_speed", RuntimeError, r"stacked, under jax.vmap.*pure_callback"),
    ("smoothed", ValueError, r"stacked.*bfloat16.*float32"),
    ("sixty_four", ValueError, r"turned JAX's 64-bit mode \(jax_enable_x64\) on"),
    ("sixty_four_then_fails", RuntimeError, r"sixty_four_then_fails\(\) raised RuntimeError: no model file"),
]


def test_a_plugin_is_checked_against_the_protocol_before_it_runs(user_module):
    for attr, error, says in REFUSED:
        with pytest.raises(error, match=f"'user_pols:{attr}'.*" + says):
            load_plugin(f"user_pols:{attr}")
        assert not jax.config.jax_enable_x64  # put back as it was, also where the plug-in fails
    # the simulator alone (the data generator) gives it a task state: accepted there
    assert load_plugin("user_pols:needs_task_state", world_model=False).kind == "plugin"
    assert G.resolve_sources(["user_pols:needs_task_state"], world_model=False)
    with pytest.raises(RuntimeError, match=r"'user_pols:broken': user_pols.broken\(\) raised ValueError") as e:
        load_plugin("user_pols:broken")
    assert isinstance(e.value.__cause__, ValueError)  # the user's traceback is kept
    for spec in ("user_pols:mlp(8)", "user_pols:mlp(width=8)"):
        with pytest.raises(ValueError, match=r"cannot pass arguments to a plug-in.*functools.partial"):
            resolve([spec])
    source = load_plugin("mine=user_pols:narrow_mlp")  # a pytree of parameters and a dict carry pass
    assert source.name == "mine" and source.kind == "plugin" and source.record == {"plugin": "user_pols:narrow_mlp"}
    assert len(source.code) == 16  # its code's digest, kept out of the record that datasets write


ODD_MODULE = '''
import collections
import jax.numpy as jnp

class Back(collections.namedtuple("Back", ["speed"])):
    def init_carry(self, params, obs, task_state, rng):
        return None
    def act(self, params, obs, carry, rng):
        return jnp.zeros((obs["proprio"].shape[0], 20)).at[:, 18].set(self.speed), None

class Forward(collections.namedtuple("Forward", ["speed"])):
    def init_carry(self, params, obs, task_state, rng):
        return None
    def act(self, params, obs, carry, rng):
        return jnp.zeros((obs["proprio"].shape[0], 20)).at[:, 18].set(-self.speed), None

class FixedBatch(Back):
    def act(self, params, obs, carry, rng):
        return jnp.zeros((2, 20)), None

class Single(Back):
    def act(self, params, obs, carry, rng):
        return jnp.zeros((obs["proprio"].shape[0], 20))

def back():
    return Back(-0.3), None

def forward():
    return Forward(-0.3), None

def fixed_batch():
    return FixedBatch(-0.3), None

def single():
    return Single(-0.3), None
'''


def test_unusual_plugins_are_kept_apart_and_checked(tmp_path, monkeypatch):
    (tmp_path / "odd_pols.py").write_text(textwrap.dedent(ODD_MODULE))
    (tmp_path / "odd_broken.py").write_text("raise KeyError('MODEL_DIR is not set')\n")
    (tmp_path / "odd_dep.py").write_text("import not_installed_anywhere\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    for name in ("odd_pols", "odd_broken", "odd_dep"):
        sys.modules.pop(name, None)
    importlib.invalidate_caches()
    back, forward = resolve(["odd_pols:back", "odd_pols:forward"])
    assert back.policy.policy == forward.policy.policy  # namedtuples of equal fields compare equal, as tuples
    assert back.policy != forward.policy and len(group_by_policy([back, forward])) == 2  # but never run as one
    refusals = [("odd_pols:fixed_batch", ValueError, r"'odd_pols:fixed_batch'.*shape \(3, 20\).*got \(2, 20\)"),
                ("odd_pols:single", ValueError, r"'odd_pols:single'.*a pair \(action, carry\), got an array of shape \(2, 20\)"),
                ("odd_pols:bak", ValueError, r"no attribute 'bak'; did you mean back"),
                ("odd_broken:make", RuntimeError, r"'odd_broken:make'.*importing 'odd_broken' raised KeyError"),
                ("odd_dep:make", ValueError, r"'odd_dep:make'.*not_installed_anywhere.*not installed"),
                ("odd_missing:make", ValueError, r"cannot import 'odd_missing'.*PYTHONPATH")]
    for spec, error, message in refusals:
        with pytest.raises(error, match=message):
            load_plugin(spec)


def test_specs_that_are_not_plugins_say_what_a_plugin_is(user_module):
    with pytest.raises(ValueError, match="a plug-in is package.module:attribute"):
        resolve([":make"])
    with pytest.raises(ValueError, match="neither a zoo registry nor a plug-in"):
        resolve(["user_pols"])
    with pytest.raises(ValueError, match="differ only in punctuation"):
        resolve(["x.y=user_pols:calm", "x_y=user_pols:fast"])
    with pytest.raises(ValueError, match="names a file: .* as examples.plugin_policy:make"):
        resolve(["mine=examples/plugin_policy.py:make"])
    # "a, b" on a command line: the space is not part of b's name
    assert [s.name for s in resolve(["user_pols:calm", " mine=user_pols:fast", ""])] == ["user_pols:calm", "mine"]


def test_a_plugins_actions_are_clipped_to_the_ranges_the_simulator_applies(user_module):
    idx = robot_index(load_model())
    fast, calm = resolve(["user_pols:fast", "user_pols:calm"])
    assert isinstance(fast.policy, ClippedPolicy)
    obs = {"image": jnp.zeros((3, 64, 64, 3), jnp.uint8), "proprio": jnp.zeros((3, R.PROPRIO_DIM))}
    got = {}
    for s in (fast, calm):
        carry = s.policy.init_carry(s.params, obs, None, jax.random.PRNGKey(0))
        got[s.name] = np.asarray(s.policy.act(s.params, obs, carry, jax.random.PRNGKey(1))[0])
    np.testing.assert_array_equal(got["user_pols:fast"], np.broadcast_to(np.minimum(5.0, idx.action_high), (3, 20)))
    assert got["user_pols:fast"][0, R.FORWARD_SPEED] == R.MAX_FORWARD_SPEED
    np.testing.assert_array_equal(got["user_pols:calm"], np.clip(np.full((3, 20), np.float32(0.1)),
                                                                 idx.action_low, idx.action_high))


@dataclasses.dataclass(frozen=True)
class _Steady:
    """Every action entry params["value"]; the carry counts steps."""

    def init_carry(self, params, obs, task_state, rng):
        return jnp.zeros((obs["proprio"].shape[0],), jnp.int32)

    def act(self, params, obs, carry, rng):
        return jnp.full((carry.shape[0], 20), params["value"], jnp.float32), carry + 1


def test_imagination_gives_the_world_model_a_learned_policys_actions_as_the_robot_applies_them():
    """A policy lengthening its drive past the robot's top speed (a drive x2 family) is clipped to what the
    robot applies before the world model reads it, as its rollouts record it; a plug-in, clipped already,
    is used as it is; equal policies give equal wrappers (one compiled imagination)."""
    idx = robot_index(load_model())
    degraded = DegradedPolicy(_Steady())
    params = degrade_params({"value": np.float32(-0.3)}, drive=2.0)
    wrapped = applied_policy(degraded)
    assert wrapped == applied_policy(DegradedPolicy(_Steady())) and hash(wrapped) == hash(applied_policy(degraded))
    obs = {"image": jnp.zeros((2, 64, 64, 3), jnp.uint8), "proprio": jnp.zeros((2, R.PROPRIO_DIM))}
    rng = jax.random.PRNGKey(1)
    raw = np.asarray(degraded.act(params, obs, degraded.init_carry(params, obs, None, rng), rng)[0])
    got = np.asarray(wrapped.act(params, obs, wrapped.init_carry(params, obs, None, rng), rng)[0])
    assert raw[0, R.FORWARD_SPEED] == np.float32(-0.6) and got[0, R.FORWARD_SPEED] == -R.MAX_FORWARD_SPEED
    assert raw[0, R.HAND_CLOSURE.start] < 0 and got[0, R.HAND_CLOSURE.start] == 0.0
    np.testing.assert_array_equal(got, np.clip(raw, idx.action_low, idx.action_high))
    plugin = resolve(["examples.plugin_policy:make"])[0].policy
    assert applied_policy(plugin) is plugin


class _Peeking:
    """A plug-in that reads what it should not (the simulator's state, the task state) and sends NaN."""

    def init_carry(self, params, obs, task_state, rng):
        seen = jnp.float32(len(obs)) + (0.0 if task_state is None else 100.0)
        return jnp.full(obs["proprio"].shape[:1], seen)

    def act(self, params, obs, carry, rng):
        action = jnp.zeros((obs["proprio"].shape[0], 20)).at[:, 0].set(carry).at[:, 1].set(jnp.nan)
        return action.at[:, 2].set(jnp.float32(len(obs))), carry


def test_a_plugin_sees_in_the_simulator_what_it_sees_in_the_world_model_and_a_nan_acts_as_0():
    idx = robot_index(load_model())
    policy = ClippedPolicy(_Peeking(), tuple(idx.action_low.tolist()), tuple(idx.action_high.tolist()))
    sim_obs = {"image": jnp.zeros((2, 64, 64, 3), jnp.uint8), "proprio": jnp.zeros((2, R.PROPRIO_DIM)),
               "qpos": jnp.zeros((2, 9)), "qvel": jnp.zeros((2, 9)), "time": jnp.zeros(2)}
    carry = policy.init_carry(None, sim_obs, object(), jax.random.PRNGKey(0))  # a task state: not passed on
    action, _ = policy.act(None, sim_obs, carry, jax.random.PRNGKey(1))
    wm_obs = {k: sim_obs[k] for k in ("image", "proprio")}
    again, _ = policy.act(None, wm_obs, policy.init_carry(None, wm_obs, None, jax.random.PRNGKey(0)),
                          jax.random.PRNGKey(1))
    np.testing.assert_array_equal(action, again)
    assert float(action[0, 2]) == np.clip(2.0, idx.action_low[2], idx.action_high[2])  # two keys seen
    assert float(action[0, 1]) == np.clip(0.0, idx.action_low[1], idx.action_high[1])  # NaN as 0
    # the data generator's (simulator_only): the simulator's view and task state, as documented
    generator = ClippedPolicy(_Peeking(), policy.low, policy.high, simulator_only=True)
    seen, _ = generator.act(None, sim_obs, generator.init_carry(None, sim_obs, object(), jax.random.PRNGKey(0)),
                            jax.random.PRNGKey(1))
    assert float(seen[0, 2]) == np.clip(5.0, idx.action_low[2], idx.action_high[2])


def test_equal_policies_with_parameters_of_other_shapes_run_apart(user_module):
    narrow, wide, narrow2 = resolve(["user_pols:narrow_mlp", "user_pols:wide_mlp", "again=user_pols:narrow_mlp"])
    assert narrow.policy == wide.policy  # one policy object, the width in its parameters
    groups = group_by_policy([narrow, wide, narrow2])
    assert [[s.name for s in g] for g in groups] == [["user_pols:narrow_mlp", "again"], ["user_pols:wide_mlp"]]
    assert G.rollout_key(narrow) == G.rollout_key(narrow2) != G.rollout_key(wide)
    for g in groups:  # each group stacks
        policy, params = stacked_sources(g)
        assert policy.count(params) == len(g)


def test_a_fingerprint_follows_the_parameters_and_the_plugins_code(user_module):
    (calm,) = resolve(["user_pols:calm"])
    (calm2,) = resolve(["user_pols:calm"])
    assert fingerprint(calm) == fingerprint(calm2)  # the same in every process: no memory addresses in it
    assert fingerprint(calm) != fingerprint(dataclasses.replace(calm, params={"value": jnp.float32(0.2)}))
    user_module.write_text(user_module.read_text().replace("carry + 1", "carry + 2"))
    assert fingerprint(resolve(["user_pols:calm"])[0]) != fingerprint(calm)  # loaded again after the edit
    # a plain class, stable across loads; an edit of a helper module it calls, seen in its traced program
    (plain,) = resolve(["user_pols:plain"])
    assert fingerprint(plain) == fingerprint(resolve(["user_pols:plain"])[0])
    helper = user_module.parent / "user_helper.py"
    helper.write_text(helper.read_text().replace("0.25", "0.5"))
    sys.modules.pop("user_helper", None)
    assert fingerprint(resolve(["user_pols:plain"])[0]) != fingerprint(plain)


def test_an_evaluation_is_not_read_back_for_edited_plugins(user_module, tmp_path):
    cfg = E.EvalConfig(policies=("user_pols:calm",), wm="runs/wm/x", video_policies=0)
    out = tmp_path / "eval"
    out.mkdir()
    E._check_config(cfg, out, resolve(cfg.policies))
    E._check_config(cfg, out, resolve(cfg.policies))  # unchanged: the rerun continues
    user_module.write_text(user_module.read_text().replace("carry + 1", "carry + 2"))
    E._check_config(cfg, out, resolve(cfg.policies))  # no results yet (a run failed before its first task)
    (out / "tasks").mkdir()
    (out / "tasks" / "mug.npz").write_bytes(b"")  # a task's results: read back by a rerun
    user_module.write_text(user_module.read_text().replace("carry + 2", "carry + 3"))
    with pytest.raises(ValueError, match=r"\['user_pols:calm'\] as their code or parameters were then"):
        E._check_config(cfg, out, resolve(cfg.policies))
    with pytest.raises(ValueError, match="another configuration"):
        E._check_config(dataclasses.replace(cfg, episodes=3), out, resolve(cfg.policies))


def test_non_finite_predictions_are_not_read_as_failures():
    p, n = 2, 4
    res = {"names": ["ok", "nans"], "true": np.array([[1, 1, 0, 0], [0, 0, 0, 0]], bool),
           "prob": np.array([[0.9, 0.8, 0.2, 0.1], [np.nan] * 4]), "prob_members": np.zeros((1, p, n)),
           **{k: np.zeros((p, n)) for k in E.READOUT_KEYS}, "sim_finite": np.ones((p, n), bool),
           "true_progress": np.zeros((p, n, 3)), "trace_progress": np.zeros((p, n, 3)),
           "action_gap": np.zeros((p, n)), "action_gap_dims": np.zeros((p, n, 20)), "action_bias_dims": np.zeros((p, n, 20)),
           "prob_observed": np.full((p, n), np.nan), E.OBSERVED_SECOND: np.full((p, n), np.nan),
           "prob_replayed": np.full((p, n), np.nan), "sim_imagined": np.full((p, n), np.nan)}
    sources = {name: dataclasses.replace(load_plugin("examples.plugin_policy:make"), name=name) for name in res["names"]}
    ok, nans = E.policy_rows(E.EvalConfig(policies=("x",), wm="y"), "mug", res, sources)
    assert ok["pred_rate_thresholded"] == 0.5 and ok["alignment"] == 1.0 and ok["nonfinite_predictions"] == 0
    assert np.isnan(nans["pred_rate"]) and np.isnan(nans["pred_rate_thresholded"]) and np.isnan(nans["alignment"])
    assert all(np.isnan(nans["pred_ci"])) and all(np.isnan(nans["pred_thresholded_ci"]))
    assert nans["nonfinite_predictions"] == 4
    assert all(np.isnan(E._interval_of_mean([np.nan, 0.2, 0.4])))
    # a t-interval over the episodes (mean 0.4, sd 0.2, n 3: t(0.975, 2) = 4.302653), within [0, 1]
    assert E._interval_of_mean([0.2, 0.4, 0.6]) == pytest.approx([0.0, 0.4 + 4.302653 * 0.2 / np.sqrt(3)], abs=1e-5)
    assert E._interval_of_mean([0.7]) == [0.0, 1.0]
    rows = [{"name": "ok", "nonfinite_episodes": 0, "nonfinite_predictions": 0},
            {"name": "nans", "nonfinite_episodes": 3, "nonfinite_predictions": 8}]
    assert "policies nans ran into non-finite values" in S.nonfinite_policies(rows)
    assert S.nonfinite_policies(rows[:1]) == ""


def test_the_ranking_leaves_out_a_policy_whose_predictions_diverged():
    """Pooled and per task, as within a task (tests/test_stats.py): the other policies' figures, the
    diverged one named, not read as a predicted failure."""
    nan = math.nan
    rows = [{"name": n, "task": "mug", "true_rate": t, "pred_rate": q, "pred_rate_thresholded": q, "val_loss": None,
             "pred_rate_readouts": {r: q for r in E.READOUTS}}
            for n, t, q in (("a", 1.0, 0.9), ("b", 0.5, nan), ("c", 0.0, 0.2), ("d", 0.5, 0.6))]
    true_eps = np.array([[1, 1], [1, 0], [0, 0], [1, 0]], float)
    prob_eps = np.array([[0.9, 0.9], [nan, nan], [0.2, 0.2], [0.6, 0.6]])
    got = E.ranking_block(rows, true_eps, prob_eps, 0.5)
    assert got["left_out"] == ["b"] and got["mmrv"] == 0 and got["pairwise_acc_gap10"] == 1
    assert got["pearson"] == pytest.approx(np.corrcoef([0.9, 0.2, 0.6], [1.0, 0.0, 0.5])[0, 1])
    assert got["alignment"] == pytest.approx(5 / 6)  # d's second episode fails, read as a success
    # fewer than two policies left: none is left out, and the statistics are undefined rather than an error
    alone = E.ranking_block(rows[:2], true_eps[:2], prob_eps[:2], 0.5)
    assert alone["left_out"] == ["b"] and np.isnan(alone["pearson"])
    assert all(np.isnan(alone[k]) for k in ("mmrv", "pairwise_acc_gap10", "alignment", "spearman"))
    assert all(np.isnan(v) for m in alone["readouts"].values() for v in m.values())
    # and the decision analysis has no binomial curve to draw at an undefined alignment
    cfg = E.EvalConfig(policies=("a",), wm="none", tasks=("mug",))
    decision = E.decision_analysis(cfg, {"mug": {"true": true_eps.astype(bool), "prob": prob_eps}}, alone["alignment"])
    assert all(curve is None for curve in decision["model"].values())


def test_a_clipped_plugin_keeps_its_policys_way_of_stacking():
    @dataclasses.dataclass(frozen=True)
    class InTurn:
        stacks_in_turn: bool = True
    assert ClippedPolicy(InTurn(), (0.0,), (1.0,)).stacks_in_turn
    assert not ClippedPolicy(object(), (0.0,), (1.0,)).stacks_in_turn


def test_the_report_escapes_names_and_names_tasks_the_world_model_never_learned():
    table = RP.md_table([["policy", "rate"], ["a|b", "0.5"]])
    assert table.splitlines()[2] == "| a\\|b | 0.5 |"
    res = {"tasks": ["mug", "step_back"], "world_model": {"train_tasks": ["mug"]}}
    assert "never saw step_back in training (it learned mug)" in RP.unlearned_warning(res)
    assert RP.unlearned_warning({"tasks": ["mug"], "world_model": {"train_tasks": ["mug"]}}) == ""


def test_a_task_no_policy_runs_on_is_an_error_before_anything_runs():
    """A zoo's checkpoints run on their own task only: asking for another task with no plug-in beside them
    leaves it no policy, which must be said up front (it failed as a ZeroDivisionError deep in the batching)."""
    step_back = PolicySource(name="step_back/c/5", kind="learned", task="step_back", policy=None, params=None,
                             record={})
    plugin = PolicySource(name="mine", kind="plugin", task=None, policy=None, params=None, record={})
    cfg = E.EvalConfig(policies=("x",), wm="w", tasks=("mug", "step_back"))
    with pytest.raises(ValueError, match="no policy runs on task mug"):
        E.evaluation_tasks(cfg, [step_back])
    assert E.evaluation_tasks(cfg, [step_back, plugin]) == ["mug", "step_back"]
    assert E.evaluation_tasks(dataclasses.replace(cfg, tasks=()), [step_back]) == ["step_back"]
    # a task named twice would be evaluated once and every policy's row on it counted twice
    with pytest.raises(ValueError, match="tasks names step_back twice"):
        dataclasses.replace(cfg, tasks=("step_back", "mug", "step_back")).validate()


def test_overrides_may_stand_on_both_sides_of_an_option(capsys):
    with pytest.raises(SystemExit):
        G.main(["--config", "smoke", "size=96", "--out", "/nonexistent/x", "episodes=2"])
    err = capsys.readouterr().err
    assert "unrecognized arguments" not in err and "size" in err


def test_the_report_places_each_plugin_among_its_tasks_policies():
    def row(name, kind, task, true, pred, ci):
        return {"name": name, "kind": kind, "task": task, "true_rate": true, "true_ci": ci, "pred_rate": pred,
                "pred_ci": [pred - 0.05, pred + 0.05] if pred is not None else [None, None]}
    policies = [row("zoo/a", "learned", "mug", 0.9, 0.8, [0.7, 1.0]),
                row("zoo/b", "learned", "mug", 0.2, 0.3, [0.05, 0.45]),
                dict(row("mine", "plugin", "mug", 0.5, 0.85, [0.3, 0.7]), pred_rate_on_truth=0.55),
                dict(row("mine", "plugin", "wipe", 0.0, None, [0.0, 0.2]), n=16, nonfinite_episodes=16),
                row("zoo/c", "learned", "wipe", 0.6, 0.6, [0.4, 0.8])]
    table = RP.plugin_table(policies)
    assert table[0][-1] == "place by true / predicted"
    # on mug: truly 2nd of 3 (0.9 > 0.5 > 0.2), read 1st (0.85 above 0.8); 0.35 off, outside [0.3, 0.7]; its
    # simulated episodes read 0.55, inside: the imagination is what differs
    assert table[1] == ["mine", "mug", "0.50 (0.30-0.70)", "0.85 (0.80-0.90)", "0.35", "no", "0.55", "+0.30 +0.05",
                        "imagination", "2 / 1 of 3"]
    assert table[2][4:] == ["n/a", "n/a", "n/a", "n/a", "n/a", "2 / n/a of 2"]  # a prediction not read
    assert table[2][2] == "0.00 (0.00-0.20, 16 of 16 episodes non-finite)"  # a truth in doubt says so
    assert RP.plugin_table([p for p in policies if p["kind"] == "learned"]) is None
    # mug ranked by its rule: the judge's 0.55 on the simulated episodes is not the rule's reading, so no split
    ruled = RP.plugin_table(policies, ruled=("mug",))
    assert ruled[1][6:9] == ["n/a", "n/a", "n/a"] and ruled[1][4:6] == table[1][4:6] and ruled[2] == table[2]


def test_the_violations_of_a_task_ranked_by_its_rule_show_no_judge_reading_of_its_true_episodes():
    def viol(name):
        return {"name": name, "true_rate": 0.2, "pred_rate": 0.9, "on_truth": 0.4, "imagined_in_sim": 0.3,
                "share": 1.0, "against": 1}
    res = {"rank_violations": {t: {"mmrv": 0.3, "policies": [viol(f"{t}/p")]} for t in ("mug", "step_back")},
           "policies": [], "world_model": {"geometric_ranks": ["step_back"]}}
    rows = RP.violation_table(res)
    col = rows[0].index("read on its true episodes")
    assert [r[col] for r in rows[1:]] == ["0.40", "n/a"]  # mug by the judge, step_back by its rule
    sim = rows[0].index("simulated on its imagined actions")
    assert [r[sim] for r in rows[1:]] == ["0.30", "0.30"]  # the simulator's outcome, whatever reads the loop
    res["world_model"]["geometric_ranks"] = ["mug", "step_back"]  # every task by its rule: no judge column
    assert "read on its true episodes" not in RP.violation_table(res)[0]
    res["world_model"] = {}  # older results: every task by the read-out
    assert [r[col] for r in RP.violation_table(res)[1:]] == ["0.40", "0.40"]
    # a policy that acts alike on imagined and true frames has no largest dimension to name
    res["rank_violations"]["mug"]["policies"][0]["action_gap_largest"] = {"rms": 0.0, "dim": "left_shoulder_pitch"}
    res["rank_violations"]["step_back"]["policies"][0]["action_gap_largest"] = {"rms": 0.25, "dim": "forward_speed"}
    rows = RP.violation_table(res)
    col = rows[0].index("largest in one dimension")
    assert [r[col] for r in rows[1:]] == ["0.000 (none differs)", "0.250 (forward_speed)"]


def test_a_plugin_s_error_is_placed_in_the_read_out_or_in_imagination():
    truth = {"true_rate": 0.0, "true_ci": [0.0, 0.19]}
    assert RP.error_source(truth | {"pred_rate": 0.97, "pred_rate_on_truth": 0.84}) == "read-out"  # misread even so
    np.testing.assert_allclose(RP.error_parts(truth | {"pred_rate": 0.97, "pred_rate_on_truth": 0.84}), (0.13, 0.84))
    assert RP.error_source(truth | {"pred_rate": 0.97, "pred_rate_on_truth": 0.05}) == "imagination"
    # a judge that reads true episodes low across the board: the larger part names the source, not the interval
    assert RP.error_source({"true_rate": 1.0, "true_ci": [0.81, 1.0], "pred_rate": 0.2,
                            "pred_rate_on_truth": 0.6}) == "read-out"  # -0.4 imagined, -0.4 read: a tie to the read-out
    assert RP.error_source({"true_rate": 1.0, "true_ci": [0.81, 1.0], "pred_rate": 0.1,
                            "pred_rate_on_truth": 0.6}) == "imagination"
    assert RP.error_source(truth | {"pred_rate": 0.10, "pred_rate_on_truth": 0.96}) == "-"  # inside: no error to place
    assert RP.error_source(truth | {"pred_rate": 0.97, "pred_rate_on_truth": None}) == "n/a"  # frames not kept
    assert RP.error_source(truth | {"pred_rate": None, "pred_rate_on_truth": 0.05}) == "n/a"
    assert RP.error_source(truth | {"pred_rate": 0.97}) == "n/a"


def test_the_examples_flailing_plugin_draws_fresh_actions_from_its_key_within_their_ranges():
    idx = robot_index(load_model())
    (flail,) = resolve(["examples.plugin_policy:flail"])
    obs = {"image": jnp.zeros((4, 64, 64, 3), jnp.uint8), "proprio": jnp.zeros((4, R.PROPRIO_DIM))}
    carry = flail.policy.init_carry(flail.params, obs, None, jax.random.PRNGKey(0))
    a, carry = flail.policy.act(flail.params, obs, carry, jax.random.PRNGKey(1))
    again, _ = flail.policy.act(flail.params, obs, carry, jax.random.PRNGKey(1))
    other, _ = flail.policy.act(flail.params, obs, carry, jax.random.PRNGKey(2))
    a, again, other = map(np.asarray, (a, again, other))
    np.testing.assert_array_equal(a, again)  # the same key, the same draw
    assert (a != other).mean() > 0.5 and (a[0] != a[1]).mean() > 0.5  # another key, another row: others
    assert (a >= idx.action_low).all() and (a <= idx.action_high).all()
    assert ((a == idx.action_low) | (a == idx.action_high)).any()  # the hands' closures clipped at 0 or 1


def test_the_examples_camera_reading_plugin_backs_away_until_the_bottom_of_its_view_darkens():
    (look,) = resolve(["examples.plugin_policy:look_back"])
    bright, dark = np.full((64, 64, 3), 230, np.uint8), np.full((64, 64, 3), 230, np.uint8)
    dark[48:] = 60  # the bottom quarter at 60/255 = 0.24, under the threshold of 0.55
    half = np.full((64, 64, 3), 230, np.uint8)
    half[:48] = 0  # dark above the bottom quarter: only that quarter counts
    obs = lambda *frames: {"image": jnp.asarray(np.stack(frames)), "proprio": jnp.zeros((len(frames), R.PROPRIO_DIM))}
    carry = look.policy.init_carry(look.params, obs(bright, bright), None, jax.random.PRNGKey(0))
    a, carry = look.policy.act(look.params, obs(bright, dark), carry, jax.random.PRNGKey(0))
    assert np.asarray(a)[:, R.FORWARD_SPEED].tolist() == pytest.approx([-0.3, 0.0])
    a, carry = look.policy.act(look.params, obs(half, bright), carry, jax.random.PRNGKey(0))
    assert np.asarray(a)[:, R.FORWARD_SPEED].tolist() == pytest.approx([-0.3, 0.0])  # a stop is for good
    np.testing.assert_array_equal(np.delete(np.asarray(a), R.FORWARD_SPEED, axis=1),
                                  np.broadcast_to(np.delete(np.asarray(ready_pose()), R.FORWARD_SPEED), (2, 19)))


def test_the_examples_body_reading_plugin_stops_where_its_sensed_speed_sums_to_its_distance():
    """The odometer sums its proprioception's forward speed over the control steps, this step's sensed speed
    counted before it acts: fed -0.3 m/s (0.015 m a step) its sum reaches 0.66 >= 0.65 at the 44th step,
    so it backs 43 steps and then stops for good; fed a still body it never stops."""
    (odo,) = resolve(["examples.plugin_policy:odometer"])
    proprio = np.zeros((2, R.PROPRIO_DIM), np.float32)
    proprio[0, R.PROPRIO_BASE_VEL.start] = -0.3
    obs = {"image": jnp.zeros((2, 64, 64, 3), jnp.uint8), "proprio": jnp.asarray(proprio)}
    carry = odo.policy.init_carry(odo.params, obs, None, jax.random.PRNGKey(0))
    speeds = []
    for _ in range(60):
        a, carry = odo.policy.act(odo.params, obs, carry, jax.random.PRNGKey(0))
        speeds.append(np.asarray(a)[:, R.FORWARD_SPEED])
    speeds = np.stack(speeds)
    np.testing.assert_allclose(speeds[:43, 0], -0.3)
    assert (speeds[43:, 0] == 0).all()
    np.testing.assert_allclose(speeds[:, 1], -0.3)


def test_the_examples_jittering_plugin_backs_away_for_its_time_at_speeds_drawn_around_its_mean():
    (jitter,) = resolve(["examples.plugin_policy:jitter_back"])
    obs = {"image": jnp.zeros((512, 64, 64, 3), jnp.uint8), "proprio": jnp.zeros((512, R.PROPRIO_DIM))}
    carry = jitter.policy.init_carry(jitter.params, obs, None, jax.random.PRNGKey(0))
    a, carry = jitter.policy.act(jitter.params, obs, carry, jax.random.PRNGKey(1))
    speed = np.asarray(a)[:, R.FORWARD_SPEED]
    assert speed.mean() == pytest.approx(-0.3, abs=0.03) and speed.std() == pytest.approx(0.15, abs=0.02)
    late = jnp.full((512,), 44, jnp.int32)  # 2.2 s at 20 Hz: its time is up
    assert (np.asarray(jitter.policy.act(jitter.params, obs, late, jax.random.PRNGKey(1))[0])[:, R.FORWARD_SPEED]
            == 0).all()


@pytest.mark.parametrize("name,metres", [("stop_go", 0.64), ("ramp_back", 0.7375), ("ramp_far", 1.1125),
                                          ("surge", 0.60), ("pulse_short", 0.30), ("decel_far", 1.2625)])
def test_the_examples_varying_speed_plugins_back_away_the_distance_they_state(name, metres):
    """Each drives its table step by step, the ready pose held, the last entry after the table ends;
    the distance in step_back's 100 steps (5 s) by hand: e.g. stop_go 4 x 8 steps at 0.4 m/s x 0.05 s."""
    (src,) = resolve([f"examples.plugin_policy:{name}"])
    obs = {"image": jnp.zeros((2, 64, 64, 3), jnp.uint8), "proprio": jnp.zeros((2, R.PROPRIO_DIM))}
    carry = src.policy.init_carry(src.params, obs, None, jax.random.PRNGKey(0))
    speeds = []
    for _ in range(130):
        a, carry = src.policy.act(src.params, obs, carry, jax.random.PRNGKey(0))
        speeds.append(-np.asarray(a)[:, R.FORWARD_SPEED])
    speeds = np.stack(speeds)
    assert (speeds >= 0).all() and (speeds <= R.MAX_FORWARD_SPEED).all() and (speeds[:, 0] == speeds[:, 1]).all()
    assert speeds[:100, 0].sum() * CONTROL_DT == pytest.approx(metres, abs=1e-3)
    held = resolve(["examples.plugin_policy:stop_go"])[0].policy  # a table ending at a speed: that speed held
    params = {"ready": ready_pose(), "speeds": jnp.asarray([0.1, 0.2, 0.3])}
    c = held.init_carry(params, obs, None, jax.random.PRNGKey(0))
    for want in (0.1, 0.2, 0.3, 0.3, 0.3):
        b, c = held.act(params, obs, c, jax.random.PRNGKey(0))
        assert -np.asarray(b)[:, R.FORWARD_SPEED] == pytest.approx([want, want])
    np.testing.assert_array_equal(np.delete(np.asarray(a), R.FORWARD_SPEED, axis=1),
                                  np.broadcast_to(np.delete(np.asarray(ready_pose()), R.FORWARD_SPEED), (2, 19)))


@dataclasses.dataclass(frozen=True)
class SharedClock:
    """The example's back-away policy with one step counter for its whole batch (shape ()), which
    lax.cond reads: a carry leaf without the batch axis."""

    def init_carry(self, params, obs, task_state, rng):
        return jnp.zeros((), jnp.int32)

    def act(self, params, obs, carry, rng):
        hold = jnp.broadcast_to(params["ready"], (obs["proprio"].shape[0], R.ACTION_DIM))
        back = hold.at[:, R.FORWARD_SPEED].set(params["speed"])
        return jax.lax.cond(carry * CONTROL_DT < params["seconds"], lambda: back, lambda: hold), carry + 1


def test_a_carry_the_batch_shares_runs_stacked_as_the_batched_one():
    """Stacked with other parameter sets, a policy whose carry has no batch axis is given the carry it
    made (shape (), not (1,)) and acts as the example's policy with a counter per episode."""
    _, params = make()
    still = dict(params, seconds=params["seconds"] * 0)
    keys = np.stack([np.asarray(jax.random.PRNGKey(s)) for s in (11, 12)])
    env = E.cached_env("step_back", 4, "cpu", False)
    outcome, rec = E.record_policies(env, *stacked(SharedClock(), [params, still]), keys, jax.random.PRNGKey(0))
    _, ref = E.record_policies(env, *stacked(BackAway(), [params, still]), keys, jax.random.PRNGKey(0))
    assert outcome.tolist() == [[True, True], [False, False]]
    np.testing.assert_array_equal(np.asarray(rec.action), np.asarray(ref.action))


@dataclasses.dataclass(frozen=True)
class KeyedJitter:
    """Holds a typed random key (jax.random.key, JAX's own) in its parameters and jitters the ready
    pose by draws from it."""

    def init_carry(self, params, obs, task_state, rng):
        return jnp.zeros((obs["proprio"].shape[0],), jnp.int32)

    def act(self, params, obs, carry, rng):
        b = obs["proprio"].shape[0]
        jitter = 0.05 * jax.random.normal(jax.random.fold_in(params["key"], carry[0]), (b, R.ACTION_DIM))
        return jnp.broadcast_to(params["ready"], (b, R.ACTION_DIM)) + jitter, carry + 1


def test_parameters_holding_typed_keys_are_fingerprinted_stacked_and_run():
    sets = [{"ready": ready_pose(), "key": jax.random.key(s)} for s in (0, 1, 0)]
    digest = lambda q: fingerprint(dataclasses.replace(resolve(["examples.plugin_policy:make"])[0], params=q))
    assert digest(sets[0]) == digest(sets[2]) != digest(sets[1])
    policy, params = stacked(KeyedJitter(), sets)
    assert jax.random.key_impl(params["key"]) == jax.random.key_impl(sets[0]["key"]) and params["key"].shape == (3,)
    keys = np.stack([np.asarray(jax.random.PRNGKey(11))])
    _, rec = E.record_policies(E.cached_env("step_back", 3, "cpu", False), policy, params, keys,
                               jax.random.PRNGKey(0), steps=20)
    actions = np.asarray(rec.action)
    assert np.isfinite(actions).all()
    np.testing.assert_array_equal(actions[0], actions[2])  # the same key, the same draws
    assert not np.array_equal(actions[0], actions[1])


def test_the_unseen_networks_are_the_unseen_lineages_that_are_not_counterfactual_families():
    rows = [{"name": n, "lineage": lin} for n, lin in (("mug/conv/5", "conv"), ("mug/vit/5", "vit"),
                                                       ("mug/conv~grip/0.5", "conv~grip"), ("mine", "mine"))]
    assert S.unseen_networks(rows, {"mug/conv/5"}) == {"mug/vit/5", "mine"}
    # no family among the unseen: the unseen block is already this one
    assert S.unseen_networks(rows, {"mug/conv/5", "mug/conv~grip/0.5"}) == set()
    assert S.unseen_networks(rows, set()) == {"mug/conv/5", "mug/vit/5", "mine"}


def test_a_plugins_rollouts_in_the_training_data_count_as_seen(tmp_path):
    """The evaluation's unseen policies leave out those whose rollouts a world model trained on: a
    plug-in's as a zoo checkpoint's; the scripted, program and perturbed episodes name no evaluated policy."""
    rows = [{"policy": "scripted@1.00", "policy_kind": "scripted"},
            {"policy": "program:reach_mug", "policy_kind": "program"},
            {"policy": "learned:mug/conv_proprio/97", "policy_kind": "learned"},
            {"policy": "plugin:examples.plugin_policy:make", "policy_kind": "plugin"},
            {"policy": "plugin:mine", "policy_kind": "plugin"},
            {"policy": "perturbed:mug/conv_proprio/97~perturbed", "policy_kind": "perturbed"}]
    (tmp_path / "manifest.jsonl").write_text("".join(json.dumps(r) + "\n" for r in rows))
    assert used_policies(tmp_path) == {"mug/conv_proprio/97", "examples.plugin_policy:make", "mine"}


def test_a_policy_evaluated_under_another_name_than_its_rollouts_counts_as_seen(tmp_path):
    """Seen is decided by what a policy computes where the training data records it: the plug-in whose
    rollouts were recorded as "plugin:mine" is seen when evaluated as examples.plugin_policy:make, a
    policy that took the name "mine" but computes something else is not, nor is another; where the data
    records no fingerprint, by name."""
    plugin = resolve(["examples.plugin_policy:make"])[0]
    other = dataclasses.replace(plugin, name="other", params=jax.tree_util.tree_map(lambda a: a + 1, plugin.params))
    assert fingerprint(other) != fingerprint(plugin)
    # the data generator loads it for the simulator alone: the same policy, the same fingerprint
    assert fingerprint(resolve(["examples.plugin_policy:make"], world_model=False)[0]) == fingerprint(plugin)
    data = tmp_path / "data"
    data.mkdir()
    rows = [{"policy": "plugin:mine", "policy_kind": "plugin", "policy_fingerprint": fingerprint(plugin)},
            {"policy": "scripted@1.00", "policy_kind": "scripted"},
            {"policy": "learned:mug/conv/5", "policy_kind": "learned"}]  # a manifest that records no fingerprint
    (data / "manifest.jsonl").write_text("".join(json.dumps(r) + "\n" for r in rows))
    assert used_fingerprints(data) == {fingerprint(plugin)}
    bundle = tmp_path / "bundle"  # a bundle carries its data's names and fingerprints
    bundle.mkdir()
    (bundle / "bundle.json").write_text(json.dumps({"data_policies": sorted(used_policies(data)),
                                                    "data_fingerprints": sorted(used_fingerprints(data))}))
    lone, revised = dataclasses.replace(other, name="lone"), dataclasses.replace(other, name="mine")
    assert E.seen_policies([bundle], [plugin, other, lone, revised]) == {plugin.name}
    (bundle / "bundle.json").write_text(json.dumps({"data_policies": ["mine"]}))  # one that records none
    assert E.seen_policies([bundle], [plugin, other, revised]) == {"mine"}


ZOO_SERVER = '''
import dataclasses
from sim_data.policies.bc import BCPolicy, PolicyNetConfig, stand_in_params
from sim_data.policies.degrade import DegradedPolicy, degrade_params

NET = PolicyNetConfig(width=8, hidden=16)


def served():
    return BCPolicy(NET), stand_in_params(NET, False)


@dataclasses.dataclass(frozen=True)
class Mine(BCPolicy):
    pass


def subclassed():
    return Mine(NET), stand_in_params(NET, False)


def wrapped():
    return DegradedPolicy(Mine(NET)), degrade_params(stand_in_params(NET, False))
'''


def test_a_plugin_serving_a_zoo_checkpoint_through_its_own_module_is_that_checkpoint(tmp_path, monkeypatch):
    """A user's module that returns one of the project's policies with a checkpoint's parameters computes
    what the checkpoint computes: the same fingerprint, so a world model that saw the checkpoint's
    rollouts counts the plug-in as seen; a class of the module's own is the module's code and is not."""
    (tmp_path / "zoo_server.py").write_text(ZOO_SERVER)
    monkeypatch.syspath_prepend(str(tmp_path))
    sys.modules.pop("zoo_server", None)
    net = PolicyNetConfig(width=8, hidden=16)
    checkpoint = PolicySource(name="mug/conv/5", kind="learned", task="mug", policy=BCPolicy(net),
                              params=stand_in_params(net, False), record={})
    served, subclassed, wrapped = resolve(["zoo_server:served", "zoo_server:subclassed", "zoo_server:wrapped"])
    assert is_project_policy(served.policy.policy) and not is_project_policy(subclassed.policy.policy)
    assert not is_project_policy(wrapped.policy.policy)  # the project's wrapper around a class of the module's
    assert wrapped.code and is_project_policy(DegradedPolicy(BCPolicy(net)))
    assert fingerprint(served) == fingerprint(checkpoint)
    assert fingerprint(subclassed) != fingerprint(checkpoint)
    bundle = tmp_path / "bundle"
    bundle.mkdir()
    (bundle / "bundle.json").write_text(json.dumps({"data_policies": [checkpoint.name],
                                                    "data_fingerprints": [fingerprint(checkpoint)]}))
    assert E.seen_policies([bundle], [served, subclassed]) == {served.name}
    sys.modules.pop("zoo_server", None)


def test_a_random_policy_draws_alike_in_the_simulator_and_in_imagination(smoke_world_model, tmp_path):
    """A policy that ignores what it sees and acts at random (flail) takes in imagination the actions it
    took in the simulator, step for step: imagination's policy keys are the simulated episodes' own, so
    an imagined episode is the counterfactual of its true twin and the action gap measures the model."""
    cfg = E.EvalConfig(policies=("examples.plugin_policy:flail",), wm=str(smoke_world_model), tasks=("mug",),
                       episodes=2, batch=2, video_policies=0, decision_episodes=(5,), keep_features=False)
    E.run(cfg, tmp_path / "run", progress=False)
    gap = E.load_task(tmp_path / "run" / "tasks" / "mug.npz")["action_gap"]
    assert gap.shape[-1] > 1 and np.isfinite(gap).all()
    np.testing.assert_array_equal(gap, 0.0)


def test_the_true_episodes_reading_names_its_read_out_where_rules_rank_some_tasks():
    w = {"on_truth": {}, "readout_progress": {}}
    assert RP._other_readouts(w) == [("readout_progress", "world model, progress read-out"),
                                     ("on_truth", "the read-out of the true episodes")]
    res = {"world_model": {"readout": "judge", "geometric_ranks": ["step_back"]}}
    assert RP._other_readouts(w, res)[1] == ("on_truth", "the judge read-out of the true episodes (every task's)")
    res["world_model"]["geometric_ranks"] = []  # every task by the judge: the plain label says it
    assert RP._other_readouts(w, res)[1] == ("on_truth", "the read-out of the true episodes")


def test_the_report_says_what_ranks_each_task_and_that_the_geometric_read_out_is_no_network():
    rule = "the task's rule on states predicted from the actions (wm.geometric, wm.grasp)"
    res = {"tasks": ["mug", "step_back", "wipe"], "world_model": {
        "readout": "judge", "geometric_ranks": ["step_back"],
        "rule": {"mug": "episode judge", "step_back": rule, "wipe": "highest per-step success probability"}}}
    said = RP.ranked_by(res)
    assert said.startswith(f"Ranked: mug by the episode judge; step_back by {rule}; wipe by the highest per-step "
                           "success probability. The geometric read-out (step_back) moves the robot")
    assert "not the learned network's reading" in said
    res["world_model"] |= {"geometric_ranks": [], "rule": {t: "episode judge" for t in res["tasks"]}}
    assert RP.ranked_by(res) == "Ranked: mug, step_back, wipe by the episode judge."
    del res["world_model"]["rule"]  # results written before the rule was recorded
    assert RP.ranked_by(res) == ""
    # the verdict names the rule where no proxy figure stands beside the world model's
    w = {"tasks": ["step_back"], "resamples": "policies",
         "world_model": {"mean": {"pearson": 0.98}, "mean_ci": {"pearson": [0.9, 1.0]}},
         "proxy": {"mean": {"pearson": math.nan}, "mean_ci": {"pearson": [None, None]}}, "difference": {"proxy": {}}}
    res = {"metrics": {"within_task": w}, "policies": [], "world_model": {"geometric_ranks": ["step_back"]}}
    assert "the world model (by its geometric read-out on step_back) alone ranks at" in RP.verdict(res)
    res["world_model"]["geometric_ranks"] = []
    assert "the world model alone ranks at" in RP.verdict(res)


def test_a_name_in_the_reports_markdown_is_text_not_a_link_or_a_tag():
    name = "x](javascript:alert(1))[y <b>*a_b*</b> `c` #1 | $x$ ~d~ back\\slash!"
    escaped = RP.md_text(name)
    assert re.sub(r"\\(.)", r"\1", escaped) == name  # dropping each escape gives the name back
    assert not re.search(r"(?<!\\)[\[\]()<>*_`#|$~!]", escaped.replace("\\\\", ""))  # nothing left unescaped


def test_a_difference_said_to_lie_above_0_is_not_printed_touching_it():
    assert RP._difference_ci(0.29, [0.00056, 0.52]) == "0.29 [0.0006, 0.52]"
    assert RP._difference_ci(-0.1, [-0.3, -0.004]) == "-0.10 [-0.30, -0.004]"
    assert RP._difference_ci(0.29, [0.0, 0.52]) == "0.29 [0.00, 0.52]"  # exactly 0 stays 0
    assert RP._difference_ci(0.2, [None, 0.31]) == "0.20 [n/a, 0.31]"


def test_what_act_returned_instead_of_a_pair_is_described_plainly():
    assert REG._described(np.zeros((2, 20))) == "an array of shape (2, 20)"
    assert REG._described((np.zeros((2, 20)), np.zeros(3), 1.0)) == "a tuple of 3: [(2, 20), (3,), 'float']"
    assert REG._described(None) == "a NoneType"
