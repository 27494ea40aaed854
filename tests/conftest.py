import os

os.environ.setdefault("MUJOCO_GL", "egl")

import jax  # noqa: E402
import mujoco  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402

from sim_data import scene as S  # noqa: E402


@pytest.fixture(scope="session")
def model() -> mujoco.MjModel:
    return S.load_model()


@pytest.fixture(scope="session")
def idx(model) -> S.SceneIndex:
    return S.scene_index(model)


@pytest.fixture(scope="session")
def rng():
    return jax.random.PRNGKey(0)


def sample_state(task: str, key, heldout: bool = False):
    """Initial (qpos, mocap, TaskState) of one episode, batched with B=1."""
    from sim_data.env import HomeEnv

    env = HomeEnv(task, 1, engine="cpu")
    st = env.reset(key[None] if key.ndim == 1 else key)
    return env, st


@pytest.fixture
def np_rng():
    return np.random.default_rng(0)


@pytest.fixture(scope="session")
def smoke_dataset(tmp_path_factory):
    """(config, directory, stats) of `make data CONFIG=smoke` (2 mug episodes, cpu, with its cache).
    Shared: tests copy it before changing anything."""
    from sim_data import generate as G

    out = tmp_path_factory.mktemp("smoke")
    cfg = G.make_config("smoke")
    return cfg, out, G.generate(cfg, out, progress=False)


@pytest.fixture(scope="session")
def smoke_world_model(smoke_dataset, tmp_path_factory):
    """Directory of `make train CONFIG=smoke` on the smoke dataset (best/, norm.json, eval.json)."""
    from wm.train import main

    _, data, _ = smoke_dataset
    out = tmp_path_factory.mktemp("wm") / "train"
    assert main(["--config", "smoke", "--data", str(data), "--out", str(out)]) == 0
    return out


@pytest.fixture(scope="session")
def smoke_zoo(smoke_dataset, tmp_path_factory):
    """(directory, registry) of `make policies CONFIG=smoke` on the smoke dataset."""
    from sim_data import zoo

    _, data, _ = smoke_dataset
    out = tmp_path_factory.mktemp("zoo") / "policies"
    return out, zoo.train_zoo(zoo.make_config("smoke"), data, out, progress=False)
