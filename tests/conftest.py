import fcntl
import json
import os
import shutil
import uuid
from pathlib import Path

os.environ.setdefault("MUJOCO_GL", "egl")

import jax  # noqa: E402
import mujoco  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402
from jax._src import cache_key as jax_cache_key  # noqa: E402

# Most of the suite's time is XLA compiling the same small functions (the cpu engine's rollout pieces, the
# policies) in each test process: one compilation cache per run lets the second pytest-xdist worker load
# what the first compiled. Each run has its own, removed at its end: nothing is reused between runs.
# The same settings go into the environment, so that the `wm.train` processes of the determinism test
# load the smoke train step the suite compiled instead of compiling it again.
JAX_CACHE = "/tmp/wmlab-test-jax-cache-{}"
if os.environ.get("PYTEST_XDIST_TESTRUNUID"):
    _cache = {"jax_compilation_cache_dir": JAX_CACHE.format(os.environ["PYTEST_XDIST_TESTRUNUID"]),
              "jax_persistent_cache_min_compile_time_secs": 0.0, "jax_persistent_cache_min_entry_size_bytes": 0}
    for _name, _value in _cache.items():
        jax.config.update(_name, _value)
        os.environ[_name.upper()] = str(_value)


@pytest.fixture(autouse=True)
def _jax_cache_key_as_found():
    """A command run in-process (run_cli) re-keys JAX's compilation cache for its process
    (sim_data.util.key_cache_by_device_kind): each test leaves the key as it found it."""
    own = jax_cache_key._hash_accelerator_config
    yield
    jax_cache_key._hash_accelerator_config = own


def pytest_configure(config):
    if not hasattr(config, "workerinput") and getattr(config.option, "testrunuid", "") is None:
        config.option.testrunuid = uuid.uuid4().hex  # the workers' run id, known here to remove the cache


def pytest_unconfigure(config):
    if not hasattr(config, "workerinput") and getattr(config.option, "testrunuid", None):
        shutil.rmtree(JAX_CACHE.format(config.option.testrunuid), ignore_errors=True)

from sim_data.policies.scripted import (
    ScriptOrProgramPolicy,
    pad_programs,
    script_or_program_params,
)
from sim_data.sim import scene as S  # noqa: E402
from sim_data.sim.robot import ACTION_DIM
from sim_data.sim.tasks import MAX_EPISODE_STEPS


@pytest.fixture(scope="package")
def model() -> mujoco.MjModel:
    return S.load_model()


@pytest.fixture(scope="package")
def idx(model) -> S.SceneIndex:
    return S.scene_index(model)


@pytest.fixture(scope="package")
def rng():
    return jax.random.PRNGKey(0)


def sample_state(task: str, key, heldout: bool = False):
    """Initial (qpos, mocap, TaskState) of one episode, batched with B=1."""
    from sim_data.sim.env import HomeEnv

    env = HomeEnv(task, 1, engine="cpu")
    st = env.reset(key[None] if key.ndim == 1 else key)
    return env, st


def scripted(model, skill, grip=None, table=None, program=None):
    """(policy, params) that run the scripted policy at `skill` (B,) as the data generator runs it: its
    ScriptOrProgramPolicy over tables of MAX_EPISODE_STEPS rows (every row scripted unless `program`
    (B,) says which rows play their `table` (B, T, 20) instead). Its scripted rows act exactly as
    ScriptedPolicy (tests/test_policies.py), and at the smoke dataset's batch of 2 on the cpu engine
    this is the dataset fixture's rollout program, so it loads from the run's shared compilation cache
    instead of compiling again (about 20 s a program on the 2-core machine)."""
    b = len(skill)
    table = np.zeros((b, 1, ACTION_DIM), np.float32) if table is None else table
    program = [False] * b if program is None else program
    params = pad_programs(script_or_program_params(skill, table, program, grip), MAX_EPISODE_STEPS)
    return ScriptOrProgramPolicy.create(MAX_EPISODE_STEPS, model), params


@pytest.fixture
def np_rng():
    return np.random.default_rng(0)


def build_once(tmp_path_factory, worker_id: str, name: str, build) -> Path:
    """A directory that `build(directory)` fills once per pytest run: under xdist the first worker
    to need it builds it under a file lock in the run's shared base temporary directory and the other
    workers wait for it and reuse it. Both workers run tests of one file side by side (make test's
    worksteal), so a test that changes what it holds works on a copy."""
    if worker_id == "master":
        out = tmp_path_factory.mktemp(name)
        build(out)
        return out
    root = tmp_path_factory.getbasetemp().parent  # shared by all of this run's workers
    out = root / name
    with open(root / f"{name}.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        if not (out / ".built").exists():
            shutil.rmtree(out, ignore_errors=True)
            out.mkdir()
            build(out)
            (out / ".built").touch()
    return out


@pytest.fixture(scope="package")
def smoke_dataset(tmp_path_factory, worker_id):
    """(config, directory, stats) of `make data CONFIG=smoke` (2 mug episodes, cpu, with its cache).
    Shared: tests copy it before changing anything."""
    from sim_data.dataset import generate as G

    cfg = G.make_config("smoke")
    out = build_once(tmp_path_factory, worker_id, "smoke", lambda d: G.generate(cfg, d, progress=False))
    return cfg, out, json.loads((out / "stats.json").read_text())


@pytest.fixture(scope="package")
def smoke_world_model(smoke_dataset, tmp_path_factory, worker_id):
    """Directory of `make train CONFIG=smoke` on the smoke dataset (best/, norm.json, eval.json)."""
    from wm.train import main

    _, data, _ = smoke_dataset

    def train(d):
        assert main(["--config", "smoke", "--data", str(data), "--out", str(d / "train")]) == 0

    return build_once(tmp_path_factory, worker_id, "wm", train) / "train"


# The evaluation fixture's settings (tests/test_experiments.py): batches of 3 policies x 2 states. Tests
# that evaluate other policies with them at that batch (3 checkpoints of one architecture, as the
# fixture's first batch) run the programs the fixture compiled instead of compiling their own.
SMOKE_EVAL = {"tasks": ("mug",), "episodes": 2, "batch": 6, "video_policies": 2, "video_episodes": 1,
              "decision_episodes": (5, 50), "readout": "judge", "keep_features": True, "replay": True}


@pytest.fixture(scope="package")
def smoke_zoo(smoke_dataset, tmp_path_factory, worker_id):
    """(directory, registry) of `make policies CONFIG=smoke` on the smoke dataset."""
    from sim_data.policies import zoo

    _, data, _ = smoke_dataset
    out = build_once(tmp_path_factory, worker_id,
                     "zoo", lambda d: zoo.train_zoo(zoo.make_config("smoke"), data, d / "policies", progress=False))
    return out / "policies", json.loads((out / "policies" / "policies.json").read_text())["policies"]
