"""Learned vision policies: behaviour cloning from head-camera frames (and proprioception) to an
action chunk, in Flax, following the project's policy protocol

    carry = policy.init_carry(params, obs, task_state, rng)      # task_state is ignored (may be None)
    action, carry = policy.act(params, obs, carry, rng)          # obs {"image": (B, S, S, 3) uint8, "proprio": (B, 37)}

so the same checkpoint runs in the simulator (either engine) and inside the world model.

The network sees the current frame, the proprioception (multiplied by `params["proprio_gate"]`: 0
for the lineages trained without it, so every checkpoint of one encoder shares one compiled
program), and the time since the episode began, which the policy counts in its carry (its only
memory). It predicts the next `chunk` actions and predicts the chunk again at every step. By
default the newest chunk's first action is executed (the rest of the chunk is an auxiliary target);
with `ensemble` set, the action executed at step t is the mean of what every chunk still covering t
predicted for it (ACT's temporal ensembling, with weights exp(-ensemble * age), age 0 the newest);
the carry then also holds the last `chunk` predicted chunks.

params: {"net": Flax parameters, "norm": {"proprio_mean", "proprio_std", "action_mean",
"action_std"}, "proprio_gate": ()}.
"""

from __future__ import annotations

import dataclasses
import functools
import os
from pathlib import Path

import flax.linen as nn
import flax.serialization
import jax
import jax.numpy as jnp
import numpy as np

from sim_data.sim import robot as R
from sim_data.sim.tasks import CONTROL_DT
from sim_data.util import is_key_array, jit_initialiser

ENCODERS = ("conv", "vit")
PROPRIO_CLIP = 5.0


@dataclasses.dataclass(frozen=True)
class PolicyNetConfig:
    """The network of a behaviour-cloning policy.

    Attributes:
      encoder: "conv" (three strided convolutions) or "vit" (patch tokens through a small transformer).
      width: channels of the convolutions / the transformer's token width. depth: transformer layers.
      hidden: the MLP head's width. chunk: actions predicted per step. size: frame height = width.
      ensemble: None to execute the newest chunk's first action; a number to execute the mean over
        the chunks covering the step with weights exp(-ensemble * age) (0: uniform; negative: the
        older predictions weigh more, as in ACT).
      keypoints: the conv encoder ends in a spatial softmax (each channel of a stride-4 feature map
        read as the expected image position of its activation, Levine et al. 2016) instead of the
        flattened stride-8 map: where things are, rather than what the map holds.
    """

    encoder: str = "conv"
    width: int = 32
    depth: int = 3
    hidden: int = 256
    chunk: int = 4
    size: int = 64
    ensemble: float | None = None
    keypoints: bool = False

    def validate(self) -> None:
        if self.encoder not in ENCODERS:
            raise ValueError(f"encoder must be one of {ENCODERS}, got {self.encoder!r}")
        if self.chunk < 1 or self.width < 1 or self.hidden < 1:
            raise ValueError("chunk, width and hidden must be >= 1")


class ConvEncoder(nn.Module):
    width: int
    keypoints: bool = False

    @nn.compact
    def __call__(self, x):
        strides = (2, 2, 1) if self.keypoints else (2, 2, 2)
        for i, ((ch, k), s) in enumerate(zip(((self.width, 4), (2 * self.width, 4), (2 * self.width, 3)), strides)):
            x = nn.gelu(nn.Conv(ch, (k, k), strides=s, name=f"conv{i}")(x))
        if self.keypoints:
            return spatial_softmax(x, self.param("temperature", nn.initializers.ones, ()))
        return x.reshape(x.shape[0], -1)


def spatial_softmax(x, temperature):
    """(B, H, W, C) feature map -> (B, 2C): per channel, the softmax-weighted mean (x, y) position in
    [-1, 1] of its activations, sharpened by dividing them by temperature."""
    b, h, w, c = x.shape
    weights = jax.nn.softmax(x.reshape(b, h * w, c) / temperature, axis=1)
    ys, xs = jnp.meshgrid(jnp.linspace(-1.0, 1.0, h), jnp.linspace(-1.0, 1.0, w), indexing="ij")
    grid = jnp.stack([xs.reshape(-1), ys.reshape(-1)], axis=-1).astype(x.dtype)  # (H*W, 2)
    return jnp.einsum("bnc,nk->bck", weights, grid).reshape(b, 2 * c)


class ViTEncoder(nn.Module):
    width: int
    depth: int
    patch: int = 8

    @nn.compact
    def __call__(self, x):
        p = self.patch
        x = nn.Conv(self.width, (p, p), strides=p, padding="VALID", name="patchify")(x)
        b, h, w, c = x.shape
        x = x.reshape(b, h * w, c)
        x = x + self.param("pos", nn.initializers.normal(0.02), (1, h * w, c))
        for i in range(self.depth):
            y = nn.LayerNorm(name=f"ln_a{i}")(x)
            x = x + nn.MultiHeadDotProductAttention(num_heads=4, name=f"attn{i}")(y, y)
            y = nn.LayerNorm(name=f"ln_m{i}")(x)
            x = x + nn.Dense(c, name=f"mlp_out{i}")(nn.gelu(nn.Dense(4 * c, name=f"mlp_in{i}")(y)))
        return nn.LayerNorm(name="ln_out")(x).mean(axis=1)


def time_features(t):
    """(B,) control steps since the episode began -> (B, 8) sines and cosines of its time in seconds."""
    s = t.astype(jnp.float32)[:, None] * CONTROL_DT
    periods = jnp.array([1.0, 2.5, 6.0, 15.0])
    ang = 2 * jnp.pi * s / periods
    return jnp.concatenate([jnp.sin(ang), jnp.cos(ang)], axis=-1)


class PolicyNet(nn.Module):
    """(image (B, S, S, 3) uint8, proprio (B, 37) normalised, t (B,) int) -> (B, chunk, 20) normalised actions.
    dtype: what the encoder computes in, given parameters of that dtype (the zoo's are float32)."""

    cfg: PolicyNetConfig
    dtype: str = "float32"

    @nn.compact
    def __call__(self, image, proprio, t):
        x = (image.astype(jnp.float32) / 255.0 - 0.5).astype(self.dtype)
        if self.cfg.encoder == "conv":
            feat = ConvEncoder(self.cfg.width, self.cfg.keypoints, name="encoder")(x)
        else:
            feat = ViTEncoder(self.cfg.width, self.cfg.depth, name="encoder")(x)
        feat = nn.LayerNorm(name="feat_norm")(nn.Dense(self.cfg.hidden, name="feat")(feat))
        p = nn.Dense(self.cfg.hidden, name="proprio")(proprio)
        h = jnp.concatenate([feat, p, nn.Dense(32, name="time")(time_features(t))], axis=-1)
        h = nn.gelu(nn.Dense(self.cfg.hidden, name="mlp0")(h))
        h = nn.gelu(nn.Dense(self.cfg.hidden, name="mlp1")(h))
        out = nn.Dense(self.cfg.chunk * R.ACTION_DIM, name="head", kernel_init=nn.initializers.zeros)(h)
        return out.reshape(-1, self.cfg.chunk, R.ACTION_DIM)


def normalise_proprio(params, proprio):
    """Standardised proprioception, clipped to +-PROPRIO_CLIP (the world model's predicted state can
    stray far outside the demonstrations), times the lineage's gate."""
    n = params["norm"]
    z = jnp.clip((proprio - n["proprio_mean"]) / n["proprio_std"], -PROPRIO_CLIP, PROPRIO_CLIP)
    return jnp.nan_to_num(z) * params["proprio_gate"]


def predict_chunk(cfg: PolicyNetConfig, params, image, proprio, t):
    """The predicted action chunk (B, chunk, 20) in the action's own units."""
    out = PolicyNet(cfg).apply({"params": params["net"]}, image, normalise_proprio(params, proprio), t)
    n = params["norm"]
    return out * n["action_std"] + n["action_mean"]


@functools.lru_cache(maxsize=16)
def _net_init(cfg: PolicyNetConfig):
    """The network's initialiser, rng -> parameters, as one program: run eagerly, each of its
    initialisers' ops would compile on its own (hundreds of small programs a network)."""
    def init(rng):
        image = jnp.zeros((1, cfg.size, cfg.size, 3), jnp.uint8)
        return PolicyNet(cfg).init(rng, image, jnp.zeros((1, R.PROPRIO_DIM)), jnp.zeros((1,), jnp.int32))["params"]

    return jit_initialiser(init)


def init_params(cfg: PolicyNetConfig, rng, norm: dict, use_proprio: bool) -> dict:
    """Fresh parameters; norm holds proprio/action mean and std ((37,), (20,))."""
    cfg.validate()
    net = _net_init(cfg)(rng)
    return {"net": net, "norm": {k: jnp.asarray(v, jnp.float32) for k, v in norm.items()},
            "proprio_gate": jnp.asarray(1.0 if use_proprio else 0.0, jnp.float32)}


@functools.lru_cache(maxsize=16)
def stand_in_params(cfg: PolicyNetConfig, use_proprio: bool) -> dict:
    """Parameters of the shapes, dtypes and placement of a saved checkpoint's (load_params), before any
    is saved: freshly initialised, with a unit normalisation. A program compiled for them is the
    checkpoint's program. One set per network and proprioception (every planned checkpoint of a
    lineage shares it: the arrays are never changed in place)."""
    norm = {"proprio_mean": np.zeros(R.PROPRIO_DIM), "proprio_std": np.ones(R.PROPRIO_DIM),
            "action_mean": np.zeros(R.ACTION_DIM), "action_std": np.ones(R.ACTION_DIM)}
    fresh = init_params(cfg, jax.random.PRNGKey(0), norm, use_proprio)
    return jax.tree_util.tree_map(lambda x: jax.device_put(np.asarray(x)), fresh)


def ensembled_action(past, age_weights):
    """The action of this step from the last C chunks past (B, C, C, 20), past[:, k] predicted k
    steps ago (zeros where no chunk was predicted yet), each chunk's prediction for this step being
    past[:, k, k]; age_weights (B, C) are 0 for the missing chunks. Returns (B, 20)."""
    c = past.shape[1]
    for_now = past[:, jnp.arange(c), jnp.arange(c)]  # (B, C, 20)
    w = age_weights / jnp.sum(age_weights, axis=1, keepdims=True)
    return jnp.einsum("bk,bka->ba", w, for_now)


@dataclasses.dataclass(frozen=True)
class BCPolicy:
    """A behaviour-cloning policy of the project's protocol (see the module doc); the carry is the
    step count (B,) int32, or with `cfg.ensemble` set {"t": (B,) int32, "past": (B, C, C, 20) the last
    C predicted chunks, newest first}."""

    cfg: PolicyNetConfig

    @property
    def stacks_in_turn(self) -> bool:
        """Stacked checkpoints of a convolutional encoder run one after another (StackedPolicy.in_turn)."""
        return self.cfg.encoder == "conv"

    def init_carry(self, params, obs, task_state, rng):
        del params, task_state, rng
        t = jnp.zeros((obs["proprio"].shape[0],), jnp.int32)
        if self.cfg.ensemble is None:
            return t
        return {"t": t, "past": jnp.zeros((t.shape[0], self.cfg.chunk, self.cfg.chunk, R.ACTION_DIM), jnp.float32)}

    def act(self, params, obs, carry, rng):
        """The action (B, 20) from obs {"image": (B, S, S, 3) uint8, "proprio": (B, 37)}: the first of the chunk
        predicted now, or with cfg.ensemble the weighted mean of what every chunk covering this step predicted for
        it; and the carry, one step on. rng is unused (the policy is deterministic)."""
        del rng
        t = carry if self.cfg.ensemble is None else carry["t"]
        chunk = predict_chunk(self.cfg, params, obs["image"], obs["proprio"], t)
        if self.cfg.ensemble is None:
            return chunk[:, 0], t + 1
        past = jnp.concatenate([chunk[:, None].astype(jnp.float32), carry["past"][:, :-1]], axis=1)
        age = jnp.arange(self.cfg.chunk)
        weights = jnp.exp(-self.cfg.ensemble * age)[None] * (age[None] <= t[:, None])
        return ensembled_action(past, weights), {"t": t + 1, "past": past}


@dataclasses.dataclass(frozen=True)
class StackedPolicy:
    """P policies of one protocol object with stacked parameters (every leaf has a leading P axis),
    run as one batch: episodes [i*n, (i+1)*n) of a batch of B = P*n use parameters i. One compiled
    rollout then serves a whole checkpoint series. size: P, for parameter trees without arrays to
    count it from (a plug-in whose params are {} or None); `stacked` sets it. in_turn: run the P
    policies one after another inside the program (`lax.map`) instead of side by side (`vmap`):
    vmapped convolutions become grouped convolutions, which run several times slower than the same
    convolutions one parameter set at a time (`stacked` sets it for policies whose `stacks_in_turn`
    is true); the actions agree to float rounding. salted: params is {"params": the stacked tree,
    "salt": (P,) uint32} and set i draws its random numbers from the call's key folded with salt[i]
    instead of from the i-th split of it, so that a policy given a salt of its own (its name's, for
    instance) draws the same numbers wherever it stands in the batch."""

    policy: object
    size: int = 0
    in_turn: bool = False
    salted: bool = False

    @staticmethod
    def _split(x, p):
        return x.reshape((p, x.shape[0] // p) + x.shape[1:])

    def count(self, params) -> int:
        """P, the parameter sets stacked in params."""
        if self.salted:
            return params["salt"].shape[0]
        leaves = jax.tree_util.tree_leaves(params)
        if leaves:
            return leaves[0].shape[0]
        if self.size < 1:
            raise ValueError("parameters without arrays: build the StackedPolicy with stacked(policy, params_list), "
                             "which records how many sets it stacks")
        return self.size

    def _each(self, fn, *stacks):
        """fn applied to each of the P slices of the stacked trees, its outputs stacked again."""
        if self.in_turn:
            return jax.lax.map(lambda args: fn(*args), stacks)
        return jax.vmap(fn)(*stacks)

    def _keys(self, params, rng) -> tuple:
        """(the stacked parameter tree, (P,) keys: one per parameter set)."""
        if self.salted:
            return params["params"], jax.vmap(jax.random.fold_in, (None, 0))(rng, params["salt"])
        return params, jax.random.split(rng, self.count(params))

    def init_carry(self, params, obs, task_state, rng):
        """The P policies' carries, stacked: each leaf (P, ...) whatever the policy's own carry holds
        (a leaf shared by its batch, of shape (), stays one; the rollout never reads the carry)."""
        p = self.count(params)
        split = lambda tree: jax.tree_util.tree_map(lambda x: self._split(x, p), tree)
        params, keys = self._keys(params, rng)
        return self._each(self.policy.init_carry, params, split(obs), split(task_state), keys)

    def act(self, params, obs, carry, rng):
        p = self.count(params)
        split = lambda tree: jax.tree_util.tree_map(lambda x: self._split(x, p), tree)
        params, keys = self._keys(params, rng)
        action, carry = self._each(self.policy.act, params, split(obs), carry, keys)
        return action.reshape((-1,) + action.shape[2:]), carry


@dataclasses.dataclass(frozen=True)
class MixedPolicy:
    """Policy objects of different architectures side by side in one batch: the first rows[0] rows
    run policies[0] with params[0], the next rows[1] policies[1] with params[1], and so on (params: a
    tuple, one tree per policy; the carry a tuple likewise). One compiled rollout then serves a whole
    zoo, whatever its architectures, instead of one per architecture. Every policy is given the call's
    key: salted StackedPolicies draw by their sets' salts, the same whatever else shares the batch."""

    policies: tuple
    rows: tuple

    def __post_init__(self):
        if len(self.policies) != len(self.rows) or not self.rows or min(self.rows) < 1:
            raise ValueError(f"one positive row count per policy, got {len(self.policies)} policies and rows {self.rows}")

    def _slices(self) -> list[slice]:
        ends = np.cumsum(self.rows)
        return [slice(int(e - r), int(e)) for e, r in zip(ends, self.rows, strict=True)]

    def count(self, params) -> int:
        """The parameter sets of every policy in params (each a StackedPolicy's, or another with count)."""
        return sum(pol.count(p) for pol, p in zip(self.policies, params, strict=True))

    def _check(self, obs):
        b = jax.tree_util.tree_leaves(obs)[0].shape[0]
        if b != sum(self.rows):
            raise ValueError(f"a batch of {b} rows for policies of {sum(self.rows)} rows {self.rows}")

    def init_carry(self, params, obs, task_state, rng):
        self._check(obs)
        return tuple(pol.init_carry(p, _rows(obs, s), None if task_state is None else _rows(task_state, s), rng)
                     for pol, p, s in zip(self.policies, params, self._slices(), strict=True))

    def act(self, params, obs, carry, rng):
        self._check(obs)
        out = [pol.act(p, _rows(obs, s), c, rng)
               for pol, p, s, c in zip(self.policies, params, self._slices(), carry, strict=True)]
        return jnp.concatenate([a.astype(jnp.float32) for a, _ in out]), tuple(c for _, c in out)


def _rows(tree, s: slice):
    return jax.tree_util.tree_map(lambda x: x[s], tree)


def stacked(policy, params_list: list, salts=None) -> tuple:
    """(StackedPolicy of policy, its stacked parameters): P = len(params_list) parameter sets of one
    policy object run as one batch (see StackedPolicy), in turn where the policy's `stacks_in_turn` says so;
    with salts (P ints), each set's random numbers follow its salt instead of its place (a salted StackedPolicy)."""
    in_turn = bool(getattr(policy, "stacks_in_turn", False))
    params = stack_params(params_list)
    if salts is None:
        return StackedPolicy(policy, size=len(params_list), in_turn=in_turn), params
    if len(salts) != len(params_list):
        raise ValueError(f"{len(salts)} salts for {len(params_list)} parameter sets")
    salt = jax.device_put(np.asarray(salts, np.uint32))
    return StackedPolicy(policy, size=len(params_list), in_turn=in_turn, salted=True), {"params": params, "salt": salt}


def stack_params(params_list: list) -> dict:
    """Stacks P parameter trees of one structure along a new leading axis. Stacked on the host, then
    moved to the device: an eager jnp.stack compiles a program for every leaf shape and count (dozens
    a zoo, each time a new set of policies is stacked; so would jnp.asarray of the result)."""
    return jax.tree_util.tree_map(_stack_leaf, *params_list)


def _stack_leaf(*xs):
    if is_key_array(xs[0]):  # typed keys: their key data stacked, wrapped as keys of the same implementation
        data = np.stack([np.asarray(jax.random.key_data(x)) for x in xs])
        return jax.random.wrap_key_data(jax.device_put(data), impl=jax.random.key_impl(xs[0]))
    return jax.device_put(np.stack([np.asarray(x) for x in xs]))


def to_numpy(params) -> dict:
    """params with every leaf copied to the host as a numpy array."""
    return jax.tree_util.tree_map(lambda x: np.asarray(x), params)


def save_params(path: Path, params) -> None:
    """Writes a parameter tree as msgpack, atomically (a temporary file, then a rename)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + f".tmp{os.getpid()}")
    tmp.write_bytes(flax.serialization.msgpack_serialize(to_numpy(params)))
    os.replace(tmp, path)


def load_params(path: Path) -> dict:
    """The parameters saved by save_params, as jax arrays (device_put: jnp.asarray of a numpy array
    compiles a small program for every leaf shape)."""
    return jax.tree_util.tree_map(jax.device_put, flax.serialization.msgpack_restore(Path(path).read_bytes()))
