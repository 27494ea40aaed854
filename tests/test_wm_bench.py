"""wm.bench: the FLOP count (XLA's cost analysis of the lowered train step, which grows with the batch)
and the scaling table over devices."""

import flax.linen as nn
import jax
import jax.numpy as jnp
import pytest

from wm import bench
from wm.bench import flops_by_module, imagine_step_flops, matmul_flops_by_shape, step_flops
from wm.config import make_config


@pytest.mark.slow
def test_step_flops_count_the_whole_batch():
    one, two = step_flops("smoke", ["batch=2"]), step_flops("smoke", ["batch=4"])
    assert one > 1e8
    # the per-sample work doubles; the optimiser's update over the parameters does not
    assert 1.8 < two / one < 2.0


@pytest.mark.slow
def test_the_read_loss_step_is_benchmarked_with_stand_in_probes():
    plain, read = step_flops("smoke", ["batch=2"]), step_flops("smoke", ["batch=2", "w_read=0.2", "read_probes=2"])
    assert read > plain  # the probes read every 4th predicted and true frame of each pass


def test_matmul_flops_by_shape_counts_convolutions_and_dots_by_hand():
    def f(x, k, a, b):
        y = jax.lax.conv_general_dilated(x, k, (2, 2), "SAME", dimension_numbers=("NHWC", "HWIO", "NHWC"))
        return y.sum() + (a @ b).sum()

    args = (jnp.zeros((2, 8, 8, 3)), jnp.zeros((3, 3, 3, 5)), jnp.zeros((4, 6)), jnp.zeros((6, 7)))
    by = matmul_flops_by_shape(jax.jit(f).lower(*args).as_text(dialect="hlo"))
    assert sorted(by.values()) == [2.0 * 4 * 7 * 6, 2.0 * (2 * 4 * 4 * 5) * (3 * 3 * 3)]
    # the strided convolution's input gradient (a convolution of the dilated output gradient) and its
    # weight gradient each cost what the forward does
    grads = jax.jit(jax.grad(f, argnums=(0, 1))).lower(*args).as_text(dialect="hlo")
    convs = [v for k, v in matmul_flops_by_shape(grads).items() if k[0] == "convolution"]
    assert convs == [2.0 * (2 * 4 * 4 * 5) * 27] * 2


class _Outer(nn.Module):
    @nn.compact
    def __call__(self, x, y):
        return nn.Dense(5)(x).sum() + nn.Conv(4, (3, 3), strides=2)(y).sum() + (x @ x.T).sum()


def test_flops_by_module_sums_each_flax_scope_by_hand():
    args = (jnp.zeros((4, 3)), jnp.zeros((2, 8, 8, 3)))
    params = _Outer().init(jax.random.PRNGKey(0), *args)
    text = jax.jit(_Outer().apply).lower(params, *args).as_text(debug_info=True)
    assert flops_by_module(text) == {"_Outer/Dense_0": 2.0 * 4 * 5 * 3,
                                     "_Outer/Conv_0": 2.0 * (2 * 4 * 4 * 4) * (3 * 3 * 3),
                                     "_Outer": 2.0 * 4 * 4 * 3}  # the product outside any submodule
    assert flops_by_module(text, depth=1) == {"_Outer": 2.0 * 4 * 5 * 3 + 2.0 * 2 * 4 * 4 * 4 * 27 + 2.0 * 4 * 4 * 3}
    plain = jax.jit(lambda a: (a @ a.T).sum()).lower(args[0]).as_text(debug_info=True)
    assert flops_by_module(plain) == {"(outside any module)": 2.0 * 4 * 4 * 3}


@jax.jit
def _helper(a, b):
    return a @ b


class _Calls(nn.Module):
    @nn.compact
    def __call__(self, x, y):
        twice = _helper(x, x.T).sum() + _helper(x, x.T).sum()  # one outlined function, two call sites
        outer = jnp.einsum("i,j->ij", x[0], x[1]).sum()  # a dot that contracts nothing
        up = nn.ConvTranspose(4, (3, 3), strides=(2, 2))(y).sum()  # its input dilated by zeros
        either = jax.lax.cond(x.sum() > 0, lambda a: (a @ a.T).sum(), lambda a: 2 * (a @ a.T).sum(), x)
        return twice + outer + up + either


def test_flops_by_module_counts_each_call_an_outer_product_a_transposed_convolution_and_both_branches():
    args = (jnp.zeros((4, 3)), jnp.zeros((2, 8, 8, 3)))
    params = _Calls().init(jax.random.PRNGKey(0), *args)
    text = jax.jit(_Calls().apply).lower(params, *args).as_text(debug_info=True)
    # each of the 2 x 8 x 8 inputs' 3 channels reaches 3 x 3 outputs' 4 features: 13,824 products
    assert flops_by_module(text) == {"_Calls": 2 * (2.0 * 4 * 4 * 3) + 2.0 * 3 * 3 + 2 * (2.0 * 4 * 4 * 3),
                                     "_Calls/ConvTranspose_0": 2.0 * (2 * 8 * 8 * 3) * (3 * 3) * 4}


def test_imagine_step_flops_count_each_euler_step_of_the_frame_generator():
    one, two = (imagine_step_flops(make_config("smoke", [f"model.refine={n}"]), batch=2) for n in (1, 2))
    gen = "WorldModel.sample_frame/WorldModel.denoise"
    assert one[gen] > 0 and two[gen] == 2 * one[gen]
    assert {k: v for k, v in one.items() if k != gen} == {k: v for k, v in two.items() if k != gen}
    assert gen not in imagine_step_flops(make_config("smoke", ["model.refine=0"]), batch=2)


def test_kernel_profile_sums_device_kernels_by_kind_per_step():
    import pytest

    from wm.bench import kernel_profile

    meta = [{"ph": "M", "name": "process_name", "pid": 1, "args": {"name": "/device:GPU:0"}},
            {"ph": "M", "name": "process_name", "pid": 7, "args": {"name": "/host:CPU"}}]
    kernels = [("sm90_xmma_fprop_implicit_gemm_bf16", 600.0), ("nvjet_sm90_tst_128x128", 200.0),
               ("loop_add_fusion_12", 100.0), ("loop_add_fusion_3", 50.0), ("loop_convert_fusion_1", 50.0)]
    events = meta + [{"ph": "X", "pid": 1, "tid": 1, "name": n, "dur": d} for n, d in kernels]
    events.append({"ph": "X", "pid": 7, "tid": 1, "name": "PjitFunction(jit(train_step))", "dur": 5000.0})  # host
    r = kernel_profile({"traceEvents": events}, steps=2)
    assert r["step_ms"] == pytest.approx(0.5)  # 1000 us of device kernels over 2 steps
    assert r["matrix_share"] == pytest.approx(0.8)
    assert r["by_kind"] == pytest.approx({"matrix kernels": 0.4, "loop_add_fusion": 0.075, "loop_convert_fusion": 0.025})
    assert r["top"][0] == {"name": "sm90_xmma_fprop_implicit_gemm_bf16", "ms": 0.3, "calls": 0.5}
    with pytest.raises(ValueError, match="GPU"):
        kernel_profile({"traceEvents": meta[1:] + events[-1:]}, steps=1)


@pytest.mark.slow
def test_train_rate_traces_the_step_and_refuses_a_profile_without_a_gpu():
    import jax
    import pytest

    from wm.bench import train_rate
    from wm.config import make_config

    if jax.devices()[0].platform != "cpu":
        pytest.skip("on a GPU the profile has kernels to sum")
    # the smoke preset cut to the cheapest step to compile (about half the smoke step's compile time):
    # what is tested is the timing and the profile around any step, not the model
    tiny = make_config("smoke", ["model.tokenizer=patch", "model.channels=8", "model.compose=false",
                                 "model.warp=false", "model.context=2", "eval_context=1", "window=2",
                                 "rollout_passes=0"])
    with pytest.raises(ValueError, match="no device kernels"):  # the trace was written and read back
        train_rate(tiny, steps=1, profile=1)


@pytest.fixture
def four_fake_devices(monkeypatch):
    """scaling on a host of 4 devices whose per-device rate falls 5% a device (fsdp 10% lower); returns
    the (devices, sharding, batch) of every train_rate call."""
    timed = []

    def fake_rate(cfg, steps, mesh):
        n = len(mesh)
        timed.append((n, cfg.param_sharding, cfg.batch))
        per_device = 100.0 * (1.0 - 0.05 * (n - 1)) * (0.9 if cfg.param_sharding == "fsdp" else 1.0)
        return {"step_s": 1.0, "frames_per_s": per_device * n, "compile_s": 0.0}

    monkeypatch.setattr(bench, "train_rate", fake_rate)
    monkeypatch.setattr(bench, "make_mesh", lambda devices: list(devices))
    monkeypatch.setattr(jax, "device_count", lambda: 4)
    monkeypatch.setattr(jax, "devices", lambda: list(range(4)))
    return timed


def test_scaling_measures_one_device_once_and_rates_every_row_against_it(four_fake_devices):
    timed = four_fake_devices
    rows = bench.scaling("smoke", per_device_batch=3, counts=(1, 2, 4, 8))
    # 8 devices are more than the host has; fsdp on one device is replicated's program, timed once
    assert timed == [(1, "replicated", 3), (2, "replicated", 6), (4, "replicated", 12), (2, "fsdp", 6), (4, "fsdp", 12)]
    eff = {(r["devices"], r["param_sharding"]): r["efficiency"] for r in rows}
    assert eff == pytest.approx({(1, "replicated"): 1.0, (2, "replicated"): 0.95, (4, "replicated"): 0.85,
                                 (2, "fsdp"): 0.855, (4, "fsdp"): 0.765})


def test_scaling_reuses_a_given_one_device_rate_and_rates_without_one_device_against_the_fewest(four_fake_devices):
    rows = bench.scaling("smoke", per_device_batch=3, counts=(1, 4), shardings=("replicated",),
                         one_device={"step_s": 1.0, "frames_per_s": 200.0, "compile_s": 5.0})
    assert four_fake_devices == [(4, "replicated", 12)]  # one device was not timed again
    assert [(r["devices"], r["efficiency"]) for r in rows] == [(1, 1.0), (4, pytest.approx(85.0 / 200.0))]
    rows = bench.scaling("smoke", per_device_batch=3, counts=(2, 4), shardings=("fsdp",))
    assert [r["efficiency"] for r in rows] == [1.0, pytest.approx(0.85 / 0.95)]


def test_scaling_refuses_counts_the_host_cannot_run(four_fake_devices):
    with pytest.raises(ValueError, match="fits this host's 4 devices"):
        bench.scaling("smoke", counts=(8, 16))
    with pytest.raises(ValueError, match=">= 1"):
        bench.scaling("smoke", counts=(0, 2))
