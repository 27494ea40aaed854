"""The policy zoo, the plug-in point and policy rollouts in the data generator."""

import dataclasses
import functools
import json
import os
import shutil
import subprocess
import sys
import textwrap

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from experiments.timing import compile_snapshot
from sim_data.bench import closures
from sim_data.dataset import generate as G
from sim_data.dataset.episodes import read_episode
from sim_data.policies import zoo
from sim_data.policies.bc import (
    BCPolicy,
    PolicyNetConfig,
    StackedPolicy,
    predict_chunk,
    spatial_softmax,
    stack_params,
    stacked,
    stand_in_params,
)
from sim_data.policies.registry import (
    PLAN,
    applied_policy,
    every_nth_checkpoint,
    fingerprint,
    registry_file,
    resolve,
    used_fingerprints,
    used_policies,
)
from sim_data.sim import robot as R
from sim_data.sim.env import HomeEnv
from sim_data.sim.rollout import run_episodes


@functools.cache
def compiled(policy):
    """(init_carry, act) of policy, each compiled as one program: run op by op, every operation of
    the networks compiles apart, which costs most of a test's time on a CPU."""
    return jax.jit(policy.init_carry), jax.jit(policy.act)


def test_zoo_registry_checkpoints_and_resume(smoke_zoo, smoke_dataset):
    out, registry = smoke_zoo
    cfg = zoo.make_config("smoke")
    trained = [r for r in registry if not r.get("degrade")]
    assert len(trained) == len(cfg.lineages) * len(cfg.checkpoint_steps())
    assert {r["lineage"] for r in trained} == {"conv_proprio", "conv_noproprio", "vit_noproprio"}
    for r in trained:
        assert np.isfinite(r["val_loss"]) and (out / r["checkpoint"]).exists()
    # the family: the base lineage's last checkpoint at each level, no imitation loss of its own
    last = max((r for r in trained if r["lineage"] == "conv_proprio"), key=lambda r: r["step"])
    family = [r for r in registry if r.get("degrade")]
    assert [r["name"] for r in family] == ["mug/conv_proprio~grip/0", "mug/conv_proprio~grip/1"]
    assert all(r["checkpoint"] == last["checkpoint"] and r["val_loss"] is None and r["step"] is None for r in family)
    assert {r["variant"]["proprio"] for r in registry} == {True, False}
    # a rerun finds every lineage complete and trains nothing
    stamp = {p: p.stat().st_mtime_ns for p in out.rglob("*.msgpack")}
    again = zoo.train_zoo(cfg, smoke_dataset[1], out, progress=False)
    assert [r["name"] for r in again] == [r["name"] for r in registry]
    assert stamp == {p: p.stat().st_mtime_ns for p in out.rglob("*.msgpack")}
    with pytest.raises(ValueError, match="another configuration"):
        zoo.train_zoo(zoo.make_config("smoke", ["steps=6"]), smoke_dataset[1], out, progress=False)


@pytest.mark.slow
def test_lineages_trained_together_match_lineages_trained_one_at_a_time(smoke_zoo, smoke_dataset, tmp_path):
    from sim_data.policies.bc import load_params

    out, registry = smoke_zoo
    assert zoo.make_config("smoke").group == 2  # the fixture trained both conv lineages as one program
    # one at a time, and the conv lineages in turn inside their one program (lax.map)
    for name, override in (("alone", "group=1"), ("in_turn", "sequential=conv")):
        other = zoo.train_zoo(zoo.make_config("smoke", [override]), smoke_dataset[1], tmp_path / name, progress=False)
        assert [r["name"] for r in other] == [r["name"] for r in registry]
        for together, single in zip(registry, other, strict=True):
            if together["val_loss"] is None:
                continue
            np.testing.assert_allclose(together["val_loss"], single["val_loss"], rtol=1e-4)
            np.testing.assert_allclose(together["train_loss"], single["train_loss"], rtol=1e-4)
            a, b = load_params(out / together["checkpoint"]), load_params(tmp_path / name / single["checkpoint"])
            jax.tree_util.tree_map(lambda x, y: np.testing.assert_allclose(x, y, rtol=1e-4, atol=1e-5), a, b)
    with pytest.raises(ValueError, match="group must be >= 0"):
        zoo.make_config("smoke", ["group=-1"]).validate()
    with pytest.raises(ValueError, match="sequential names encoders"):
        zoo.make_config("smoke", ["sequential=mlp"]).validate()


def test_a_family_level_runs_its_base_checkpoint_with_the_knob_applied(smoke_zoo):
    from sim_data.policies.degrade import DegradedPolicy

    out, registry = smoke_zoo
    weak, same = resolve([f"{out}#conv_proprio~grip"])
    last = max((r for r in registry if r["lineage"] == "conv_proprio"), key=lambda r: r["step"] or 0)
    base = resolve([f"{out}#{last['name']}"])[0]
    assert isinstance(weak.policy, DegradedPolicy) and weak.policy == same.policy and weak.policy.base == base.policy
    rng = np.random.default_rng(1)
    obs = {"image": jnp.asarray(rng.integers(0, 255, (2, 64, 64, 3), dtype=np.uint8)),
           "proprio": jnp.asarray(rng.normal(size=(2, 37)), jnp.float32)}

    def first_action(src):
        init, act = compiled(src.policy)
        carry = init(src.params, obs, None, jax.random.PRNGKey(0))
        return np.asarray(act(src.params, obs, carry, jax.random.PRNGKey(0))[0])

    want = first_action(base)
    np.testing.assert_allclose(first_action(same), want, atol=1e-6)
    got = first_action(weak)
    np.testing.assert_array_equal(got[:, 16:18], 0.0)
    np.testing.assert_allclose(got[:, :16], want[:, :16], atol=1e-6)


def test_a_family_joins_only_the_tasks_it_names():
    cfg = dataclasses.replace(zoo.make_config("smoke"), tasks=("mug", "step_back"), families=(
        zoo.Family("all", "conv_proprio", "noise", (0.1, 0.2)),
        zoo.Family("driving", "conv_proprio", "drive", (0.5,), tasks=("step_back",))))
    registry = [{"name": f"{t}/conv_proprio/{s}", "task": t, "lineage": "conv_proprio", "step": s,
                 "variant": {}, "checkpoint": f"ck/{t}/{s}", "net": "conv"} for t in cfg.tasks for s in (2, 4)]
    names = [r["name"] for r in zoo.family_records(cfg, registry)]
    assert names == ["mug/all/0.1", "mug/all/0.2", "step_back/all/0.1", "step_back/all/0.2", "step_back/driving/0.5"]
    bad = dataclasses.replace(cfg, families=(zoo.Family("driving", "conv_proprio", "drive", (0.5,), tasks=("wipe",)),))
    with pytest.raises(ValueError, match="wipe"):
        bad.validate()


def test_a_lineage_trains_only_on_the_tasks_it_names():
    main = zoo.make_config("smoke").lineages
    only_mug = tuple(dataclasses.replace(lin, tasks=("mug",)) if lin.name != "conv_proprio" else lin for lin in main)
    cfg = dataclasses.replace(zoo.make_config("smoke"), tasks=("mug", "step_back"), lineages=only_mug,
                              families=(zoo.Family("driving", "conv_proprio", "drive", (0.5,), tasks=("step_back",)),))
    cfg.validate()
    assert [(t, lin.name) for t, lin in cfg.lineage_jobs()] == [
        ("mug", "conv_proprio"), ("mug", "conv_noproprio"), ("mug", "vit_noproprio"), ("step_back", "conv_proprio")]
    with pytest.raises(ValueError, match="wipe"):
        dataclasses.replace(cfg, lineages=(dataclasses.replace(main[0], tasks=("wipe",)),) + main[1:]).validate()
    # a family cannot degrade a lineage on a task the lineage is not trained on
    orphan = zoo.Family("driving", "conv_noproprio", "drive", (0.5,), tasks=("step_back",))
    with pytest.raises(ValueError, match="base lineage conv_noproprio"):
        dataclasses.replace(cfg, families=(orphan,)).validate()


def test_learned_policies_follow_the_protocol_and_stack(smoke_zoo):
    out, _ = smoke_zoo
    sources = resolve([f"{out}#conv_proprio+conv_noproprio"])
    assert len(sources) == 4 and all(s.kind == "learned" and s.task == "mug" for s in sources)
    rng = np.random.default_rng(0)
    obs = {"image": jnp.asarray(rng.integers(0, 255, (6, 64, 64, 3), dtype=np.uint8)),
           "proprio": jnp.asarray(rng.normal(size=(6, 37)), jnp.float32)}
    policy = sources[0].policy
    init, act = compiled(policy)
    singles = []
    for s in sources[:2]:
        carry = init(s.params, obs, None, jax.random.PRNGKey(0))
        a, carry = act(s.params, obs, carry, jax.random.PRNGKey(1))
        assert a.shape == (6, 20) and np.isfinite(np.asarray(a)).all() and np.all(np.asarray(carry) == 1)
        singles.append(np.asarray(a))
    # two checkpoints stacked: episodes 0-2 use the first, 3-5 the second
    stacked_init, stacked_act = compiled(StackedPolicy(policy))
    params = stack_params([sources[0].params, sources[1].params])
    carry = stacked_init(params, obs, None, jax.random.PRNGKey(0))
    a, _ = stacked_act(params, obs, carry, jax.random.PRNGKey(1))
    np.testing.assert_allclose(np.asarray(a)[:3], singles[0][:3], atol=1e-5)
    np.testing.assert_allclose(np.asarray(a)[3:], singles[1][3:], atol=1e-5)
    # without proprioception the policy's actions ignore it
    noprop = next(s for s in sources if s.record["lineage"] == "conv_noproprio")
    c0 = init(noprop.params, obs, None, jax.random.PRNGKey(0))
    a1, _ = act(noprop.params, obs, c0, jax.random.PRNGKey(0))
    a2, _ = act(noprop.params, {**obs, "proprio": obs["proprio"] + 3.0}, c0, jax.random.PRNGKey(0))
    np.testing.assert_array_equal(np.asarray(a1), np.asarray(a2))


def test_stacked_conv_checkpoints_run_in_turn_with_the_actions_of_side_by_side(smoke_zoo):
    out, _ = smoke_zoo
    sources = resolve([f"{out}#conv_proprio"])[:2]
    assert sources[0].policy.stacks_in_turn and not resolve([f"{out}#vit_noproprio"])[0].policy.stacks_in_turn
    policy, params = stacked(sources[0].policy, [s.params for s in sources] + [sources[0].params])
    assert policy.in_turn and policy.count(params) == 3
    side_by_side = dataclasses.replace(policy, in_turn=False)
    rng = np.random.default_rng(1)
    obs = {"image": jnp.asarray(rng.integers(0, 255, (6, 64, 64, 3), dtype=np.uint8)),
           "proprio": jnp.asarray(rng.normal(size=(6, R.PROPRIO_DIM)), jnp.float32)}
    got = []
    for pol in (policy, side_by_side):
        init, act = compiled(pol)
        carry = init(params, obs, None, jax.random.PRNGKey(0))
        got.append([np.asarray(x) for x in act(params, obs, carry, jax.random.PRNGKey(1))])
    np.testing.assert_allclose(got[0][0], got[1][0], atol=1e-5)
    np.testing.assert_array_equal(got[0][1], got[1][1])


def test_readme_plugin_example_runs_in_the_simulator():
    (source,) = resolve(["examples.plugin_policy:make"])
    assert source.kind == "plugin" and source.runs_on("step_back") and source.runs_on("mug")
    env = HomeEnv("step_back", 2, engine="cpu")
    state, _ = run_episodes(env, source.policy, source.params, jax.random.PRNGKey(3))
    assert np.asarray(state.success).all()  # it backs 0.6 m away, clear of the stool


@dataclasses.dataclass(frozen=True)
class _CountingSteps:
    """A plug-in without parameters: every action entry is the number of steps it has taken."""

    def init_carry(self, params, obs, task_state, rng):
        return jnp.zeros((obs["proprio"].shape[0],), jnp.int32)

    def act(self, params, obs, carry, rng):
        return jnp.broadcast_to(carry[:, None].astype(jnp.float32), (carry.shape[0], R.ACTION_DIM)), carry + 1


@pytest.mark.parametrize("params", [{}, None])
def test_plugins_without_parameters_run_side_by_side(params):
    policy, stacked_params = stacked(_CountingSteps(), [params] * 3)
    obs = {"image": jnp.zeros((6, 64, 64, 3), jnp.uint8), "proprio": jnp.zeros((6, R.PROPRIO_DIM))}
    carry = policy.init_carry(stacked_params, obs, None, jax.random.PRNGKey(0))
    for k in range(2):
        action, carry = policy.act(stacked_params, obs, carry, jax.random.PRNGKey(k))
    assert policy.count(stacked_params) == 3 and action.shape == (6, R.ACTION_DIM)
    assert np.all(np.asarray(action) == 1) and np.all(np.asarray(carry) == 2)
    with pytest.raises(ValueError, match="stacked"):  # nothing to count the parameter sets from
        StackedPolicy(_CountingSteps()).count(stacked_params)


def test_bad_policy_specs_are_refused():
    with pytest.raises(ValueError, match="cannot import"):
        resolve(["no_such_package.policies:make"])
    with pytest.raises(ValueError, match="no attribute"):
        resolve(["examples.plugin_policy:missing"])
    with pytest.raises(FileNotFoundError, match="make policies"):
        resolve(["runs/no/such/zoo"])
    with pytest.raises(ValueError, match="repeat"):
        resolve(["examples.plugin_policy:make", "examples.plugin_policy:make"])


def test_a_zoo_spec_names_its_registry_or_its_plan(tmp_path):
    (tmp_path / "zoo").mkdir()
    assert registry_file(tmp_path / "zoo") == tmp_path / "zoo" / "policies.json"
    assert registry_file(tmp_path / "zoo", PLAN) == tmp_path / "zoo" / "plan.json"
    assert registry_file(tmp_path / "zoo" / "policies.json", PLAN) == tmp_path / "zoo" / "plan.json"
    assert registry_file(tmp_path / "not_yet", PLAN) == tmp_path / "not_yet" / "plan.json"  # a zoo not yet started
    assert registry_file(tmp_path / "mine.json", PLAN) == tmp_path / "mine.json"


def test_every_nth_checkpoint_thins_each_lineage_by_training_step():
    records = [{"name": f"{t}/{lin}/{s}", "task": t, "lineage": lin, "step": s}
               for t in ("mug", "wipe") for lin in ("a", "b") for s in (300, 5, 80, 20, 160)]  # steps out of order
    even = every_nth_checkpoint(records, "@0/2")
    odd = every_nth_checkpoint(records, "@1/2")
    mug_a = [r["name"] for r in even if r["task"] == "mug" and r["lineage"] == "a"]
    assert mug_a == ["mug/a/300", "mug/a/5", "mug/a/80"]  # steps 5, 80, 300 of 5, 20, 80, 160, 300
    assert [r["name"] for r in odd if r["task"] == "wipe" and r["lineage"] == "b"] == ["wipe/b/20", "wipe/b/160"]
    assert len(even) == 12 and len(odd) == 8 and not {r["name"] for r in even} & {r["name"] for r in odd}
    assert [r["step"] for r in every_nth_checkpoint(records, "@2/3") if r["name"].startswith("mug/b/")] == [80]
    for bad in ("@2/2", "@x", "@1"):
        with pytest.raises(ValueError, match="@K/N"):
            every_nth_checkpoint(records, bad)


@pytest.mark.slow  # what `make demo`'s rollouts stage builds, end to end
def test_mixed_dataset_records_policy_rollouts(smoke_dataset, smoke_zoo, smoke_world_model, tmp_path):
    cfg, data, _ = smoke_dataset
    zoo_dir, registry = smoke_zoo
    out = tmp_path / "mixed"
    last = max(r["step"] for r in registry if r["lineage"] == "conv_proprio")
    # two episodes a policy: batches of the dataset fixture's 2 rows, whose compiled rendering serves
    mixed = G.make_config("smoke", [f"policies={zoo_dir}#mug/conv_proprio/{last},examples.plugin_policy:make",
                                    "policy_episodes=2"])
    with pytest.raises(ValueError, match=r"other settings \(\['seed'\]\)"):
        G.generate(G.make_config("smoke", ["seed=5"]), tmp_path / "other", progress=False, reuse=data)
    # the scripted episodes are linked from the dataset they were generated in; only the rollouts are new
    stats = G.generate(mixed, out, progress=False, reuse=data)
    assert stats["throughput"]["episodes_generated"] == 4
    for f in (data / "episodes").iterdir():
        assert (out / "episodes" / f.name).read_bytes() == f.read_bytes()
    rows = [json.loads(line) for line in (out / "manifest.jsonl").read_text().splitlines()]
    kinds = {r["policy_kind"] for r in rows}
    assert kinds == {"scripted", "program", "learned", "plugin"}
    learned = [r for r in rows if r["policy_kind"] == "learned"]
    assert learned[0]["policy"] == f"learned:mug/conv_proprio/{last}"
    # a world model trained on it has seen that checkpoint and the plug-in act
    assert used_policies(out) == {f"mug/conv_proprio/{last}", "examples.plugin_policy:make"}
    assert used_policies(data) == set()
    # and what each computes, so that it is seen under another name too
    sources = resolve([f"{zoo_dir}#mug/conv_proprio/{last}", "examples.plugin_policy:make"])
    assert used_fingerprints(out) == {fingerprint(s) for s in sources} and used_fingerprints(data) == set()
    scripted_seed = next(r["seed"] for r in rows if r["policy_kind"] == "scripted" and r["episode_id"].endswith("0"))
    assert learned[0]["seed"] == scripted_seed  # the same initial state as scripted episode 0
    meta = G.read_episode_meta(out / learned[0]["file"])
    assert meta["policy_source"]["lineage"] == "conv_proprio"
    # the episode judge imagines a policy's own rollout closed loop, with that policy acting
    from sim_data.dataset.cache import TrainingCache
    from wm.checkpoint import load_trained
    from wm.imagine import closed_loop
    from wm.judge import dataset_policies, imagine_episodes

    wm_cfg, wm_params, norm = load_trained(smoke_world_model)
    cache = TrainingCache(out)
    pols = dataset_policies(out)
    i = next(k for k, e in enumerate(cache.episodes) if e["policy_kind"] == "learned")
    src = pols[cache.episodes[i]["policy"]]
    got = imagine_episodes(wm_cfg.model, wm_params, norm, cache, [i], "head_cam", False, pols, seed=3)
    ep = cache.episode(i, cameras=["head_cam"])
    want = closed_loop(wm_cfg.model, applied_policy(StackedPolicy(src.policy)), ep["record"]["length"] - 1, wm_params, norm,
                       stack_params([src.params]), ep["frames"]["head_cam"][None, :1], ep["proprio"][None, :1],
                       np.zeros((1, 0, 20), np.float32), jax.random.PRNGKey(3))
    np.testing.assert_allclose(got["features"][0], np.asarray(want["features"][0]), rtol=1e-5, atol=1e-5)
    logged = imagine_episodes(wm_cfg.model, wm_params, norm, cache, [i], "head_cam", False)
    assert not np.allclose(logged["features"][0], got["features"][0])  # not the logged actions replayed
    # the policy in the loop: the actions it takes on the observations imagined under its logged actions
    # and on the first one held, against those on the true observations, by hand
    from wm.imagine import open_loop
    from wm.quality import policy_action_divergence

    cfg = dataclasses.replace(wm_cfg, eval_horizons=(1, 3))
    pil = policy_action_divergence(cfg, wm_params, norm, cache, [i], pols)
    n = ep["record"]["length"] - 1
    frames, prop = ep["frames"]["head_cam"][:n], ep["proprio"][:n]
    imag = open_loop(wm_cfg.model, wm_params, norm, frames[None, :1], prop[None, :1], np.zeros((1, 0, 20), np.float32),
                     ep["action"][None, : n - 1])
    k_init, k_act = jax.random.split(jax.random.PRNGKey(i))

    pol = applied_policy(src.policy)  # as the robot applies them, as the episode logs them

    def acts(images, proprio):
        carry = pol.init_carry(src.params, {"image": images[None, 0], "proprio": proprio[None, 0]}, None, k_init)
        out = []
        for t in range(n):
            a, carry = pol.act(src.params, {"image": images[None, t], "proprio": proprio[None, t]}, carry,
                               jax.random.fold_in(k_act, t))
            out.append(np.asarray(a[0]))
        return np.asarray(norm.action(np.stack(out)))

    on_true = acts(frames, prop)
    on_imagined = acts(np.concatenate([frames[:1], np.asarray(imag["frames"][0])]),
                       np.concatenate([prop[:1], np.asarray(imag["proprio"][0])]))
    on_held = acts(np.repeat(frames[:1], n, 0), np.repeat(prop[:1], n, 0))
    row = pil["tasks"]["mug"]
    assert pil["episodes"] == 1 and pil["horizons"] == [1, 3] and row["episodes"] == 1
    for k, h in enumerate((1, 3)):
        np.testing.assert_allclose(row["imagined"][k], np.abs(on_imagined - on_true).mean(-1)[h], rtol=1e-3, atol=1e-5)
        np.testing.assert_allclose(row["copy_first"][k], np.abs(on_held - on_true).mean(-1)[h], rtol=1e-3, atol=1e-5)
    np.testing.assert_allclose(row["copy_first_mean"], np.abs(on_held - on_true).mean(), rtol=1e-3)
    # the frames it read, against the true ones from step 1 on (identical frames at 100 dB)
    from wm.metrics import psnr

    read = {"imagined": np.asarray(imag["frames"][0])[: n - 1], "copy_first": np.repeat(frames[:1], n - 1, 0)}
    for key, seen in read.items():
        np.testing.assert_allclose(row[f"{key}_psnr_db"], np.minimum(psnr(seen, frames[1:]), 100.0).mean(), rtol=1e-6)
    np.testing.assert_allclose(pil["logged_vs_true"], np.abs(on_true - np.asarray(norm.action(ep["action"][:n]))).mean(),
                               rtol=1e-3, atol=1e-6)
    assert pil["logged_vs_true"] < 1e-3  # a deterministic policy on its own episode's frames acts as it logged
    assert policy_action_divergence(cfg, wm_params, norm, cache, [i], {})["episodes"] == 0
    # the judge's warm-up runs the programs of its fit, closed loops included: a fit after it compiles
    # none of them (a model width no other test imagines with, so that they are new here)
    from wm.judge import fit_judge, warm_judge
    from wm.model import init_params

    cfg = dataclasses.replace(wm_cfg, model=dataclasses.replace(wm_cfg.model, dim=20), judge_episodes=10, judge_steps=3)
    shapes = jax.eval_shape(functools.partial(init_params, cfg.model, window=cfg.window), jax.random.PRNGKey(0))
    ids = list(range(len(cache.episodes)))
    assert {e["success"] for e in cache.episodes} == {True, False}

    def compiled(step) -> set:
        before = compile_snapshot()
        step()
        return {name for name, (count, _) in compile_snapshot()["by_program"].items()
                if count > before["by_program"].get(name, (0, 0.0))[0]}

    imagining = {"init_state", "_open_loop_segment", "_closed_loop_start", "_closed_loop_segment"}
    warmed = compiled(lambda: warm_judge(cfg, jax.tree_util.tree_map(lambda x: jnp.zeros(x.shape, x.dtype), shapes),
                                         norm, cache, ids))
    assert imagining | {"_probability"} <= warmed
    params = init_params(cfg.model, jax.random.PRNGKey(1), window=cfg.window)
    (tmp_path / "judge").mkdir()
    fitted = compiled(lambda: fit_judge(cfg, params, norm, cache, ids, tmp_path / "judge", progress=False))
    assert (tmp_path / "judge" / "judge.json").exists()
    assert not fitted & (imagining | {"_probability", "_update", "_judge_loss"})


@pytest.mark.slow
def test_perturbed_copies_send_their_checkpoints_actions_degraded_by_each_episodes_knob(smoke_dataset, smoke_zoo,
                                                                                       tmp_path):
    """A checkpoint's own rollouts beside its perturbed copy's, from the same initial states (4 each, in
    chunks of 2 rows, so a chunk's knobs are those of its own episodes): each perturbed episode's first
    action is the checkpoint's own first action on that state, degraded by that episode's one knob."""
    from sim_data.dataset.cache import TrainingCache
    from sim_data.policies.degrade import KNOBS, NEUTRAL, perturbation

    _, data, _ = smoke_dataset
    zoo_dir, registry = smoke_zoo
    last = max(r["step"] for r in registry if r["lineage"] == "conv_proprio")
    spec = f"{zoo_dir}#mug/conv_proprio/{last}"
    cfg = G.make_config("smoke", [f"policies={spec}", "policy_episodes=4", f"perturbed={spec}", "perturb_episodes=4"])
    G.generate(cfg, tmp_path / "perturbed", progress=False, reuse=data)
    rows = [json.loads(line) for line in (tmp_path / "perturbed" / "manifest.jsonl").read_text().splitlines()]
    own = [r for r in rows if r["policy_kind"] == "learned"]
    copy = [r for r in rows if r["policy_kind"] == "perturbed"]
    assert len(own) == len(copy) == 4 and {r["policy"] for r in copy} == {f"perturbed:mug/conv_proprio/{last}~perturbed"}
    assert [r["seed"] for r in copy] == [r["seed"] for r in own]
    assert used_policies(tmp_path / "perturbed") == {f"mug/conv_proprio/{last}"}  # the copy is not a seen policy
    cache = TrainingCache(tmp_path / "perturbed")
    index = {e["episode_id"]: k for k, e in enumerate(cache.episodes)}
    first = lambda r: cache.episode(index[r["episode_id"]], cameras=["head_cam"])["action"]
    for i, (mine, theirs) in enumerate(zip(copy, own, strict=True)):
        knobs = G.read_episode_meta(tmp_path / "perturbed" / mine["file"])["degrade"]
        assert knobs == perturbation(i) and [k for k in KNOBS if knobs[k] != NEUTRAL[k]] == [KNOBS[i % 4]]
        got, want = first(mine), first(theirs)
        if KNOBS[i] == "noise":
            assert np.abs(got[0, :16] - want[0, :16]).max() > 1e-3
            np.testing.assert_allclose(got[0, 16:], want[0, 16:], rtol=1e-5, atol=1e-6)
        elif KNOBS[i] == "delay":  # the first action held for `delay` steps
            np.testing.assert_allclose(got[:knobs["delay"] + 1], np.repeat(want[:1], knobs["delay"] + 1, 0), atol=1e-6)
        else:
            scaled = R.HAND_CLOSURE if KNOBS[i] == "grip" else R.DRIVE
            expect = want[0].copy()
            expect[scaled] *= knobs[KNOBS[i]]
            np.testing.assert_allclose(got[0], expect, rtol=1e-5, atol=1e-6)
            if KNOBS[i] == "grip":
                assert np.abs(want[0, scaled]).max() > 1e-3  # the knob had something to scale (a mug policy drives late)
    with pytest.raises(ValueError, match="can be perturbed"):
        G.generate(G.make_config("smoke", ["perturbed=examples.plugin_policy:make"]), tmp_path / "bad", progress=False)


@pytest.mark.slow
def test_checkpoints_of_one_architecture_run_stacked_in_one_chunk_as_each_runs_alone(smoke_dataset, smoke_zoo,
                                                                                      tmp_path):
    _, data, _ = smoke_dataset
    zoo_dir, _ = smoke_zoo
    cfg = G.make_config("smoke", [f"policies={zoo_dir}#conv_proprio", "policy_episodes=1"])
    sources = resolve(cfg.policies)
    assert len(sources) == 2 and sources[0].policy == sources[1].policy
    (chunk,) = [c for c in G._plan(cfg, sources) if c.key == G.rollout_key(sources[0])]
    assert [s for s, _ in chunk.slots] == sources  # batch 2: both checkpoints, one episode each
    out = tmp_path / "stacked"
    assert G.generate(cfg, out, progress=False, reuse=data)["throughput"]["episodes_generated"] == 2
    eps = [read_episode(out / "episodes" / f"{G.episode_id('mug', s, 0)}.mcap", cameras=()) for s in sources]
    for src, ep in zip(sources, eps):
        assert ep["meta"]["policy"] == f"learned:{src.name}" and ep["meta"]["policy_source"]["name"] == src.name
        # alone, the checkpoint acts as it did beside the other
        _, alone = G.simulate_chunk(cfg, G.Chunk("mug", G.rollout_key(src), ((src, (0,)),), 1, 1), "cpu")
        np.testing.assert_allclose(alone.action[0], ep["action"], atol=1e-5)
    np.testing.assert_array_equal(eps[0]["qpos"][0], eps[1]["qpos"][0])  # one initial state
    assert not np.allclose(eps[0]["action"], eps[1]["action"])


def test_temporal_ensembling_executes_the_weighted_mean_of_the_chunks_covering_the_step(smoke_zoo):
    out, _ = smoke_zoo
    src = resolve([f"{out}#conv_noproprio"])[-1]
    rng = np.random.default_rng(1)
    frames = [jnp.asarray(rng.integers(0, 255, (2, 64, 64, 3), dtype=np.uint8)) for _ in range(6)]
    proprio = jnp.zeros((2, 37), jnp.float32)
    cfg = src.policy.cfg
    chunks = [np.asarray(predict_chunk(cfg, src.params, f, proprio, jnp.full((2,), t, jnp.int32)))
              for t, f in enumerate(frames)]
    for decay in (0.0, -0.5):
        policy = BCPolicy(dataclasses.replace(cfg, ensemble=decay))
        carry = policy.init_carry(src.params, {"image": frames[0], "proprio": proprio}, None, jax.random.PRNGKey(0))
        for t, f in enumerate(frames):
            a, carry = policy.act(src.params, {"image": f, "proprio": proprio}, carry, jax.random.PRNGKey(0))
            ages = range(min(t, cfg.chunk - 1) + 1)  # chunk predicted `age` steps ago, its entry for step t
            w = np.array([np.exp(-decay * k) for k in ages])
            want = sum(wk * chunks[t - k][:, k] for wk, k in zip(w, ages)) / w.sum()
            np.testing.assert_allclose(np.asarray(a), want, rtol=1e-4, atol=1e-5)
    assert len(frames) > cfg.chunk and not np.allclose(want, chunks[-1][:, 0])  # it differs from the newest chunk


def test_spatial_softmax_is_the_softmax_weighted_mean_position_of_each_channel():
    rng = np.random.default_rng(4)
    x = rng.normal(size=(2, 3, 5, 4)).astype(np.float32)
    got = np.asarray(spatial_softmax(jnp.asarray(x), 0.5))
    for b in range(2):
        for c in range(4):
            w = np.exp(x[b, :, :, c] / 0.5)
            w /= w.sum()
            cols, rows = np.meshgrid(np.linspace(-1, 1, 5), np.linspace(-1, 1, 3))
            np.testing.assert_allclose(got[b, 2 * c:2 * c + 2], [(w * cols).sum(), (w * rows).sum()], rtol=1e-5,
                                       atol=1e-6)
    peak = np.zeros((1, 3, 5, 1), np.float32)
    peak[0, 2, 4, 0] = 50.0  # one dominant cell: its position, bottom right
    np.testing.assert_allclose(np.asarray(spatial_softmax(jnp.asarray(peak), 1.0))[0], [1.0, 1.0], atol=1e-6)


def test_a_keypoint_encoder_reads_each_channel_as_a_position_and_gives_the_chunk():
    cfg = PolicyNetConfig(width=4, hidden=8, chunk=2, keypoints=True)
    params = stand_in_params(cfg, use_proprio=False)
    assert params["net"]["feat"]["kernel"].shape[0] == 2 * (2 * cfg.width)  # (x, y) of each last-layer channel
    image = jnp.asarray(np.random.default_rng(0).integers(0, 255, (3, 64, 64, 3), dtype=np.uint8))
    chunk = predict_chunk(cfg, params, image, jnp.zeros((3, 37)), jnp.zeros((3,), jnp.int32))
    assert chunk.shape == (3, 2, 20) and np.isfinite(np.asarray(chunk)).all()


def test_random_shift_crops_the_edge_padded_image():
    rng = np.random.default_rng(3)
    images = rng.integers(0, 256, (5, 8, 8, 3), dtype=np.uint8)
    key = jax.random.PRNGKey(1)
    got = np.asarray(zoo.random_shift(jnp.asarray(images), 2, key))
    off = np.asarray(jax.random.randint(key, (5, 2), 0, 5))
    for i in range(5):
        padded = np.pad(images[i], ((2, 2), (2, 2), (0, 0)), mode="edge")
        assert (got[i] == padded[off[i, 0]:off[i, 0] + 8, off[i, 1]:off[i, 1] + 8]).all()
    assert (got != images).any()  # some offset differs from the centre


@pytest.mark.slow  # what only the GPU chain uses (pipeline --warm-rollouts)
def test_the_rollouts_warm_up_runs_the_zoos_planned_policies_as_the_rollouts_then_run_them(smoke_zoo, tmp_path):
    """The zoo writes its plan before training: the registry it then writes, less the losses. The
    rollouts' warm-up runs the plan's checkpoints with stand-in parameters (the shapes, dtypes and
    placement of the saved ones), so the rollouts that follow compile none of the policy's programs
    again (in one process here; across processes on the mjx engine below). It writes no episode."""
    zoo_dir, registry = smoke_zoo
    plan = json.loads((zoo_dir / "plan.json").read_text())["policies"]
    assert [(r["name"], r["net"], r["checkpoint"]) for r in plan] == \
        [(r["name"], r["net"], r["checkpoint"]) for r in registry]
    assert {r["val_loss"] for r in plan} == {None}
    real = resolve([f"{zoo_dir}#conv_proprio"])
    planned = resolve([f"{zoo_dir / 'policies.json'}#conv_proprio"], planned=True)  # the file's sibling plan.json
    assert [s.name for s in planned] == [s.name for s in real]
    signature = lambda t: [(p, np.shape(x), np.asarray(x).dtype) for p, x in jax.tree_util.tree_leaves_with_path(t)]
    assert signature(planned[0].params) == signature(real[0].params)
    np.testing.assert_array_equal(planned[0].params["norm"]["action_std"], 1.0)  # stand-ins, not the checkpoint

    # a chunk of 2 checkpoints x 3 episodes, a stack no other test runs
    cfg = G.make_config("smoke", [f"policies={zoo_dir}#conv_proprio", "policy_episodes=3", "batch=6"])
    learned = [c for c in G._plan(cfg, G.learned_sources(cfg)) if not isinstance(c.key, str)]
    assert [len(c.rows(padded=False)) for c in learned] == [6]

    def compiled(step) -> set:  # the programs `step` compiled
        before = compile_snapshot()
        step()
        return {name for name, (count, _) in compile_snapshot()["by_program"].items()
                if count > before["by_program"].get(name, (0, 0.0))[0]}

    assert "act" in compiled(lambda: G.warm(cfg, progress=False))  # compiled here
    assert list(tmp_path.iterdir()) == []
    rolled = compiled(lambda: G.simulate_chunk(cfg, learned[0], "cpu"))  # the rollouts as generate runs them
    asked = []  # a learned chunk's rollout is the warm-up's to compile: none compiles ahead beside the stage
    with pytest.MonkeyPatch.context() as m:
        m.setattr(G, "record_episodes",
                  lambda *a, compile_ahead=False, **k: asked.append(compile_ahead) or (None, None))
        G.simulate_chunk(cfg, learned[0], "cpu")
    assert asked == [False]
    assert not rolled & {"act", "init_carry", "observe"}
    with pytest.raises(FileNotFoundError, match="plan.json is missing"):
        G.warm(G.make_config("smoke", [f"policies={tmp_path / 'none'}#conv_proprio"]), progress=False)


_ROLLOUTS_IN_A_PROCESS = textwrap.dedent("""
    import json, sys
    import jax
    jax.config.update("jax_compilation_cache_dir", sys.argv[1])
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
    from experiments.timing import compile_snapshot
    from sim_data.dataset import generate as G
    cfg = G.make_config("smoke", sys.argv[3:])
    before = compile_snapshot()
    if sys.argv[2] == "warm":
        G.warm(cfg, progress=False)
    else:  # as the pipeline runs them: after the data stage's scripted chunk, the caches cleared, the rollouts
        chunks = list(G._plan(cfg, G.learned_sources(cfg)))
        G.simulate_chunk(cfg, next(c for c in chunks if isinstance(c.key, str)), cfg.engine, steps=G.WARM_STEPS)
        jax.clear_caches()
        before = compile_snapshot()
        for chunk in chunks:
            if not isinstance(chunk.key, str):
                G.simulate_chunk(cfg, chunk, cfg.engine)
    after = compile_snapshot()
    print(json.dumps({k: after[k] - before[k] for k in ("cache_lookups", "cache_hits")}))
""")


@pytest.mark.slow  # MJX on the CPU: minutes of compiling
def test_the_rollouts_warm_up_fills_the_persistent_cache_that_a_later_process_loads_on_mjx(smoke_zoo, tmp_path):
    """As the pipeline runs them: the warm-up in one process, the rollouts in another that first
    simulated the data stage's scripted chunk and then cleared JAX's caches (a module's text, and so its
    persistent-cache key, follows what its process traced before it), one persistent compilation cache,
    the `mjx` engine. The rollouts compile nothing but the joining of an episode's segments
    (`_recording_of`, a program per episode length: the warm-up runs two segments)."""
    zoo_dir, _ = smoke_zoo
    script = tmp_path / "rollouts.py"
    script.write_text(_ROLLOUTS_IN_A_PROCESS)
    overrides = [f"policies={zoo_dir}#conv_proprio", "policy_episodes=2", "engine=mjx"]

    def run(mode) -> dict:
        out = subprocess.run([sys.executable, str(script), str(tmp_path / "cache"), mode, *overrides], check=True,
                             capture_output=True, text=True, cwd=os.getcwd())
        return json.loads(out.stdout.strip().splitlines()[-1])

    warmed = run("warm")
    assert warmed["cache_lookups"] > warmed["cache_hits"]  # compiled there
    rolled = run("rollouts")
    assert rolled["cache_lookups"] - rolled["cache_hits"] <= 1, rolled


def test_measured_success_is_read_back_only_for_the_same_states_engine_and_policies(smoke_zoo, tmp_path,
                                                                                    monkeypatch):
    """measure_success keeps each task's outcomes; a rerun reads them back where it would measure the
    same policies (as they are now) over the same states with the same engine, and measures again
    otherwise. The simulation is replaced by outcomes that say which call made them."""
    zoo_dir, _ = smoke_zoo
    out = tmp_path / "zoo"
    shutil.copytree(zoo_dir, out)
    calls = []

    def fake(env, policy, params, keys, rng, renderers):
        calls.append(len(keys))
        return np.ones((jax.tree_util.tree_leaves(params)[0].shape[0], len(keys)), bool), None

    monkeypatch.setattr(zoo, "record_policies", fake)
    monkeypatch.setattr(zoo, "cached_env", lambda *a: None)
    monkeypatch.setattr(zoo, "cached_renderers", lambda *a: None)
    first = zoo.measure_success(out, 2, engine="cpu", progress=False)
    n = len(calls)
    assert n >= 1 and all(p["n"] == 2 and p["rate"] == 1.0 for p in first["policies"])
    assert zoo.measure_success(out, 2, engine="cpu", progress=False) == first and len(calls) == n  # read back
    again = zoo.measure_success(out, 3, engine="cpu", progress=False)  # more states: measured again
    assert len(calls) > n and all(p["n"] == 3 for p in again["policies"])
    n = len(calls)
    zoo.measure_success(out, 3, seed=1, engine="cpu", progress=False)
    assert len(calls) > n
    n = len(calls)
    zoo.measure_success(out, 3, seed=1, engine="cpu", progress=False)
    assert len(calls) == n  # read back
    registry = json.loads((out / "policies.json").read_text())  # a checkpoint trained again: other parameters
    recs = registry["policies"]
    recs[0]["checkpoint"] = next(r["checkpoint"] for r in recs[1:] if r["net"] == recs[0]["net"]
                                 and r["task"] == recs[0]["task"])
    (out / "policies.json").write_text(json.dumps(registry))
    zoo.measure_success(out, 3, seed=1, engine="cpu", progress=False)
    assert len(calls) > n


def test_closures_of_a_grip_family_are_its_base_policys_scaled(smoke_zoo, tmp_path):
    """sim_data.bench.closures on the smoke zoo's grip family: the member at grip 0 never closes the hand (every
    failure weak), the member at grip 1 has its base checkpoint's summary, figure for figure."""
    zoo_dir, registry = smoke_zoo
    base = max((r for r in registry if r["lineage"] == "conv_proprio"), key=lambda r: r["step"])["name"]
    out = tmp_path / "closures.json"
    spec = f"{zoo_dir}#conv_proprio~grip+{base}"
    assert closures.main(["--policies", spec, "--episodes", "2", "--engine", "cpu", "--out", str(out)]) == 0
    rows = {r["name"]: r for r in json.loads(out.read_text())["policies"]}
    weak, full = rows["mug/conv_proprio~grip/0"], rows["mug/conv_proprio~grip/1"]
    assert weak["successes"] == 0 and weak["max_success"] is None
    assert weak["max_failure"] == 0.0 and weak["firmest_failure"] == 0.0 and weak["weak_failures"] == 2
    assert {k: v for k, v in full.items() if k != "name"} == {k: v for k, v in rows[base].items() if k != "name"}
    assert rows[base]["max_failure"] > 0.0 or rows[base]["max_success"] > 0.0  # the base does close its hand


def test_closure_summary_by_hand():
    closure = np.array([[0.0, 0.2, 1.0, 0.9], [0.1, 0.3, 0.2, 0.0], [0.5, 0.5, 0.4, 0.6]])
    got = closures.closure_summary(closure, [True, False, False], firmest=2, threshold=0.45)
    assert got == {"successes": 1, "n": 3, "max_success": 1.0, "max_failure": round((0.3 + 0.6) / 2, 4),
                   "firmest_success": 0.95, "firmest_failure": round((0.25 + 0.55) / 2, 4), "weak_failures": 1}
    assert closures.closure_summary(closure[:1], [False], 9, 0.45)["firmest_success"] is None
