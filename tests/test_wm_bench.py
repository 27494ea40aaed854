"""wm.bench's FLOP count: XLA's cost analysis of the lowered train step, which grows with the batch."""

from wm.bench import step_flops


def test_step_flops_count_the_whole_batch():
    one, two = step_flops("smoke", ["batch=2"]), step_flops("smoke", ["batch=4"])
    assert one > 1e8
    # the per-sample work doubles; the optimiser's update over the parameters does not
    assert 1.8 < two / one < 2.0


def test_matmul_flops_by_shape_counts_convolutions_and_dots_by_hand():
    import jax
    import jax.numpy as jnp

    from wm.bench import matmul_flops_by_shape

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
