"""sim_data.bench.determinism: episodes compared bit for bit, and the command's mistakes refused."""

import numpy as np
import pytest

from sim_data.bench import determinism as D
from sim_data.util import with_xla_flags


def episodes(rng, b=4, t=6):
    return {"outcome": rng.random(b) < 0.5, "proprio": rng.normal(size=(b, t + 1, 3)).astype(np.float32),
            "action": rng.normal(size=(b, t, 2)).astype(np.float32)}


def test_identical_runs_agree_nan_included(np_rng):
    a = episodes(np_rng)
    a["proprio"][1, 3:] = np.nan  # an episode that blew up the same way in both runs
    b = {k: v.copy() for k, v in a.items()}
    assert D.compare([a, b, b]) == {"identical": True, "episodes": 4, "differing_episodes": 0,
                                    "differing_outcomes": 0, "first_divergent_step": None,
                                    "max_abs_proprio_diff": 0.0}


def test_differences_are_counted_per_episode_from_their_first_step(np_rng):
    a = episodes(np_rng)
    b = {k: v.copy() for k, v in a.items()}
    c = {k: v.copy() for k, v in a.items()}
    b["proprio"][2, 5:, 1] += 1e-6  # one last-bit drift from step 5 ...
    b["outcome"][2] = ~b["outcome"][2]  # ... that flips the episode's outcome
    c["proprio"][0, 4, 0] += 0.25  # another process drifts earlier, in another episode
    c["action"][3, 0, 1] = 7.0  # an action alone differs
    r = D.compare([a, b, c])
    assert not r["identical"]
    assert (r["differing_episodes"], r["differing_outcomes"], r["first_divergent_step"]) == (3, 1, 4)
    assert r["max_abs_proprio_diff"] == pytest.approx(0.25)
    assert D.compare([a, b])["first_divergent_step"] == 5


def test_the_commands_mistakes_are_refused(tmp_path):
    with pytest.raises(ValueError, match="--processes must be >= 2"):
        D.main(["--out", str(tmp_path / "d.json"), "--processes", "1"])
    with pytest.raises(ValueError, match="--out is required"):
        D.main([])
    with pytest.raises(FileNotFoundError, match="is missing: train a zoo first"):
        D.main(["--out", str(tmp_path / "d.json"), "--policies", str(tmp_path / "nozoo")])


def test_a_settings_flags_replace_the_projects_flags_of_the_same_name():
    base = "--xla_cpu_multi_thread_eigen=false --xla_gpu_deterministic_ops=true"
    assert with_xla_flags(base, "--xla_gpu_deterministic_ops=false", override=True) == \
        "--xla_cpu_multi_thread_eigen=false --xla_gpu_deterministic_ops=false"
    assert with_xla_flags(base, "", override=True) == base
    assert with_xla_flags("", "--a=1 --b", override=True) == "--a=1 --b"
