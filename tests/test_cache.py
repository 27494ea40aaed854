"""The training cache (built from MCAP alone, resumable, corrupt files named or skipped and listed),
the window loader (contents, epochs, resumable state) and replay."""

import os
import shutil

import numpy as np
import pytest

from sim_data.dataset import cache as C
from sim_data.dataset.episodes import CorruptEpisode, read_episode
from sim_data.dataset.replay import replay_files, summarize
from sim_data.sim.render import grip_pixels
from sim_data.sim.scene import load_model, scene_index, scene_state


@pytest.fixture(scope="module")
def two_shards(smoke_dataset, tmp_path_factory):
    """The smoke dataset's 6 episodes with a cache of 3 episodes per shard (the loader crosses shards)."""
    _, out, _ = smoke_dataset
    copy = tmp_path_factory.mktemp("two_shards")
    shutil.copytree(out / "episodes", copy / "episodes")
    C.build_cache(copy, shard_episodes=3, workers=2, progress=False)
    return copy


def test_cache_rows_equal_the_mcap_files(two_shards):
    cache = C.TrainingCache(two_shards)
    assert len(cache.index["shards"]) == 2 and cache.cameras == ["head_cam", "ext_cam"]
    for i, rec in enumerate(cache.episodes):
        ep = read_episode(two_shards / rec["file"])
        row = cache.episode(i)
        for cam in cache.cameras:
            np.testing.assert_array_equal(row["frames"][cam], ep["frames"][cam])
        np.testing.assert_array_equal(row["proprio"], ep["proprio"])
        np.testing.assert_array_equal(row["action"][:-1], ep["action"])
        assert not row["action"][-1].any()
        np.testing.assert_array_equal(row["success"], ep["success"])
        np.testing.assert_array_equal(row["progress"], ep["progress"])
        np.testing.assert_array_equal(row["scene"], scene_state(ep["qpos"], ep["mocap_pos"], scene_index(load_model())))
        np.testing.assert_array_equal(row["grip_px"], grip_pixels(load_model(), ep["qpos"], ep["mocap_pos"]))
        assert rec["success"] == ep["meta"]["success"] and rec["length"] == ep["proprio"].shape[0]


def test_killed_build_resumes_to_the_same_bytes(two_shards, tmp_path):
    copy = tmp_path / "copy"
    shutil.copytree(two_shards, copy)
    shutil.rmtree(copy / "cache" / "shard-00001")
    (copy / "cache" / "index.json").unlink()
    (copy / "cache" / "shard-00001.tmp").mkdir()  # a shard being written when the build died
    (copy / "cache" / "shard-00001.tmp" / "proprio.npy").write_bytes(b"half")
    C.build_cache(copy, shard_episodes=3, workers=1, progress=False)
    for f in sorted((two_shards / "cache").rglob("*")):
        if f.is_file():
            assert (copy / f.relative_to(two_shards)).read_bytes() == f.read_bytes(), f
    assert not (copy / "cache" / "shard-00001.tmp").exists()


def test_an_episode_file_written_again_under_its_name_rebuilds_its_shard_alone(two_shards, tmp_path):
    """A rerun that finds an episode file changed since its shard was built (simulated again with
    another engine or policy, a corrupt file replaced) builds that shard again; the others stay."""
    copy = tmp_path / "copy"
    shutil.copytree(two_shards, copy)
    files = sorted((copy / "episodes").glob("*.mcap"))
    other = read_episode(files[4])
    tmp = files[1].with_suffix(".new")
    shutil.copyfile(files[4], tmp)  # another episode's bytes under the second file's name
    os.replace(tmp, files[1])
    kept = (copy / "cache" / "shard-00001" / "proprio.npy").stat().st_ino
    C.build_cache(copy, shard_episodes=3, workers=1, progress=False)
    cache = C.TrainingCache(copy)
    rec = cache.episodes[1]
    assert rec["file"] == f"episodes/{files[1].name}" and rec["episode_id"] == other["meta"]["episode_id"]
    np.testing.assert_array_equal(cache.episode(1)["proprio"], other["proprio"])
    assert (copy / "cache" / "shard-00001" / "proprio.npy").stat().st_ino == kept


def test_corrupt_file_stops_the_build_or_is_skipped_and_listed(two_shards, tmp_path, capsys):
    copy = tmp_path / "copy"
    shutil.copytree(two_shards / "episodes", copy / "episodes")
    victim = sorted((copy / "episodes").iterdir())[1]
    data = bytearray(victim.read_bytes())
    data[len(data) // 3: len(data) // 3 + 64] = bytes(64)  # damage inside a compressed chunk
    victim.write_bytes(bytes(data))
    n = len(list((copy / "episodes").iterdir()))
    with pytest.raises(CorruptEpisode, match=victim.name):
        C.build_cache(copy, workers=1, progress=False)
    assert not (copy / "cache" / "index.json").exists()
    assert C.main(["rebuild", str(copy), "--skip-corrupt", "--workers", "1"]) == 0
    index = C.TrainingCache(copy).index
    assert [s["file"] for s in index["skipped"]] == [f"episodes/{victim.name}"]
    assert len(index["episodes"]) == n - 1 and victim.name in capsys.readouterr().err
    victim.write_bytes(bytes(data[: len(data) // 2]))  # truncated
    assert C.main(["rebuild", str(copy)]) == 1
    assert victim.name in capsys.readouterr().err


def test_loader_windows_epochs_and_resume(two_shards):
    cache = C.TrainingCache(two_shards)
    window, batch = 16, 8
    loader = C.WindowLoader(cache, window, batch, split=None, seed=3, cameras=["head_cam", "ext_cam"],
                            first_frames=True)
    lengths = [e["length"] for e in cache.episodes]
    assert loader.windows == sum(n - window + 1 for n in lengths)
    first = [next(loader) for _ in range(3)]
    b = first[0]
    assert b["frames"]["head_cam"].shape == (batch, window, cache.index["size"], cache.index["size"], 3)
    assert b["proprio"].shape == (batch, window, 37) and b["action"].shape == (batch, window, 20)
    assert b["frames"]["head_cam"].dtype == np.uint8 and b["outcome"].dtype == bool
    for j in range(batch):  # each window is a slice of its episode
        ep = cache.episode(int(b["episode"][j]))
        s = int(b["start"][j])
        np.testing.assert_array_equal(b["frames"]["ext_cam"][j], ep["frames"]["ext_cam"][s:s + window])
        np.testing.assert_array_equal(b["action"][j], ep["action"][s:s + window])
        for cam in ("head_cam", "ext_cam"):  # and the episode's first frame beside it (the anchor)
            np.testing.assert_array_equal(b["first_frames"][cam][j], ep["frames"][cam][0])
        assert b["outcome"][j] == ep["record"]["success"] and cache.tasks[b["task"][j]] == ep["record"]["task"]
    state = loader.state()
    expected = next(loader)
    loader.close()
    again = C.WindowLoader(cache, window, batch, split=None, seed=3, cameras=["head_cam", "ext_cam"])
    again.restore(state)
    got = next(again)
    assert "first_frames" not in got  # only for a loader asked for them
    np.testing.assert_array_equal(got["frames"]["head_cam"], expected["frames"]["head_cam"])
    np.testing.assert_array_equal(got["start"], expected["start"])
    # an epoch visits every window at most once
    seen = {(int(e), int(s)) for k in range(loader.batches_per_epoch)
            for e, s in zip(*(lambda x: (x["episode"], x["start"]))(loader.batch_at(0, k)))}
    assert len(seen) == loader.batches_per_epoch * batch
    with pytest.raises(ValueError, match="another loader"):
        C.WindowLoader(cache, window + 1, batch, split=None, seed=3).restore(state)
    with pytest.raises(ValueError, match="cameras"):
        C.WindowLoader(cache, window, batch, split=None, cameras=["top_cam"])


def test_first_windows_count_each_episode_s_start_that_many_more_times(two_shards):
    cache = C.TrainingCache(two_shards)
    window, batch, extra = 16, 4, 3
    plain = C.WindowLoader(cache, window, batch, split=None, seed=3)
    loader = C.WindowLoader(cache, window, batch, split=None, seed=3, first_windows=extra)
    per_episode = {i: r["length"] - window + 1 for i, r in enumerate(cache.episodes)}
    assert loader.windows == plain.windows + extra * len(per_episode)
    every = loader.gather(np.arange(loader.windows))  # an epoch's windows, all of them
    drawn = {}
    for e, s in zip(every["episode"], every["start"]):
        drawn[(int(e), int(s))] = drawn.get((int(e), int(s)), 0) + 1
    assert drawn == {(i, s): 1 + extra * (s == 0) for i, n in per_episode.items() for s in range(n)}
    ep = cache.episode(0)  # an extra window is the episode's first steps, as the plain one
    first = loader.gather(np.array([plain.windows]))
    assert int(first["episode"][0]) == 0 and int(first["start"][0]) == 0
    np.testing.assert_array_equal(first["frames"]["head_cam"][0], ep["frames"]["head_cam"][:window])
    np.testing.assert_array_equal(first["action"][0], ep["action"][:window])
    # without them every start once, in the order the seed draws: window id k is the k-th start of the
    # episodes in turn, the epoch's order a permutation of the ids by (seed, epoch)
    assert plain.windows == sum(per_episode.values())
    ids = [(i, s) for i, n in per_episode.items() for s in range(n)]
    order = np.random.default_rng([3, 0]).permutation(plain.windows)[batch:2 * batch]
    got = plain.batch_at(0, 1)
    assert list(zip(got["episode"].tolist(), got["start"].tolist())) == [ids[k] for k in order]
    with pytest.raises(ValueError, match="first_windows"):
        C.WindowLoader(cache, window, batch, split=None, first_windows=-1)


def test_a_repeated_episode_counts_its_windows_that_many_times_an_epoch(two_shards):
    from wm.config import make_config
    from wm.train import failed_attempts_repeated

    cache = C.TrainingCache(two_shards)
    window, batch = 16, 4
    recs = cache.episodes
    times = {i: 1 + i % 3 for i in range(len(recs))}  # 1, 2, 3, 1, ...: one episode left at once
    loader = C.WindowLoader(cache, window, batch, split=None, seed=3,
                            repeat=lambda rec: times[recs.index(rec)])
    per_episode = {i: r["length"] - window + 1 for i, r in enumerate(recs)}
    assert loader.windows == sum(times[i] * n for i, n in per_episode.items())
    assert sorted(loader.distinct.tolist()) == list(range(len(recs)))
    drawn = {}
    every = loader.gather(np.arange(loader.windows))  # an epoch's windows, all of them
    for e, s in zip(every["episode"], every["start"]):
        drawn[(int(e), int(s))] = drawn.get((int(e), int(s)), 0) + 1
    assert drawn == {(i, s): times[i] for i, n in per_episode.items() for s in range(n)}
    with pytest.raises(ValueError, match="a count >= 0"):
        C.WindowLoader(cache, window, batch, split=None, repeat=lambda rec: 1.5)
    # the training run's rule: failed task attempts `times`, the rest (successes, play, programs) once
    rule = failed_attempts_repeated(4)
    assert rule({"policy_kind": "scripted", "success": False}) == 4
    assert rule({"policy_kind": "weak_grip", "success": False}) == 4
    assert rule({"policy_kind": "learned", "success": True}) == 1
    assert rule({"policy_kind": "play", "success": False}) == rule({"policy_kind": "program", "success": False}) == 1
    with pytest.raises(ValueError, match="fail_repeat"):
        make_config("smoke", ["fail_repeat=0"])


def test_replay_reproduces_recorded_episodes(smoke_dataset):
    _, out, _ = smoke_dataset
    files = sorted((out / "episodes").glob("*.mcap"))
    results = replay_files(files)
    s = summarize(results)
    assert s["episodes"] == len(files) and s["outcome_agreement"] == 1.0 and s["mean_flags_agree"] == 1.0
    assert s["max_initial_state_error"] == 0.0  # the cpu engine replays bit for bit


def test_a_cache_built_beside_a_reused_dataset_copies_its_rows_byte_for_byte(two_shards, tmp_path):
    """A dataset that links episodes of another (generate --reuse) copies their rows from the other's
    built cache: the same shards, byte for byte, as decoding its files; a file that is not the same
    file (a copy, not a link) is decoded."""
    files = sorted((two_shards / "episodes").glob("*.mcap"))
    mixed = tmp_path / "mixed"
    (mixed / "episodes").mkdir(parents=True)
    for f in files[:-1]:
        os.link(f, mixed / "episodes" / f.name)
    shutil.copyfile(files[-1], mixed / "episodes" / files[-1].name)  # the same bytes, another file
    assert set(C.reused_rows(two_shards, sorted((mixed / "episodes").glob("*.mcap")), ["head_cam"])) == \
        {f.name for f in files[:-1]}
    C.build_cache(mixed, shard_episodes=3, workers=1, progress=False, reuse=two_shards)
    got = sorted(p.relative_to(mixed / "cache") for p in (mixed / "cache").rglob("*") if p.is_file())
    assert got == sorted(p.relative_to(two_shards / "cache") for p in (two_shards / "cache").rglob("*") if p.is_file())
    for rel in got:  # the decoded file's rows too: the shards the reused dataset decoded
        if rel.name == C.SOURCES:
            continue  # the files' stamps: the copy is another file
        assert (mixed / "cache" / rel).read_bytes() == (two_shards / "cache" / rel).read_bytes(), rel
    # the rows come from the reused cache: altered there, they are altered here (every file linked)
    altered = tmp_path / "altered"
    shutil.copytree(two_shards / "cache", altered / "cache")
    (altered / "episodes").mkdir()
    for f in files:
        os.link(f, altered / "episodes" / f.name)
    proprio = np.load(altered / "cache" / "shard-00000" / "proprio.npy")
    np.save(altered / "cache" / "shard-00000" / "proprio.npy", proprio + 1)
    (mixed / "episodes" / files[-1].name).unlink()
    os.link(files[-1], mixed / "episodes" / files[-1].name)
    C.rebuild_cache(mixed, shard_episodes=3, workers=1, progress=False, reuse=altered)
    np.testing.assert_array_equal(np.load(mixed / "cache" / "shard-00000" / "proprio.npy"), proprio + 1)
    assert C.reused_rows(tmp_path / "none", files, ["head_cam"]) == {}  # no built cache there
