"""The judge study's pieces on imaginations whose outcome a feature decides."""

import json

import jax
import numpy as np
import pytest

from experiments import judge_study as J
from experiments import stats as S
from wm import judge as WJ
from wm.config import make_config
from wm.imagine import Norm, feature_columns, feature_dim


def kept(rng, policies=12, states=16, steps=(5, 7)):
    """Two tasks' kept features (P, N, T, 6) and outcomes: each policy's rate spread over [0, 1]; an
    episode succeeds where its feature 0 (constant over time) is positive."""
    features, true = {}, {}
    for t, T in zip(("a", "b"), steps, strict=True):
        rate = np.linspace(0.05, 0.95, policies)
        y = rng.random((policies, states)) < rate[:, None]
        x = rng.normal(size=(policies, states, T, 6)).astype(np.float16)
        x[..., 0] = np.where(y, 1.0, -1.0)[..., None] + 0.1 * rng.normal(size=(policies, states, 1))
        features[t], true[t] = x, y
    return features, true


def test_evaluation_episodes_pad_and_label_each_task(np_rng):
    features, true = kept(np_rng)
    d = J.evaluation_episodes(features, true, {"a": np.array([0, 3]), "b": np.array([1])})
    assert d["features"].shape == (3 * 16, 7, 6) and d["task"] == ["a"] * 32 + ["b"] * 16
    assert d["mask"][:32].sum(1).tolist() == [5] * 32 and d["mask"][32:].all()
    assert not d["features"][:32, 5:].any()
    assert d["label"].tolist() == true["a"][[0, 3]].reshape(-1).tolist() + true["b"][1].tolist()
    np.testing.assert_array_equal(d["features"][16:32, :5], features["a"][3].astype(np.float32))


@pytest.mark.slow  # a diagnostic's bound (experiments.judge_study); make test keeps its observed bound
def test_the_crossfit_bound_reads_an_outcome_the_imaginations_carry(np_rng):
    features, true = kept(np_rng)
    probs = J.crossfit_bound(features, true, ("a", "b"), steps=150, seed=0)
    for t in ("a", "b"):
        assert probs[t].shape == true[t].shape
        # every fold is read by a judge that never saw its policies, and still follows feature 0
        assert S.pearson(probs[t].mean(1), true[t].mean(1))[0] > 0.9
        assert ((probs[t] > 0.5) == true[t]).mean() > 0.9


def test_an_unknown_variant_is_refused(tmp_path):
    with pytest.raises(ValueError, match="unknown variants"):
        J.study(tmp_path, tmp_path / "out", wm_run=tmp_path, variants=["bigger"])


def test_a_dataset_whose_policies_do_not_load_from_here_is_refused(tmp_path):
    (tmp_path / "config.json").write_text(json.dumps({"policies": ["runs/policies/elsewhere#conv_noproprio"]}))
    with pytest.raises(FileNotFoundError, match="cannot be loaded from here"):
        J.loaded_policies(tmp_path)
    (tmp_path / "config.json").write_text(json.dumps({"policies": []}))
    assert J.loaded_policies(tmp_path) == {}  # scripted data: nothing to imagine closed loop


def test_the_observed_bound_reads_the_simulated_episodes_with_a_judge_of_true_frames(np_rng):
    features, true = kept(np_rng)
    every = {t: np.arange(len(true[t])) for t in true}
    train = J.evaluation_episodes(*kept(np_rng), every)  # other episodes of the same kind: the training set's
    val = J.evaluation_episodes(*kept(np_rng, states=4), every)
    probs, metrics = J.observed_bound(train, val, features, ("a", "b"), steps=150, seed=0)
    assert metrics["val_auroc"] > 0.95
    for t in ("a", "b"):
        assert probs[t].shape == true[t].shape and ((probs[t] > 0.5) == true[t]).mean() > 0.9


def test_an_observed_variant_learns_from_both_readings_of_the_same_episodes(np_rng, monkeypatch):
    features, true = kept(np_rng)
    every = {t: np.arange(len(true[t])) for t in true}
    train = J.evaluation_episodes(features, true, every)
    seen = {**train, "features": train["features"] + 1.0}
    got = {}
    monkeypatch.setattr(J, "fit", lambda learn, val, *a, **k: got.update(learn=learn) or (None, {}))
    wm_cfg = make_config("smoke")
    J.fit_variant(J.VARIANTS["all"], train, None, ("a", "b"), wm_cfg, 10, seen)
    assert len(got["learn"]["label"]) == len(train["label"])
    J.fit_variant(J.VARIANTS["all_observed"], train, None, ("a", "b"), wm_cfg, 10, seen)
    n = len(train["label"])
    assert len(got["learn"]["label"]) == 2 * n and got["learn"]["task"] == train["task"] * 2
    np.testing.assert_array_equal(got["learn"]["features"][n:], seen["features"])
    # the judge of true frames alone: the same episodes' true readings, and no imagination
    J.fit_variant(J.VARIANTS["observed_only"], train, None, ("a", "b"), wm_cfg, 10, seen)
    assert got["learn"]["task"] == train["task"] and got["learn"]["label"].tolist() == train["label"].tolist()
    np.testing.assert_array_equal(got["learn"]["features"], seen["features"])


def test_a_variant_fits_its_judge_at_its_seed_learning_rate_and_members(np_rng, monkeypatch):
    features, true = kept(np_rng)
    train = J.evaluation_episodes(*kept(np_rng), {t: np.arange(len(true[t])) for t in true})
    calls, real = [], J.fit

    def fit(learn, val, tasks, steps, seed, progress=True, columns=None, lr=None, members=1, select="best",
            raw_mean=False):
        calls.append((seed, lr, members, select, raw_mean))  # every column: the kept features are not a world model's
        return real(learn, val, tasks, steps, seed, progress=False, lr=lr, members=members, select=select,
                    raw_mean=raw_mean)

    monkeypatch.setattr(J, "fit", fit)
    wm_cfg = make_config("smoke", ["seed=1"])
    probs, metrics = J.read_variant(J.Variant(seed=2, members=3, lr=1e-3), train, None, ("a", "b"), wm_cfg, 30,
                                    features)
    assert calls == [(3, 1e-3, 3, "best", False)] and metrics["members"] == 3
    assert J.VARIANTS["all_x6"].members == 6 and J.VARIANTS["all_lr5e-4"].lr == 5e-4
    assert J.VARIANTS["all_lr5e-4_x6_last"].select == "last"
    # the presets' own judges, and the same pooling the features' own mean
    demo, raw = J.VARIANTS["demo_recipe"], J.VARIANTS["demo_recipe_raw_mean"]
    assert (demo.inputs, demo.lr, demo.members, demo.select, demo.raw_mean) == (("proprio", "action"), 5e-4, 6, "last",
                                                                                False)
    assert raw == J.dataclasses.replace(demo, raw_mean=True)
    full, full2 = J.VARIANTS["full_recipe"], J.VARIANTS["full_judge2"]
    assert (full.inputs, full.lr, full.members, full.select) == (("proprio", "action"), 5e-4, 6, "best")
    assert "scene" not in full2.inputs and "latent" in full2.inputs and full2.select == "best"
    assert J.VARIANTS["full_recipe_raw_mean"] == J.dataclasses.replace(full, raw_mean=True)
    # the presets' judges without the actions: the body alone, or every imagined group but the scene head's
    assert J.VARIANTS["demo_recipe_proprio"] == J.dataclasses.replace(demo, inputs=("proprio",))
    seen = J.VARIANTS["full_recipe_seen"]
    assert seen == J.dataclasses.replace(full, inputs=seen.inputs)
    assert "action" not in seen.inputs and "scene" not in seen.inputs and {"proprio", "latent"} <= set(seen.inputs)
    for t in ("a", "b"):
        assert probs[t].shape == true[t].shape and ((probs[t] > 0.5) == true[t]).mean() > 0.9


def test_kept_imaginations_read_back_with_their_labels_and_rollout_flags(tmp_path, np_rng):
    d = {"features": np_rng.normal(size=(3, 4, 5)).astype(np.float32), "mask": np.ones((3, 4), bool),
         "task": ["a", "b", "a"], "label": np.array([True, False, True]), "rollout": np.array([False, True, True])}
    path = tmp_path / "imagined_train_3.npz"
    J.imagined(path, lambda: d)
    back = J.imagined(path, lambda: pytest.fail("a kept file is read, not made again"))
    assert back["task"] == d["task"] and back["label"].tolist() == d["label"].tolist()
    assert back["rollout"].tolist() == d["rollout"].tolist()  # what a resumed study's summary counts
    np.testing.assert_allclose(back["features"], d["features"], atol=2e-3)  # kept as float16


def test_replayed_labels_are_the_simulated_outcomes_of_the_imagined_actions(monkeypatch):
    """Closed-loop rows take the simulator's outcome of their own imagined actions (unstandardised,
    played from the episode's seed), task by task; open-loop rows keep their label."""
    cfg = make_config("smoke")
    F, cols = feature_dim(cfg.model), feature_columns(cfg.model, ("action",))
    episodes = [{"task": "mug", "seed": 7}, {"task": "step_back", "seed": 8}, {"task": "mug", "seed": 9},
                {"task": "step_back", "seed": 10}]
    cache = type("Cache", (), {"episodes": {10 + k: e for k, e in enumerate(episodes)}})()
    ids = [10, 11, 12, 13]
    actions = np.arange(4 * 3 * 20, dtype=np.float32).reshape(4, 3, 20) / 100.0
    norm = Norm(proprio_mean=np.zeros(37), proprio_std=np.ones(37), action_mean=np.full(20, 0.5),
                  action_std=np.full(20, 2.0))
    x = np.zeros((4, 5, F), np.float32)
    x[:, :3, cols] = (actions - 0.5) / 2.0
    mask = np.arange(5)[None].repeat(4, 0) < np.array([[3], [3], [3], [3]])
    d = {"features": x, "mask": mask, "label": np.array([True, True, False, False]),
         "rollout": np.array([True, True, False, True])}
    calls = []

    def simulate(task, acts, keys, engine):
        calls.append((task, acts, keys, engine))
        return np.array([[task == "step_back"] * len(acts)])  # step_back's replays succeed, mug's fail

    monkeypatch.setattr(WJ, "simulate_actions", simulate)
    batch = WJ.replay_batch(cache, [(ids, d["rollout"])])
    assert batch == 2  # step_back's two closed-loop rows: one batch size for every task
    got = WJ.replayed_labels(cfg.model, norm, cache, ids, d, d["rollout"], "cpu", batch)
    assert got.tolist() == [False, True, False, True]  # row 2 is open loop: its label stays
    assert [c[0] for c in calls] == ["mug", "step_back"] and {c[3] for c in calls} == {"cpu"}
    np.testing.assert_allclose(calls[0][1], actions[[0, 0]], atol=1e-6)  # mug's one row, padded with itself
    np.testing.assert_allclose(calls[1][1], actions[[1, 3]], atol=1e-6)
    np.testing.assert_array_equal(calls[1][2], np.stack([np.asarray(jax.random.PRNGKey(s)) for s in (8, 10)]))
    calls.clear()  # in batches of one: a call per row
    assert WJ.replayed_labels(cfg.model, norm, cache, ids, d, d["rollout"], "cpu", 1).tolist() == got.tolist()
    assert [c[0] for c in calls] == ["mug", "step_back", "step_back"] and all(len(c[1]) == 1 for c in calls)
    assert J.VARIANTS["demo_recipe_replay"] == J.dataclasses.replace(J.VARIANTS["demo_recipe"], replay_labels=True)
    assert J.VARIANTS["full_recipe_replay"].replay_labels and not J.VARIANTS["full_recipe"].replay_labels


def test_saved_readings_are_reused_only_where_fit_as_their_variant_is_now_defined(tmp_path, capsys):
    now = json.dumps(J.variant_definition("full_recipe"))
    other = json.dumps(J.dataclasses.asdict(J.VARIANTS["full_judge2"]))
    for stem, fields in (("now", {"__variant__": now}), ("other", {"__variant__": other}), ("unrecorded", {})):
        np.savez(tmp_path / f"{stem}.npz", __fit__="{}", mug=np.zeros((2, 3)), **fields)
    assert J.fit_matches(tmp_path / "now.npz", "full_recipe")
    assert not J.fit_matches(tmp_path / "other.npz", "full_recipe")
    assert "fitting it again" in capsys.readouterr().err
    assert not J.fit_matches(tmp_path / "unrecorded.npz", "full_recipe")
    assert J.variant_definition(J.BOUND) is None
    # the presets' judges follow wm.config, observed and replayed labels included
    replay = J.dataclasses.replace(J.preset_judge("demo"), replay_labels=True)
    assert J.VARIANTS["demo_recipe_replay"] == replay and not J.preset_judge("full").observed
