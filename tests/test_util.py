"""sim_data.util: atomic JSON, the Wilson interval, output directories, users' mistakes, XLA's flags and
the parameter initialisers' compilation."""

import json
import os
import subprocess
import sys

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from sim_data import util
from sim_data.util import (
    CPU_INIT_OPTIONS,
    XLA_DEFAULT_FLAGS,
    jit_initialiser,
    make_output_dir,
    pad_with_last,
    run_cli,
    wilson_interval,
    write_json_atomic,
)


def test_a_users_mistake_is_one_line_and_exit_status_2(tmp_path, capsys):
    afile = tmp_path / "afile"
    afile.write_text("")

    def main():
        make_output_dir(afile / "tasks")
        return 0

    assert run_cli(main) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and str(afile) in err[0] and "is a file" in err[0]
    assert make_output_dir(tmp_path / "a" / "b").is_dir()


def test_json_is_written_whole_and_the_interval_is_scipys_wilson(tmp_path):
    write_json_atomic(tmp_path / "d" / "x.json", {"a": [1, 2]})
    assert json.loads((tmp_path / "d" / "x.json").read_text()) == {"a": [1, 2]}
    assert [p.name for p in (tmp_path / "d").iterdir()] == ["x.json"]
    assert wilson_interval(0, 0) == (0.0, 1.0)
    assert wilson_interval(80, 100) == pytest.approx((0.7112, 0.8666), abs=1e-4)


DEFAULTS = " ".join(f"{k}={v}" for k, v in XLA_DEFAULT_FLAGS.items())
CPU_FLAG, GPU_FLAG = XLA_DEFAULT_FLAGS


def test_every_command_runs_with_the_same_xla_flags_unless_the_user_set_them(monkeypatch):
    seen = []
    monkeypatch.delenv("XLA_FLAGS", raising=False)
    assert run_cli(lambda: seen.append(os.environ["XLA_FLAGS"]) or 0) == 0
    monkeypatch.setenv("XLA_FLAGS", "--xla_force_host_platform_device_count=2")
    run_cli(lambda: seen.append(os.environ["XLA_FLAGS"]) or 0)
    run_cli(lambda: seen.append(os.environ["XLA_FLAGS"]) or 0)  # not appended twice
    monkeypatch.setenv("XLA_FLAGS", f"{CPU_FLAG}=true {GPU_FLAG}=false")  # the user's choice stands
    run_cli(lambda: seen.append(os.environ["XLA_FLAGS"]) or 0)
    assert seen == [DEFAULTS, f"--xla_force_host_platform_device_count=2 {DEFAULTS}",
                    f"--xla_force_host_platform_device_count=2 {DEFAULTS}", f"{CPU_FLAG}=true {GPU_FLAG}=false"]
    assert XLA_DEFAULT_FLAGS == {"--xla_cpu_multi_thread_eigen": "false", "--xla_gpu_deterministic_ops": "true"}


def test_importing_the_project_sets_the_xla_flags_before_jax_starts():
    """pytest's own process and a user's script run JAX as the commands do (the in-process smoke training
    must equal the one a subprocess runs, bit for bit)."""
    env = {k: v for k, v in os.environ.items() if k != "XLA_FLAGS"}
    code = "import os, sim_data, jax; jax.numpy.zeros(1).block_until_ready(); print(os.environ['XLA_FLAGS'])"
    got = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True)
    assert got.stdout.strip() == DEFAULTS


class _Net(nn.Module):
    width: int

    @nn.compact
    def __call__(self, x):
        x = nn.Conv(self.width, (3, 3))(x)
        x = nn.LayerNorm()(nn.gelu(x))
        return nn.Dense(2)(x.reshape(x.shape[0], -1))


def test_an_initialiser_gives_its_plain_jits_parameters_nests_in_a_trace_and_takes_the_cpu_options(monkeypatch):
    def init(width, rng):
        return _Net(width).init(rng, jnp.zeros((1, 8, 8, 3)))["params"]

    fast = jit_initialiser(init, static_argnums=(0,))
    rng = jax.random.PRNGKey(5)
    got, ref = fast(4, rng), jax.jit(init, static_argnums=(0,))(4, rng)
    assert jax.tree_util.tree_structure(got) == jax.tree_util.tree_structure(ref)
    assert all(np.array_equal(a, b) for a, b in zip(jax.tree_util.tree_leaves(got), jax.tree_util.tree_leaves(ref)))
    assert not np.array_equal(got["Dense_0"]["kernel"], fast(4, jax.random.PRNGKey(6))["Dense_0"]["kernel"])
    assert fast.__name__ == "init" and jax.default_backend() == "cpu"
    # inside a trace it is part of the enclosing program
    shapes = jax.eval_shape(lambda: fast(4, jax.random.PRNGKey(5)))
    assert jax.tree_util.tree_map(lambda a: a.shape, shapes) == jax.tree_util.tree_map(lambda a: a.shape, ref)
    inner = jax.jit(lambda r: fast(4, r))(rng)
    assert all(np.array_equal(a, b) for a, b in zip(jax.tree_util.tree_leaves(inner), jax.tree_util.tree_leaves(ref)))
    # the options reach XLA on this CPU: one it does not know is refused
    monkeypatch.setattr(util, "CPU_INIT_OPTIONS", {**CPU_INIT_OPTIONS, "no_such_option": 1})
    with pytest.raises(Exception, match="no_such_option"):
        util.jit_initialiser(init, static_argnums=(0,))(4, rng)


def test_on_another_backend_an_initialiser_runs_on_the_host_cpu_and_places_its_parameters(monkeypatch):
    def init(width, rng):
        return _Net(width).init(rng, jnp.zeros((1, 8, 8, 3)))["params"]

    rng = jax.random.PRNGKey(5)
    ref = jax.jit(init, static_argnums=(0,))(4, rng)
    calls = []
    real_jit = jax.jit

    def recording_jit(fun, **kw):  # which of the two programs runs, and with which options
        compiled = real_jit(fun, **kw)

        def run(*args):
            calls.append(kw.get("compiler_options"))
            return compiled(*args)
        return run

    monkeypatch.setattr(util.jax, "jit", recording_jit)
    fast = util.jit_initialiser(init, static_argnums=(0,))
    monkeypatch.setattr(util.jax, "default_backend", lambda: "gpu")
    got = fast(4, rng)
    assert calls == [CPU_INIT_OPTIONS]  # the host's program, with the CPU options
    leaves = jax.tree_util.tree_leaves(got)
    assert all(np.array_equal(a, b) for a, b in zip(leaves, jax.tree_util.tree_leaves(ref)))
    assert all(x.devices() == {jax.devices()[0]} for x in leaves)
    # a JAX started without its CPU platform compiles for the default backend
    monkeypatch.setattr(util, "host_cpu", lambda: None)
    calls.clear()
    fast(4, rng)
    assert calls == [None]


def test_an_initialiser_on_another_backend_places_its_parameters_on_the_chosen_default_device():
    """On two host devices with the second chosen as the default, parameters initialised on the host's
    CPU as for a GPU land on the chosen device, not on the first."""
    code = """
import jax, jax.numpy as jnp, flax.linen as nn
from sim_data import util
jax.config.update("jax_default_device", jax.devices()[1])
util.jax.default_backend = lambda: "gpu"
init = util.jit_initialiser(lambda rng: nn.Dense(3).init(rng, jnp.zeros((1, 2)))["params"])
print(sorted({d.id for x in jax.tree_util.tree_leaves(init(jax.random.PRNGKey(0))) for d in x.devices()}))
"""
    env = {**os.environ, "XLA_FLAGS": "--xla_force_host_platform_device_count=2"}
    got = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True)
    assert got.stdout.strip() == "[1]"


def test_a_batch_is_padded_by_repeating_its_last_item_and_a_full_one_is_left_alone():
    assert pad_with_last([3, 1, 4], 5) == [3, 1, 4, 4, 4]
    assert pad_with_last([(0, [1, 2])], 2) == [(0, [1, 2]), (0, [1, 2])]
    part = [7, 8]
    assert pad_with_last(part, 2) == [7, 8] and part == [7, 8]  # a copy: the caller's list is untouched
