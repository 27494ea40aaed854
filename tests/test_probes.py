"""wm.probes: the read loss is the probe checkpoints' action difference on their own tasks' frames,
and only registry checkpoints of behaviour-cloning networks probe."""

import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from sim_data.policies.bc import BCPolicy, PolicyNet, PolicyNetConfig, init_params, normalise_proprio
from sim_data.policies.degrade import DegradedPolicy
from sim_data.policies.registry import PolicySource, perturbed_copy
from sim_data.sim import robot as R
from wm import probes as PR
from wm.config import make_config
from wm.train import main as train_main
from wm.train import read_probes

NET = PolicyNetConfig(width=4, hidden=8, chunk=2, size=16)
VIT = PolicyNetConfig(encoder="vit", width=8, depth=1, hidden=8, chunk=2, size=16)


def _params(net, seed):
    rs = np.random.default_rng(seed)
    norm = {"proprio_mean": rs.normal(size=R.PROPRIO_DIM), "proprio_std": rs.uniform(0.5, 2, R.PROPRIO_DIM),
            "action_mean": rs.normal(size=R.ACTION_DIM), "action_std": rs.uniform(0.5, 2, R.ACTION_DIM)}
    p = init_params(net, jax.random.PRNGKey(seed), norm, use_proprio=True)
    # the head starts at zero (every chunk 0): random weights, so that the frames change the actions
    p["net"]["head"]["kernel"] = jnp.asarray(rs.normal(size=p["net"]["head"]["kernel"].shape), jnp.float32)
    return jax.tree_util.tree_map(np.asarray, p)


def _source(name, task, net=NET, seed=0, kind="learned"):
    return PolicySource(name=name, kind=kind, task=task, policy=BCPolicy(net), params=_params(net, seed), record={})


def _inputs(n=6, seed=0):
    rs = np.random.default_rng(seed)
    pred, target = (rs.uniform(0, 1, (n, 16, 16, 3)).astype(np.float32) for _ in range(2))
    return (pred, target, rs.normal(size=(n, R.PROPRIO_DIM)).astype(np.float32),
            rs.integers(0, 100, n).astype(np.int32), np.array([0, 0, 1, 1, 2, 2], np.int32)[:n])


@pytest.mark.slow  # an option no preset uses (make test-slow runs it)
def test_the_read_loss_is_each_frames_probes_squared_action_difference():
    sources = [_source("a/conv/1", "a", seed=1), _source("b/conv/2", "b", seed=2), _source("a/vit/3", "a", VIT, 3)]
    probes = PR.make_probes(sources, ["a", "b", "c"])
    assert probes.count == 3 and len(probes.nets) == 2
    pred, target, proprio, t, task = _inputs()
    errs = []
    # task a's two frames go to its two probes in turn (row 0 to a/conv/1, row 1 to a/vit/3), task b's
    # two to its one probe; task c has none, so its frames count for nothing
    for s, row in ((sources[0], 0), (sources[2], 1), (sources[1], 2), (sources[1], 3)):
        read = lambda img, s=s: np.asarray(PolicyNet(s.policy.cfg).apply(  # noqa: E731
            {"params": s.params["net"]}, img * 255.0, normalise_proprio(s.params, proprio), t))
        errs.append(((read(pred) - read(target)) ** 2).mean(axis=(1, 2))[row])
    want = sum(errs) / 4
    got = float(jax.jit(PR.read_loss)(probes, pred, target, proprio, t, task))
    np.testing.assert_allclose(got, want, rtol=1e-4)
    assert got > 0
    assert float(PR.read_loss(probes, target, target, proprio, t, task)) == 0.0


def test_the_read_loss_weighs_the_hands_closure_by_read_closure():
    """With read_dims(w), a frame's error is the mean over its chunk of the action dimensions' squared
    differences weighted by w (the two closure commands at w, the other 18 at 1) over their sum; at 1
    the plain mean, and the config refuses a weight <= 0."""
    sources = [_source("a/conv/1", "a", seed=1)]
    probes = PR.make_probes(sources, ["a"])
    pred, target, proprio, t, _ = _inputs(4)
    task = np.zeros(4, np.int32)
    s = sources[0]
    read = lambda img: np.asarray(PolicyNet(s.policy.cfg).apply(  # noqa: E731
        {"params": s.params["net"]}, img * 255.0, normalise_proprio(s.params, proprio), t))
    per_dim = ((read(pred) - read(target)) ** 2).mean(axis=1)  # (4 frames, 20)
    closure = per_dim[:, R.HAND_CLOSURE].sum(1)
    want = ((per_dim.sum(1) - closure + 10 * closure) / (18 + 2 * 10)).mean()
    assert PR.read_dims(1.0) is None
    w = PR.read_dims(10.0)
    assert w.shape == (R.ACTION_DIM,) and w[R.HAND_CLOSURE].tolist() == [10.0, 10.0] and w.sum() == 38.0
    got = float(jax.jit(PR.read_loss)(probes, pred, target, proprio, t, task, w))
    np.testing.assert_allclose(got, want, rtol=1e-4)
    plain = float(PR.read_loss(probes, pred, target, proprio, t, task))
    np.testing.assert_allclose(float(PR.read_loss(probes, pred, target, proprio, t, task, np.ones(R.ACTION_DIM))),
                               plain, rtol=1e-6)
    assert abs(got - plain) > 1e-3 * plain
    with pytest.raises(ValueError, match="read_closure"):
        make_config("smoke", ["read_closure=0"])


def test_the_read_loss_trains_the_predicted_frames_alone_and_ignores_other_tasks():
    probes = PR.make_probes([_source("a/conv/1", "a", seed=1)], ["a", "b", "c"])
    pred, target, proprio, t, task = _inputs()
    g_pred, g_target = jax.grad(PR.read_loss, argnums=(1, 2))(probes, pred, target, proprio, t, task)
    assert np.abs(np.asarray(g_pred[:2])).sum() > 0  # task a's rows
    np.testing.assert_array_equal(np.asarray(g_pred[2:]), 0.0)  # tasks b and c: no probe of theirs
    np.testing.assert_array_equal(np.asarray(g_target), 0.0)
    only_c = np.full_like(task, 2)
    assert float(PR.read_loss(probes, pred, target, proprio, t, only_c)) == 0.0


def test_a_tasks_frames_go_to_its_probes_in_turn_up_to_each_probes_capacity():
    # three probes of task 0 (names sorted: turns 0, 1, 2) and one of task 1
    sources = [_source(f"a/conv/{k}", "a", seed=k) for k in range(3)] + [_source("b/conv/9", "b", seed=9)]
    probes = PR.make_probes(sources, ["a", "b"])
    np.testing.assert_array_equal(probes.turns[0], [0, 1, 2, 0])
    np.testing.assert_array_equal(probes.shares[0], [3, 3, 3, 1])
    task = np.array([0, 0, 0, 0, 0, 0, 1, 0], np.int32)  # task 0's frames by place: rows 0-5 then 7
    (rows, valid), = PR.probe_rows(probes, jnp.asarray(task))
    assert rows.shape == (4, PR.row_capacity(8, 4)) == (4, 4)
    got = [sorted(np.asarray(rows)[p][np.asarray(valid)[p]].tolist()) for p in range(4)]
    assert got == [[0, 3, 7], [1, 4], [2, 5], [6]]
    # every frame of one task with a single probe of it: that probe reads its capacity, the first 4
    one = PR.make_probes([sources[0]] + [_source(f"b/conv/{k}", "b", seed=k) for k in range(3)], ["a", "b"])
    (rows, valid), = PR.probe_rows(one, jnp.zeros(8, jnp.int32))
    assert np.asarray(rows)[0][np.asarray(valid)[0]].tolist() == [0, 1, 2, 3]
    assert not np.asarray(valid)[1:].any()


def test_bfloat16_probes_read_as_the_float32_checkpoints_do_within_bfloat16_rounding():
    sources = [_source("a/conv/1", "a", seed=1), _source("a/vit/3", "a", VIT, 3)]
    f32, bf16 = (PR.make_probes(sources, ["a", "b", "c"], d) for d in ("float32", "bfloat16"))
    assert {x.dtype for x in jax.tree_util.tree_leaves(bf16.params[0]["net"])} == {np.dtype(jnp.bfloat16)}
    assert bf16.params[0]["norm"]["proprio_std"].dtype == np.float32  # the normalisation keeps its precision
    _, target, proprio, t, _ = _inputs()
    rows = PR.probe_rows(f32, jnp.zeros(len(t), jnp.int32))
    for a, b in zip(PR.readings(f32, target, proprio, t, rows), PR.readings(bf16, target, proprio, t, rows),
                    strict=True):
        a, b = np.asarray(a), np.asarray(b)
        assert b.dtype == np.float32 and b.shape == a.shape
        # bfloat16 keeps 8 significant bits: about 1% of the readings' spread
        assert np.abs(a - b).max() < 0.05 * np.abs(a).max()
        assert np.corrcoef(a.ravel(), b.ravel())[0, 1] > 0.99


def test_probes_are_registry_checkpoints_of_networks_spread_over_their_names():
    learned = [_source(f"a/conv/{k}", "a") for k in range(6)]
    others = [
        _source("my.plugin:make", None, kind="plugin"),
        perturbed_copy(_source("a/conv/9", "a")),
        PolicySource("a/conv~noise/0.2", "learned", "a", DegradedPolicy(BCPolicy(NET)), {}, {}),
        _source("z/conv/1", "z"),  # a task the world model does not learn
    ]
    pols = {s.name: s for s in learned + others}
    assert [s.name for s in PR.probe_sources(pols, ["a", "b"], 16, 8)] == [s.name for s in learned]
    # six in name order (a/conv/0 .. a/conv/5), three spread evenly: the first, one between, the last
    assert [s.name for s in PR.probe_sources(pols, ["a", "b"], 16, 3)] == ["a/conv/0", "a/conv/2", "a/conv/5"]
    assert PR.probe_sources({}, ["a"], 16, 3) == [] and PR.make_probes([], ["a"]) is None
    with pytest.raises(ValueError, match="16x16 frames"):
        PR.probe_sources(pols, ["a"], 64, 3)


def test_the_read_loss_refuses_a_dataset_without_checkpoint_rollouts(tmp_path):
    (tmp_path / "config.json").write_text(json.dumps({"policies": []}))
    cache = type("Cache", (), {"tasks": ["mug"]})()
    assert read_probes(make_config("smoke"), cache, tmp_path) is None  # w_read 0: nothing to read with
    with pytest.raises(ValueError, match="behaviour-cloning checkpoints"):
        read_probes(make_config("smoke", ["w_read=0.1"]), cache, tmp_path)
    with pytest.raises(ValueError, match="w_read"):
        make_config("smoke", ["w_read=-1"])
    with pytest.raises(ValueError, match="read_probes"):
        make_config("smoke", ["read_probes=0"])


def test_probe_policies_go_with_the_warm_up_alone(tmp_path, capsys):
    with pytest.raises(SystemExit):
        train_main(["--data", str(tmp_path), "--out", str(tmp_path / "run"), "--probe-policies", "runs/policies/x#conv"])
    assert "--probe-policies goes with --warm" in capsys.readouterr().err
    cache = type("Cache", (), {"tasks": ["a"]})()
    cfg = make_config("smoke", ["w_read=0.1"])
    net = PolicyNetConfig(width=4, hidden=8, chunk=2, size=cfg.model.size)
    given = {"a/conv/1": _source("a/conv/1", "a", net)}
    (tmp_path / "config.json").write_text(json.dumps({"policies": []}))  # the data's own rollouts: none
    got = read_probes(cfg, cache, tmp_path, given)
    assert got.count == 1 and got.nets == (net,)


def test_the_probe_studys_stand_ins_read_zero_where_they_are_the_true_frames():
    from experiments.probe_study import main as study_main
    from experiments.probe_study import stand_in_terms

    probes = PR.make_probes([_source("a/conv/1", "a", seed=1), _source("b/conv/2", "b", seed=2)], ["a", "b"])
    rs = np.random.default_rng(0)
    still = rs.integers(0, 256, (2, 1, 16, 16, 3), dtype=np.uint8)  # each window one frame throughout
    batch = {"frames": np.repeat(still, 9, axis=1), "proprio": rs.normal(size=(2, 9, R.PROPRIO_DIM)).astype(np.float32),
             "task": np.array([0, 1], np.int32), "start": np.array([3, 40], np.int32)}
    got = stand_in_terms(probes, batch)
    assert got["copy_last"] == 0.0 and got["first_held"] == 0.0  # the still windows' own frames
    assert got["grey"] > 0
    # another window's frames: window 0 shown window 1's frame and the reverse, read by each window's own probe
    pix = batch["frames"][:, 1:].astype(np.float32) / 255.0
    want = PR.read_loss(probes, pix[::-1, ::4].reshape(-1, 16, 16, 3), pix[:, ::4].reshape(-1, 16, 16, 3),
                        batch["proprio"][:, 1::4].reshape(-1, R.PROPRIO_DIM),
                        (batch["start"][:, None] + 1 + np.arange(0, 8, 4)).reshape(-1).astype(np.int32),
                        np.repeat(batch["task"], 2))
    np.testing.assert_allclose(got["other_window"], float(want), rtol=1e-5)
    assert got["other_window"] > 0
    with pytest.raises(SystemExit):
        study_main(["--runs", "no/such/run"])
