"""The loop oracle: a policy's closed loop in the simulator reading stand-ins for imagined frames."""

import json
import textwrap

import numpy as np
import pytest
from PIL import Image

from experiments import loop_oracle as L

PLUGINS = "blind=examples.plugin_policy:make,look=oracle_probe:make"
PLAIN = [m for m in L.MODES if m not in L.NEEDS_FILL]  # the stand-ins that need no trained fill

# Backs away until the counter's white top fills less than 60% of the share of the frame it filled at the
# start (a latch in the carry): a policy that reads how far it has come from its camera alone.
PROBE = textwrap.dedent("""
    import dataclasses
    import jax.numpy as jnp
    from examples.plugin_policy import ready_pose
    from sim_data.sim import robot

    def white(image):
        return (image.min(axis=-1) > 200).mean(axis=(1, 2))

    @dataclasses.dataclass(frozen=True)
    class WhiteBack:
        def init_carry(self, params, obs, task_state, rng):
            return white(obs["image"]), jnp.zeros((obs["image"].shape[0],), bool)

        def act(self, params, obs, carry, rng):
            start, stopped = carry
            stopped = stopped | (white(obs["image"]) < 0.6 * start)
            hold = jnp.broadcast_to(params["ready"], (start.shape[0], robot.ACTION_DIM))
            return hold.at[:, robot.FORWARD_SPEED].set(jnp.where(stopped, 0.0, -0.3)), (start, stopped)

    def make():
        return WhiteBack(), {"ready": ready_pose()}
""")


@pytest.fixture(autouse=True)
def probe_module(tmp_path_factory, monkeypatch):
    d = tmp_path_factory.mktemp("probe")
    (d / "oracle_probe.py").write_text(PROBE)
    monkeypatch.syspath_prepend(str(d))


@pytest.mark.slow  # 30 s of closed loops on 2 cores; the reprojection itself is tested in tests/test_render.py
def test_the_frames_move_a_policy_that_reads_them_and_no_other(tmp_path, monkeypatch):
    """The back-away plug-in that ignores its camera acts alike on every stand-in, whose frames drift
    from the true ones as the robot moves; a probe that stops once the counter's white top has shrunk in its
    view never stops on the first frame held and stops near the true place on the reprojected one.
    Rerun, the same study computes nothing again."""
    res = L.study(PLUGINS, ["step_back"], tmp_path, PLAIN, 2, 0, progress=False)
    blind, look = res["tasks"]["step_back"]["blind"], res["tasks"]["step_back"]["look"]
    assert blind["true"]["psnr_db_steps_1_8"] == 100.0 and "action_gap" not in blind["true"]
    for mode in PLAIN[1:]:
        assert blind[mode]["action_gap"] == 0.0
        assert blind[mode]["back_m"] == blind["true"]["back_m"]
        assert blind[mode]["psnr_db_second_half"] < 30.0
    assert blind["still"]["psnr_db_second_half"] < blind["reproject"]["psnr_db_second_half"]
    true_back = look["true"]["back_m"]["mean"]
    assert 0.1 < true_back < 1.0
    assert look["still"]["back_m"]["mean"] > true_back + 0.4 and look["still"]["action_gap"] > 0.0
    assert abs(look["reproject"]["back_m"]["mean"] - true_back) < 0.2

    strip = np.asarray(Image.open(tmp_path / "frames" / "step_back" / "look_still.png"))
    assert strip.shape == (2 * 64 * 4, L.STRIP_FRAMES * 64 * 4, 3)
    first, last = strip[:256, :256], strip[:256, -256:]  # the true view moved; the still one did not
    assert (first != last).any() and (strip[256:, :256] == strip[256:, -256:]).all()
    monkeypatch.setattr(L, "run_loop", lambda *a, **k: pytest.fail("a finished loop ran again"))
    assert L.study(PLUGINS, ["step_back"], tmp_path, PLAIN, 2, 0, progress=False) == res
    assert L.study(PLUGINS, ["step_back"], tmp_path, ["still"], 2, 0, progress=False) == res
    assert json.loads((tmp_path / L.RESULTS).read_text()) == res
    with pytest.raises(ValueError, match="--episodes"):
        L.study(PLUGINS, ["step_back"], tmp_path, ["still"], 3, 0, progress=False)


@pytest.mark.parametrize("modes, tasks, match", [(["blurry"], ["step_back"], "unknown modes"),
                                                 (["still"], ["dance"], "unknown tasks")])
def test_bad_inputs_are_refused(tmp_path, modes, tasks, match):
    with pytest.raises(ValueError, match=match):
        L.study(PLUGINS, tasks, tmp_path, modes, 2, 0, progress=False)
