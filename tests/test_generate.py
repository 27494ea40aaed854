"""make data's generator: files read back, determinism, resume, bad input."""

import base64
import dataclasses
import itertools
import json
import shutil

import cv2
import jax
import numpy as np
import pytest
from mcap.reader import make_reader

from sim_data.dataset import generate as G
from sim_data.dataset.episodes import read_episode
from sim_data.policies.registry import PolicySource, fingerprint
from sim_data.policies.scripted import PROGRAMS
from sim_data.sim import robot as R
from sim_data.util import even_pieces

TOPICS = {"/head_cam/image", "/ext_cam/image", "/robot_state", "/action", "/task_state", "/sim_state", "/tf", "/scene"}


@pytest.fixture
def smoke(smoke_dataset):
    return smoke_dataset


def test_manifest_and_stats(smoke):
    cfg, out, stats = smoke
    rows = [json.loads(line) for line in (out / "manifest.jsonl").read_text().splitlines()]
    programs = len(cfg.tasks) * cfg.programs * len(PROGRAMS)
    assert len(rows) == cfg.episodes * len(cfg.tasks) * len(cfg.skills) + programs == stats["episodes"]
    assert sum(r["policy_kind"] == "program" and r["split"] == "programs" for r in rows) == programs > 0
    for r in rows:
        for k in ("episode_id", "task", "policy", "skill", "seed", "success", "num_steps", "split", "file", "engine",
                  "renderer"):
            assert k in r
        assert (out / r["file"]).exists() and r["split"] in G.SPLITS and r["engine"] == "cpu"
    rows = [r for r in rows if r["policy"] == "scripted@1.00"]
    per = next(p for p in stats["per_task_policy"] if p["policy"] == "scripted@1.00")
    k = sum(r["success"] for r in rows)
    assert per["episodes"] == len(rows) and per["success_rate"] == k / len(rows)
    lo, hi = per["success_ci95"]
    assert lo <= k / len(rows) <= hi


def test_mcap_reads_back_with_every_image_decoded(smoke):
    cfg, out, _ = smoke
    row = json.loads((out / "manifest.jsonl").read_text().splitlines()[0])
    counts, successes = {}, []
    with open(out / row["file"], "rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        assert summary is not None and summary.chunk_indexes  # indexed and chunked
        assert {c.compression for c in summary.chunk_indexes} == {"zstd"}
        for schema, channel, message in reader.iter_messages():
            counts[channel.topic] = counts.get(channel.topic, 0) + 1
            body = json.loads(message.data)
            if channel.topic.endswith("/image"):
                assert schema.name == "foxglove.CompressedImage" and schema.encoding == "jsonschema"
                img = cv2.imdecode(np.frombuffer(base64.b64decode(body["data"]), np.uint8), cv2.IMREAD_COLOR)
                assert img.shape == (cfg.size, cfg.size, 3) and body["format"] == "jpeg"
            if channel.topic == "/task_state":
                successes.append(body["success"])
                assert 0.0 <= body["progress"] <= 1.0 and (body["progress"] == 1.0 or not body["success"])
        meta = G.read_episode_meta(out / row["file"])
    steps = row["num_steps"]
    assert set(counts) == TOPICS
    assert counts["/action"] == steps and counts["/head_cam/image"] == counts["/sim_state"] == counts["/tf"] == steps + 1
    assert counts["/scene"] == 1
    assert successes[-1] == row["success"] == meta["success"] and meta["config"]["episodes"] == cfg.episodes


@pytest.mark.slow  # the parts are what only a host of several GPUs runs (sim_data.parts)
def test_same_config_gives_same_bytes_in_parts_and_resume_completes(smoke, tmp_path):
    cfg, out, _ = smoke
    files = sorted(p.name for p in (out / "episodes").iterdir())
    again = tmp_path / "again"
    # in two parts, as on two GPUs (sim_data.parts), each a share of the chunks, then gathered
    assert G.generate(cfg, again, progress=False, part=(0, 2)) is None
    first = sorted(p.name for p in (again / "episodes").iterdir())
    assert 0 < len(first) < len(files) and not (again / "manifest.jsonl").exists()
    assert G.generate(cfg, again, progress=False, part=(1, 2)) is None
    gathered = G.generate(cfg, again, progress=False)["throughput"]
    assert gathered["episodes_generated"] == 0
    assert sorted(t["episodes_generated"] for t in gathered["parts"]) == sorted([len(first), len(files) - len(first)])
    assert (again / "manifest.jsonl").read_bytes() == (out / "manifest.jsonl").read_bytes()
    for name in files:
        assert (again / "episodes" / name).read_bytes() == (out / "episodes" / name).read_bytes()
    cached = sorted(p.relative_to(out) for p in (out / "cache").rglob("*") if p.is_file())
    assert cached and cached == sorted(p.relative_to(again) for p in (again / "cache").rglob("*") if p.is_file())
    for rel in cached:
        assert (again / rel).read_bytes() == (out / rel).read_bytes(), rel
    # a killed run: one episode missing, one half-written temporary file left behind
    victim = again / "episodes" / files[0]
    victim.unlink()
    (again / "episodes" / (files[1] + ".tmp")).write_bytes(b"half")
    stats = G.generate(cfg, again, progress=False)
    assert stats["throughput"]["episodes_generated"] == 1
    assert victim.read_bytes() == (out / "episodes" / files[0]).read_bytes()
    assert sorted(p.name for p in (again / "episodes").iterdir()) == files


def test_corrupt_file_is_named(smoke, tmp_path):
    _, out, _ = smoke
    src = next((out / "episodes").iterdir())
    bad = tmp_path / src.name
    bad.write_bytes(src.read_bytes()[: src.stat().st_size // 2])
    with pytest.raises(G.CorruptEpisode, match=src.name):
        G.read_episode_meta(bad)


def test_bad_configuration_is_refused_before_work(tmp_path):
    with pytest.raises(ValueError, match="episodes"):
        G.make_config("smoke", ["episodes=0"])
    with pytest.raises(ValueError, match="unknown"):
        G.make_config("smoke", ["tasks=mug,juggling"])
    with pytest.raises(ValueError, match="unknown setting 'epsiodes'"):
        G.make_config("smoke", ["epsiodes=3"])
    with pytest.raises(ValueError, match="unknown preset"):
        G.make_config("huge")
    with pytest.raises(ValueError, match="drive and perturb_episodes must be >= 0"):
        G.make_config("smoke", ["weak_grip=-1"])
    with pytest.raises(ValueError, match="play_nod is a chance"):
        G.make_config("smoke", ["play_nod=-0.1"])
    with pytest.raises(ValueError, match="skills must differ by at least 0.01"):  # both would be episodes "s030"
        G.make_config("smoke", ["skills=0.3,0.304"])
    with pytest.raises(ValueError, match="names a task twice"):
        G.make_config("smoke", ["tasks=mug,mug"])
    with pytest.raises(SystemExit):
        G.main(["--config", "smoke", "--out", str(tmp_path / "x"), "size=96"])
    assert not (tmp_path / "x").exists()


def test_another_config_is_not_mixed_into_a_dataset(smoke, tmp_path):
    cfg, out, _ = smoke
    copy = tmp_path / "copy"
    shutil.copytree(out, copy)
    with pytest.raises(ValueError, match="another configuration"):
        G.generate(G.make_config("smoke", ["seed=5"]), copy, progress=False)


def test_a_rerun_may_change_the_workers_but_not_the_engine_or_what_its_policies_compute(smoke, tmp_path):
    """config.json names the engine and the learned policies by their specs alone: sources.json records
    the engine resolved and each policy's fingerprint, and a rerun (or a reused dataset) that would mix
    other episodes into the finished ones is refused; the writer processes change no episode."""
    _, out, _ = smoke
    copy = tmp_path / "copy"
    shutil.copytree(out, copy)
    assert json.loads((copy / G.SOURCES_FILE).read_text()) == {"engine": "cpu", "actions": "applied", "policies": {}}
    G.generate(G.make_config("smoke", ["workers=1"]), copy, progress=False)  # nothing left to simulate
    with pytest.raises(ValueError, match="simulated with the cpu engine, and this run would use mjx"):
        G._check_sources_match(copy, [], "mjx")
    with pytest.raises(ValueError, match=r"\(reused\) holds episodes simulated with the cpu engine"):
        G._check_sources_match(tmp_path / "new", [], "mjx", reuse=copy)
    src = PolicySource("mine", "plugin", None, "a policy", {"w": np.zeros(2)}, {"plugin": "mine"})
    mixed = tmp_path / "mixed"
    mixed.mkdir()
    G._check_sources_match(mixed, [src], "cpu")
    G._check_sources_match(mixed, [src], "cpu")  # the same policy: resumes
    with pytest.raises(ValueError, match=r"now compute otherwise or are no longer named \(\['mine'\]"):
        G._check_sources_match(mixed, [dataclasses.replace(src, params={"w": np.ones(2)})], "cpu")
    # rollouts whose actions are recorded as asked (no "actions" entry) are neither resumed nor reused;
    # scripted episodes alone are the same either way
    older = tmp_path / "older"
    older.mkdir()
    (older / G.SOURCES_FILE).write_text(json.dumps({"engine": "cpu", "policies": {}}))
    G._check_sources_match(tmp_path / "new1", [], "cpu", reuse=older)
    (older / G.SOURCES_FILE).write_text(json.dumps({"engine": "cpu", "policies": {"mine": fingerprint(src)}}))
    for out, reuse, says in ((older, None, "holds"), (tmp_path / "new2", older, r"\(reused\) holds")):
        with pytest.raises(ValueError, match=says + " rollouts whose actions are recorded as the policies asked"):
            G._check_sources_match(out, [src], "cpu", reuse=reuse)


def test_drives_join_a_reused_dataset_only_where_no_weak_grip_shares_their_chunks(tmp_path):
    base = G.make_config("smoke", ["weak_grip=2", "programs=1"])
    reused = tmp_path / "reused"
    reused.mkdir()
    (reused / "config.json").write_text(json.dumps(dataclasses.asdict(base)))
    with pytest.raises(ValueError, match=r"other settings \(\['drive'\]\)"):
        G.link_shared_episodes(dataclasses.replace(base, drive=2), tmp_path / "out", reused)


def test_chunks_group_by_compiled_rollout_across_tasks_and_parts_begin_on_different_ones():
    plan = [("mug", 1.0, [0]), ("mug", 0.5, [1]), ("mug", "play", [2]), ("wipe", 1.0, [3]), ("wipe", "reach_mug", [4]),
            ("wipe", "play", [5])]
    key = lambda c: G.rollout_key(c[1])  # noqa: E731
    keys = list(dict.fromkeys(key(c) for c in plan))
    assert keys == ["scripted", "program"]  # the task is data: one rollout serves both tasks
    grouped = G.staggered(plan, key, keys, None)
    assert [c[2][0] for c in grouped] == [0, 1, 3, 2, 4, 5] == [c[2][0] for c in G.staggered(plan, key, keys, (0, 2))]
    assert [c[2][0] for c in G.staggered(plan, key, keys, (1, 2))] == [2, 4, 5, 0, 1, 3]  # the programs first


@dataclasses.dataclass(frozen=True)
class _Arch:
    """A stand-in policy object: learned sources sharing one share a compiled rollout."""

    name: str


def _rows(chunk, padded=False):
    return [(s.name if isinstance(s, PolicySource) else s, i) for s, i in chunk.rows(padded)]


def test_a_tasks_rows_of_one_rollout_share_chunks_cut_evenly_and_padded_only_to_the_chunk_size():
    cfg = G.make_config("smoke", ["tasks=mug,wipe", "skills=0.5,1.0", "episodes=3", "batch=4", "play=2",
                                  "policy_episodes=2"])
    a, b = _Arch("a"), _Arch("b")
    learned = [PolicySource(f"mug/a/{k}", "learned", "mug", a, None, {}) for k in range(3)]
    learned += [PolicySource("wipe/b/0", "learned", "wipe", b, None, {})]
    plan = G._plan(cfg, learned)
    mug = [c for c in plan if c.task == "mug"]
    key_a, key_b = G.rollout_key(learned[0]), G.rollout_key(learned[-1])  # the policy and its parameters' layout
    assert key_a[0] is a and key_b[0] is b
    assert [c.key for c in mug] == ["scripted", "scripted", "program", "program", key_a, key_a]
    # 6 scripted rows in the fewest chunks of at most 4: two of 3, not 4 and 2 padded to 4
    assert [_rows(c) for c in mug[:2]] == [[(0.5, 0), (0.5, 1), (0.5, 2)], [(1.0, 0), (1.0, 1), (1.0, 2)]]
    # the programs and random play share ProgramPolicy: one set of 4 programs and 2 play episodes
    assert [_rows(c) for c in mug[2:4]] == [[("reach_mug", 0), ("wipe_counter", 0), ("step_backwards", 0)],
                                            [("air_guitar", 0), ("play", 0), ("play", 1)]]
    # learned checkpoints run whole (a checkpoint's rows side by side, StackedPolicy), 4 // 2 a chunk,
    # two chunks of 2 for 3; the last repeats its checkpoint on the GPU
    assert [_rows(c) for c in mug[4:]] == [[("mug/a/0", 0), ("mug/a/0", 1), ("mug/a/1", 0), ("mug/a/1", 1)],
                                           [("mug/a/2", 0), ("mug/a/2", 1)]]
    assert _rows(mug[5], padded=True) == [("mug/a/2", 0), ("mug/a/2", 1)] * 2 and mug[5].width == 2
    assert [c.key for c in plan if c.task == "wipe"][-1] == key_b
    # every episode once, in the manifest's order within a rollout
    ids = [e for c in plan for e in c.episode_ids()]
    assert sorted(ids) == sorted(G.episode_id(t, s, i) for t, s, i in G._episodes(cfg, learned))
    assert len(set(ids)) == len(ids)
    assert all(len(c.rows(padded=True)) == len(plan[k - 1].rows(padded=True))
               for k, c in enumerate(plan) if k and c.task == plan[k - 1].task and c.key == plan[k - 1].key)
    # more episodes of a checkpoint than a batch: each checkpoint over chunks of its own
    long = G._plan(G.make_config("smoke", ["batch=4", "policy_episodes=5"]), learned[:1])
    assert [_rows(c) for c in long if c.key == key_a] == [[("mug/a/0", 0), ("mug/a/0", 1), ("mug/a/0", 2)],
                                                      [("mug/a/0", 3), ("mug/a/0", 4)]]
    assert _rows(long[-1], padded=True) == [("mug/a/0", 3), ("mug/a/0", 4), ("mug/a/0", 4)]
    # where whole checkpoints fill the scripted chunks' rows, a learned chunk is padded to them: one
    # batch size for every chunk of the plan
    one = G._plan(G.make_config("smoke", ["batch=4", "episodes=4", "policy_episodes=2"]), learned[:1])
    (ck,) = [c for c in one if c.key == key_a]
    assert ck.size == 2 and _rows(ck, padded=True) == [("mug/a/0", 0), ("mug/a/0", 1)] * 2
    assert {len(c.rows(padded=True)) for c in one} == {4}
    assert even_pieces(list(range(7)), 3) == ([[0, 1, 2], [3, 4, 5], [6]], 3)


class _Rollout(Exception):
    """Raised by the stand-in rollout below, with the inputs simulate_chunk gave it."""


def _signature(tree) -> tuple:
    return jax.tree_util.tree_structure(tree), tuple((np.shape(x), np.asarray(x).dtype) for x in jax.tree.leaves(tree))


@pytest.mark.filterwarnings("ignore:the mjx engine is meant for GPUs")
def test_scripted_program_and_play_chunks_run_through_one_compiled_rollout(monkeypatch):
    # per task one chunk of 3 scripted rows; the 8 programs and play alone would make two chunks of 4, with
    # the scripted ones they make chunks of at most 3, the last padded to 3: one batch shape
    cfg = G.make_config("smoke", ["engine=mjx", "episodes=3", "batch=4", "play=4", "tasks=mug,step_back"])
    plan = G._plan(cfg)
    assert [(c.key, len(c.rows(padded=False)), len(c.rows(padded=True))) for c in plan[:4]] == \
        [("scripted", 3, 3), ("program", 3, 3), ("program", 3, 3), ("program", 2, 3)]
    alone = G._plan(G.make_config("smoke", ["engine=mjx", "episodes=3", "batch=4", "programs=0", "tasks=mug,step_back"]))
    assert [c for c in plan if c.key == "scripted"] == alone  # their rows, batch and so their noise unchanged

    def rollout(env, policy, params, rng, renderers=(), progress=None, reset_keys=None, steps=None,
                compile_ahead=False):
        ahead.append(compile_ahead)
        raise _Rollout(env, policy, params, rng, renderers, reset_keys)

    ahead = []
    monkeypatch.setattr(G, "record_episodes", rollout)
    calls = []
    for chunk in plan:
        with pytest.raises(_Rollout) as got:
            G.simulate_chunk(cfg, chunk, "mjx")
        calls.append(got.value.args)
    # what record_episodes' compiled programs are keyed on: _scan_recorded's static arguments (the env's
    # core, the policy, the renderers) and the shapes of its data, which follow from the core (state,
    # observation), the policy and its parameters (carry) and the rng; reset keys feed the core's reset
    keys = {(env.core, policy, renderers, _signature(params), _signature(rng), _signature(reset_keys))
            for env, policy, params, rng, renderers, reset_keys in calls}
    assert len(keys) == 1, "scripted and program chunks would compile apart"
    assert all(ahead), "the data's own rollout, which no warm-up compiles, compiles beside the reset's programs"
    kinds = {bool(p) for _, _, params, *_ in calls for p in params["program"]}
    assert kinds == {True, False}  # both kinds went through it


def test_the_cpu_engine_pads_only_the_chunks_that_play_tables(monkeypatch):
    """On the cpu engine the program and play chunks run at the scripted chunks' batch (one compiled
    rollout, as on mjx): their rows play tables and draw nothing from the batch; the scripted chunks,
    and a chunk with weak grips (the script, its noise drawn per batch), run their own rows alone."""
    cfg = G.make_config("smoke", ["engine=cpu", "episodes=3", "batch=4", "play=4", "tasks=mug"])
    grips = G.make_config("smoke", ["engine=cpu", "episodes=3", "batch=4", "weak_grip=3", "tasks=mug"])

    def rollout(env, policy, params, rng, renderers=(), progress=None, reset_keys=None, steps=None,
                compile_ahead=False):
        raise _Rollout(env, policy, params, rng, renderers, reset_keys)

    monkeypatch.setattr(G, "record_episodes", rollout)
    shapes = {}
    for c, chunk in [(cfg, ch) for ch in G._plan(cfg)] + [(grips, ch) for ch in G._plan(grips)]:
        with pytest.raises(_Rollout) as got:
            G.simulate_chunk(c, chunk, "cpu")
        env, policy, params, _, _, reset_keys = got.value.args
        weak = any(src == G.WEAK_GRIP for src, _ in chunk.slots)
        shapes[chunk.key, weak, len(chunk.rows(padded=False))] = (env.batch_size, _signature(params), policy)
    assert shapes[("scripted", False, 3)] == shapes[("program", False, 2)]  # padded to the scripted batch
    assert shapes[("program", False, 3)] == shapes[("program", False, 2)]
    assert [b for (key, weak, n), (b, *_) in shapes.items() if weak] == [n for key, weak, n in shapes if weak]


@pytest.mark.filterwarnings("ignore:the mjx engine is meant for GPUs")
def test_weak_grip_episodes_start_where_the_scripted_ones_do_and_close_the_hand_part_way(monkeypatch):
    cfg = G.make_config("smoke", ["engine=mjx", "episodes=3", "batch=4", "weak_grip=3"])
    plan = G._plan(cfg)
    weak = [(c, i) for c in plan for s, i in c.rows(padded=False) if s == G.WEAK_GRIP]
    assert [i for _, i in weak] == [0, 1, 2] and {c.key for c, _ in weak} == {"program"}  # beside the programs
    assert [c for c in plan if c.key == "scripted"] == \
        G._plan(G.make_config("smoke", ["engine=mjx", "episodes=3", "batch=4"]))[:1]  # the scripted chunk unchanged
    for i in range(3):  # the scripted episode i's initial state and split, not a demonstration of skill 1
        meta, scripted = (G._episode_meta(cfg, "mug", s, i, False, 10, "mjx") for s in (G.WEAK_GRIP, 1.0))
        assert meta["seed"] == scripted["seed"] and meta["split"] == scripted["split"] != "programs"
        assert (meta["policy"], meta["policy_kind"], meta["skill"]) == ("weak_grip", "weak_grip", None)
        assert meta["episode_id"] == f"mug-weak-{i:06d}"
    factors = np.array([G.weak_grip_factor(i) for i in range(100)])
    lo, hi = G.WEAK_GRIP_RANGE
    assert factors.min() >= lo and factors.max() < hi and len(np.unique(factors)) == 100
    assert np.histogram(factors, bins=6, range=(lo, hi))[0].min() >= 15  # spread evenly: 100 / 6 each, about

    def rollout(env, policy, params, rng, renderers=(), progress=None, reset_keys=None, steps=None,
                compile_ahead=False):
        raise _Rollout(params)

    monkeypatch.setattr(G, "record_episodes", rollout)
    chunk = weak[0][0]
    with pytest.raises(_Rollout) as got:
        G.simulate_chunk(cfg, chunk, "mjx")
    params = got.value.args[0]
    for r, (s, i) in enumerate(chunk.rows(padded=True)):
        weak_row = s == G.WEAK_GRIP
        assert params["grip"][r] == pytest.approx(G.weak_grip_factor(i) if weak_row else 1.0)
        assert not weak_row or (params["skill"][r] == 1.0 and not params["program"][r])


def test_drive_episodes_back_away_for_times_spread_over_the_range_from_the_scripted_starts(monkeypatch):
    """drive=N: N episodes of every task, each from the scripted episode i's initial state and split,
    playing the ready pose while the base backs away at 0.3 m/s for drive_seconds(i)."""
    cfg = G.make_config("smoke", ["engine=cpu", "episodes=3", "batch=4", "drive=3", "tasks=mug,step_back"])
    plan = G._plan(cfg)
    drives = [(c, i) for c in plan for s, i in c.rows(padded=False) if s == G.DRIVE]
    for task in ("mug", "step_back"):
        assert [i for c, i in drives if c.task == task] == [0, 1, 2]
    assert {c.key for c, _ in drives} == {"program"}
    for task, i in itertools.product(("mug", "step_back"), range(3)):
        meta, scripted = (G._episode_meta(cfg, task, s, i, False, 10, "cpu") for s in (G.DRIVE, 1.0))
        assert meta["seed"] == scripted["seed"] and meta["split"] == scripted["split"] != "programs"
        assert (meta["policy"], meta["policy_kind"], meta["skill"], meta["episode_id"]) == (
            "drive", "drive", None, f"{task}-drive-{i:06d}")
    seconds = np.array([G.drive_seconds(i) for i in range(60)])
    lo, hi = G.DRIVE_SECONDS
    assert seconds.min() >= lo and seconds.max() < hi and np.histogram(seconds, bins=5, range=(lo, hi))[0].min() >= 10
    assert G.drive_seconds(0) == 0.0  # the first drive stands still
    table = G.drive_table(1.0, 40)  # 20 steps of 0.05 s
    speed = table[:, R.FORWARD_SPEED]
    np.testing.assert_allclose(speed, [-0.3] * 20 + [0.0] * 20)
    others = np.delete(table, R.FORWARD_SPEED, axis=1)
    np.testing.assert_array_equal(others, np.broadcast_to(others[0], others.shape))  # the pose held throughout

    def rollout(env, policy, params, rng, renderers=(), progress=None, reset_keys=None, steps=None,
                compile_ahead=False):
        raise _Rollout(env, params)

    monkeypatch.setattr(G, "record_episodes", rollout)
    chunk = drives[0][0]
    with pytest.raises(_Rollout) as got:
        G.simulate_chunk(cfg, chunk, "cpu")
    env, params = got.value.args
    for r, (s, i) in enumerate(chunk.rows(padded=True)):
        if s == G.DRIVE:
            assert params["program"][r]
            np.testing.assert_array_equal(params["table"][r][: env.episode_steps],
                                          G.drive_table(G.drive_seconds(i), env.episode_steps))


def test_drives_by_split_spread_each_splits_durations_over_the_range():
    """drive_by_split: the k-th drive of a split (in index order) lasts drive_seconds(k), so each split,
    training's first, holds the range's spread; without it drive i lasts drive_seconds(i)."""
    for by_split in (False, True):
        cfg = G.make_config("demo", [f"drive_by_split={str(by_split).lower()}"])
        splits = [G.split_of(cfg, G.initial_seed(cfg, "step_back", i)) for i in range(40)]
        for split in ("train", "val", "test"):
            mine = [i for i in range(40) if splits[i] == split]
            order = [G.drive_of_split(cfg, "step_back", i) for i in mine]
            assert order == (list(range(len(mine))) if by_split else mine)
    cfg = G.make_config("demo", ["drive_by_split=true"])
    train = [G.drive_seconds(G.drive_of_split(cfg, "step_back", i)) for i in range(16)
             if G.split_of(cfg, G.initial_seed(cfg, "step_back", i)) == "train"]
    assert max(train) > 5.0 and min(train) == 0.0  # a drive still backing away at step_back's 5 s end, one standing


def test_varied_drives_cover_the_scripted_distance_at_speeds_within_range(monkeypatch):
    """drive_varied: a share of the drives back away the same distance as a drive at 0.3 m/s for
    drive_seconds(i) would, through segments of other speeds and stops; the others are as before."""
    n = 100  # step_back's 5 s
    varied = [i for i in range(200) if G.drive_is_varied(i, 0.5)]
    assert 80 <= len(varied) <= 120 and not any(G.drive_is_varied(i, 0.0) for i in range(200))
    assert all(G.drive_is_varied(i, 1.0) for i in range(200))
    reached = 0
    for i in varied:
        seconds = G.drive_seconds(i)
        speed = G.drive_profile(i, seconds, n)
        assert speed.shape == (n,) and speed.min() >= 0.0 and speed.max() <= R.MAX_FORWARD_SPEED + 1e-6
        scripted = -G.drive_table(seconds, n)[:, R.FORWARD_SPEED]  # what the drive at 0.3 m/s covers
        distance, target = speed.sum() * G.CONTROL_DT, scripted.sum() * G.CONTROL_DT
        assert distance <= target + 1e-5
        if distance > target - 1e-5:
            reached += 1
            k = int(np.argmax(np.cumsum(speed, dtype=np.float64) * G.CONTROL_DT >= target - 1e-5))
            assert (speed[k + 1:] == 0.0).all()  # it stops for good once there
        else:  # only where every moving segment is at the top speed
            assert speed[speed > 0].min() >= R.MAX_FORWARD_SPEED - 1e-3
        np.testing.assert_array_equal(speed, G.drive_profile(i, seconds, n))  # a function of i
    assert reached >= 0.75 * len(varied)
    assert len({round(float(np.ptp(G.drive_profile(i, 3.0, n)[:40])), 3) for i in varied[:10]}) > 5  # not one speed
    table = G.drive_table(3.0, n, G.drive_profile(varied[1], 3.0, n))
    np.testing.assert_allclose(-table[:, R.FORWARD_SPEED], G.drive_profile(varied[1], 3.0, n))
    np.testing.assert_array_equal(np.delete(table, R.FORWARD_SPEED, axis=1), np.delete(G.drive_table(3.0, n), R.FORWARD_SPEED, axis=1))
    with pytest.raises(ValueError, match="drive_varied"):
        G.make_config("smoke", ["drive_varied=1.5"])

    # the chunk plays each varied drive's own profile, the others the scripted speed
    cfg = G.make_config("smoke", ["engine=cpu", "episodes=4", "batch=8", "drive=4", "drive_varied=0.5", "tasks=step_back"])

    def rollout(env, policy, params, rng, renderers=(), progress=None, reset_keys=None, steps=None,
                compile_ahead=False):
        raise _Rollout(env, params)

    monkeypatch.setattr(G, "record_episodes", rollout)
    chunk = next(c for c in G._plan(cfg) if any(s == G.DRIVE for s, _ in c.rows(padded=False)))
    with pytest.raises(_Rollout) as got:
        G.simulate_chunk(cfg, chunk, "cpu")
    env, params = got.value.args
    kinds = set()
    for r, (s, i) in enumerate(chunk.rows(padded=True)):
        if s == G.DRIVE:
            t = G.drive_seconds(i)
            want = G.drive_profile(i, t, env.episode_steps) if G.drive_is_varied(i, 0.5) else None
            kinds.add(want is None)
            np.testing.assert_array_equal(params["table"][r][: env.episode_steps], G.drive_table(t, env.episode_steps, want))
    assert kinds == {True, False}


def test_a_chunk_mixing_skills_writes_each_episode_once_and_a_rerun_rewrites_only_the_missing_one(smoke, tmp_path):
    # the smoke dataset's batch and cameras: its compiled rollout serves this one too
    cfg = G.make_config("smoke", ["skills=0.0,0.5", "episodes=1", "programs=0", "cache=false", "workers=1"])
    assert (cfg.batch, cfg.cameras) == (smoke[0].batch, smoke[0].cameras)
    plan = G._plan(cfg)
    assert [_rows(c) for c in plan] == [[(0.0, 0), (0.5, 0)]]
    out = tmp_path / "mixed"
    stats = G.generate(cfg, out, progress=False)
    steps = 120  # mug
    assert stats["throughput"]["episodes_generated"] == 2 == stats["episodes"]
    assert stats["throughput"]["frames_generated"] == 2 * (steps + 1) * len(cfg.cameras)
    rows = [json.loads(line) for line in (out / "manifest.jsonl").read_text().splitlines()]
    assert [(r["skill"], r["policy"]) for r in rows] == [(s, f"scripted@{s:.2f}") for s in (0.0, 0.5)]
    eps = {r["episode_id"]: read_episode(out / r["file"], cameras=()) for r in rows}
    for r in rows:
        ep = eps[r["episode_id"]]
        assert ep["meta"]["skill"] == r["skill"] and ep["meta"]["policy_kind"] == "scripted"
        assert ep["meta"]["success"] == r["success"] == bool(ep["success"][-1]) and ep["action"].shape == (steps, 20)
    # episode 0 of skills 0.0 and 0.5, side by side in one chunk: one initial state, each skill's own actions
    first, second = eps["mug-s000-000000"], eps["mug-s050-000000"]
    np.testing.assert_array_equal(first["qpos"][0], second["qpos"][0])
    assert not np.allclose(first["action"], second["action"])
    # a killed run: the chunk of the missing episode is simulated whole, only that episode written
    files = {p.name: p.read_bytes() for p in (out / "episodes").iterdir()}
    stamps = {p.name: p.stat().st_mtime_ns for p in (out / "episodes").iterdir()}
    victim = out / "episodes" / "mug-s050-000000.mcap"
    victim.unlink()
    again = G.generate(cfg, out, progress=False)["throughput"]
    assert again["episodes_generated"] == 1 and again["frames_generated"] == (steps + 1) * len(cfg.cameras)
    assert {p.name: p.read_bytes() for p in (out / "episodes").iterdir()} == files
    assert {p.name: p.stat().st_mtime_ns for p in (out / "episodes").iterdir() if p != victim} == \
        {k: v for k, v in stamps.items() if k != victim.name}


def test_drives_join_a_dataset_that_is_reused_whole(smoke, tmp_path):
    """A dataset generated with drive=1 from one without drives links every episode of the first and
    simulates the drive alone (drives only add episodes); the drive, standing still, fails."""
    _, data, _ = smoke
    out = tmp_path / "drives"
    stats = G.generate(G.make_config("smoke", ["drive=1"]), out, progress=False, reuse=data)
    assert stats["throughput"]["episodes_generated"] == 1
    for f in (data / "episodes").iterdir():
        assert (out / "episodes" / f.name).read_bytes() == f.read_bytes()
    (row,) = [r for r in map(json.loads, (out / "manifest.jsonl").read_text().splitlines()) if r["policy"] == "drive"]
    assert row["episode_id"] == "mug-drive-000000" and not row["success"]
