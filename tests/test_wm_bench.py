"""wm.bench's FLOP count: XLA's cost analysis of the lowered train step, which grows with the batch."""

from wm.bench import step_flops


def test_step_flops_count_the_whole_batch():
    one, two = step_flops("smoke", ["batch=2"]), step_flops("smoke", ["batch=4"])
    assert one > 1e8
    # the per-sample work doubles; the optimiser's update over the parameters does not
    assert 1.8 < two / one < 2.0
