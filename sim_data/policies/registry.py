"""Naming policies: registry checkpoints and users' own policies (plug-ins), for the data generator,
the evaluator and the report.

A policy spec is one of
- a zoo registry: `runs/policies/demo` or `runs/policies/demo/policies.json` (every checkpoint),
  optionally narrowed with `#` and `+`-separated names, lineages or tasks:
  `runs/policies/demo#conv_proprio+vit_noproprio`, `runs/policies/demo#mug/conv_proprio/300`,
  and thinned with `@K/N`: every N-th checkpoint of each lineage and task, from the K-th, in the
  order of training steps (`runs/policies/demo#@0/2`: the 1st, 3rd, 5th, ... of every lineage);
  a term that names nothing in the registry, or a `#` with no term after it, is an error, and the
  registry's records are checked (load_registry) before any policy runs;
- a plug-in: `package.module:attribute`, where the attribute is a callable returning
  `(policy, params)` (or is that pair itself). `policy` follows the project's protocol,

      carry = policy.init_carry(params, obs, task_state, rng)
      action, carry = policy.act(params, obs, carry, rng)

  batched over a leading axis B (obs {"image": (B, 64, 64, 3) uint8 head-camera frame,
  "proprio": (B, 37)}; action (B, 20), layout in `sim_data.sim.robot`), jittable, with `params` shared by
  the batch (any pytree: typed random keys included) and a carry that only the policy reads (any
  pytree of arrays, with or without the batch axis); it must be hashable (a frozen dataclass, for
  instance), since compiled rollouts are cached per policy. In the world model `task_state` is None.
  A plug-in policy runs on every task it is asked for; `name=` in front of the spec names it
  (`mine=my_pkg.policies:make`).
"""

from __future__ import annotations

import dataclasses
import difflib
import functools
import hashlib
import importlib
import importlib.util
import inspect
import json
import re
import sys
import typing
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from sim_data.policies.bc import BCPolicy, PolicyNetConfig, load_params, stacked, stand_in_params
from sim_data.policies.degrade import DegradedPolicy, degrade_params, perturbed_params
from sim_data.sim.robot import ACTION_DIM, PROPRIO_DIM, clip_action, robot_index
from sim_data.sim.scene import load_model
from sim_data.sim.tasks import TASK_NAMES
from sim_data.util import even_pieces, hash_arrays, pad_with_last, read_json


@typing.runtime_checkable
class Policy(typing.Protocol):
    """The policy protocol (see the module doc): batched over a leading axis B, jittable, hashable.

    init_carry(params, obs, task_state, rng) -> carry; act(params, obs, carry, rng) -> (action (B, 20),
    carry), with obs {"image": (B, S, S, 3) uint8, "proprio": (B, 37)} and task_state None in the
    world model."""

    def init_carry(self, params, obs, task_state, rng): ...

    def act(self, params, obs, carry, rng): ...


@dataclasses.dataclass(frozen=True, eq=False)
class PolicySource:
    """A named policy with its parameters.

    Attributes:
      name: unique, e.g. "mug/conv_proprio/300" or "my_pkg.policies:make".
      kind: "learned" (a registry checkpoint), "plugin", or PERTURBED (perturbed_copy). task: the task it
      was trained for (None: any). policy, params: the protocol object and its parameters (a perturbed
      copy's: the base's; episodes_params gives a batch's). record: the registry record (lineage, step,
      val_loss, ...) or {"plugin": its spec} for a plug-in. code: a plug-in's code_digest ("" else).
    """

    name: str
    kind: str
    task: str | None
    policy: object
    params: object
    record: dict
    code: str = ""

    @property
    def slug(self) -> str:
        """The name as a file-name fragment."""
        return re.sub(r"[^A-Za-z0-9]+", "_", self.name).strip("_")

    def runs_on(self, task: str) -> bool:
        return self.task is None or self.task == task

    @property
    def salt(self) -> int:
        """A number from the name alone (uint32): the evaluator's salt for this policy's random numbers
        (sim_data.policies.bc.stacked), so that they do not depend on which policies share its batch."""
        return int.from_bytes(hashlib.sha256(self.name.encode()).digest()[:4], "little")

    def episodes_params(self, episodes) -> object:
        """The parameters that run this source's episodes `episodes` (indices, one per row of a batch)."""
        return perturbed_params(self.params, episodes) if self.kind == PERTURBED else self.params


PERTURBED = "perturbed"


def perturbed_copy(source: PolicySource) -> PolicySource:
    """A registry checkpoint whose every episode is degraded by its own knob and level
    (sim_data.policies.degrade.perturbation): named `<name>~perturbed`, of kind PERTURBED."""
    if source.kind != "learned" or source.record.get("degrade"):
        raise ValueError(f"{source.name}: only a registry checkpoint (not a plug-in or a family's member) "
                         "can be perturbed")
    return dataclasses.replace(source, name=f"{source.name}~perturbed", kind=PERTURBED,
                               policy=DegradedPolicy(source.policy))


def is_plugin(spec: str) -> bool:
    """Whether a policy spec names a plug-in (`[name=]package.module:attribute`) rather than a registry: its target
    holds a colon, is not an existing path, and has no slash before the colon."""
    target = spec.split("=", 1)[-1]
    return ":" in target and not Path(target.split("#")[0]).exists() and "/" not in target.split(":")[0]


def _import_plugin(spec: str, module_name: str, attr: str) -> tuple:
    """(the plug-in's module, what its attribute gives: the attribute called where it is callable), with
    errors that name the plug-in and keep the user's traceback."""
    try:
        module = importlib.import_module(module_name)
    except ImportError as e:
        if e.name and (module_name == e.name or module_name.startswith(e.name + ".")):  # the module itself
            raise ValueError(f"plug-in {spec!r}: cannot import {module_name!r} ({e}); is it on PYTHONPATH?") from e
        raise ValueError(f"plug-in {spec!r}: importing {module_name!r} failed: {e} (something it imports is "
                         "not installed or not on PYTHONPATH)") from e
    except Exception as e:  # the user's module fails as it imports (a SyntaxError, its own code): keep its traceback
        raise RuntimeError(f"plug-in {spec!r}: importing {module_name!r} raised {type(e).__name__}: {e}") from e
    if not hasattr(module, attr):
        close = difflib.get_close_matches(attr, [n for n in dir(module) if not n.startswith("_")], n=3)
        raise ValueError(f"plug-in {spec!r}: module {module_name!r} has no attribute {attr!r}"
                         + (f"; did you mean {' or '.join(close)}?" if close else ""))
    obj = getattr(module, attr)
    if callable(obj) and not isinstance(obj, tuple):
        try:
            return module, obj()
        except Exception as e:  # the user's own code: keep its traceback, name the plug-in
            raise RuntimeError(f"plug-in {spec!r}: {module_name}.{attr}() raised {type(e).__name__}: {e}") from e
    return module, obj


def load_plugin(spec: str, world_model: bool = True) -> PolicySource:
    """`[name=]package.module:attribute` -> its PolicySource, the policy checked against the protocol
    (check_protocol) before anything runs it. world_model: whether it will also run in a world model,
    which gives it no task state (False: the simulator alone, whose task state it may read)."""
    name, _, target = spec.rpartition("=")
    module_name, _, attr = target.partition(":")
    if not module_name or not attr:
        raise ValueError(f"plug-in {spec!r}: a plug-in is package.module:attribute, the attribute a callable "
                         "returning (policy, params)")
    x64 = bool(jax.config.jax_enable_x64)
    try:
        module, got = _import_plugin(spec, module_name, attr)
    finally:  # put back whatever befell the import: every program of the process would change its dtypes
        switched = bool(jax.config.jax_enable_x64) != x64
        if switched:
            jax.config.update("jax_enable_x64", x64)
    if switched:
        raise ValueError(f"plug-in {spec!r}: importing or calling it turned JAX's 64-bit mode (jax_enable_x64) "
                         f"{'on' if not x64 else 'off'}; the simulator, renderer and world model run in 32 bits: "
                         "leave the setting as it is and cast inside the policy instead")
    if not (isinstance(got, tuple) and len(got) == 2):
        raise ValueError(f"plug-in {spec!r} must give (policy, params), got {type(got).__name__}")
    policy, params = got
    if not isinstance(policy, Policy):
        missing = [m for m in ("init_carry", "act") if not callable(getattr(policy, m, None))]
        raise ValueError(f"plug-in {spec!r}: the policy has no {', '.join(missing)}() "
                         "(the protocol: sim_data.policies.registry.Policy)")
    try:
        hash(policy)
    except TypeError:
        raise ValueError(f"plug-in {spec!r}: the policy must be hashable (a frozen dataclass, for instance)") from None
    traced = check_protocol(spec, policy, params, task_state_optional=not world_model)
    files = sorted({f for f in (_source_file(module), _source_file(type(policy))) if f})
    # a policy of the project's own classes (a zoo checkpoint served by a user's module) computes what
    # its description and parameters say, as the zoo's does: the module that built it is no part of it
    code = "" if is_project_policy(policy) else code_digest(files, traced)
    return PolicySource(name=name or target, kind="plugin", task=None,
                        policy=ClippedPolicy(policy, *action_bounds(), simulator_only=not world_model),
                        params=params, record={"plugin": target}, code=code)


def is_project_policy(policy) -> bool:
    """Whether a policy object and every policy it wraps (its dataclass fields, in turn) are of classes the
    project defines (sim_data's), whose code is the project's at every commit, rather than ones a
    plug-in's module defines."""
    def policies(x):
        if callable(getattr(x, "act", None)):
            yield x
        if dataclasses.is_dataclass(x) and not isinstance(x, type):
            for f in dataclasses.fields(x):
                yield from policies(getattr(x, f.name))
        elif isinstance(x, (tuple, list)):
            for y in x:
                yield from policies(y)

    return all(type(p).__module__.split(".")[0] == "sim_data" for p in policies(policy))


@dataclasses.dataclass(frozen=True, eq=False)
class ClippedPolicy:
    """A plug-in whose actions are clipped to their ranges (the actuators' control ranges; speeds
    +-0.5 m/s and +-1 rad/s): the simulator applies them so, and the world model and the dataset see
    the actions as applied, not as asked for. Equal (and so stacked, and sharing compiled rollouts)
    only where the wrapped policies are equal and of one type: policies of different classes may
    compare equal (namedtuples of equal fields do, as tuples)."""

    policy: object
    low: tuple  # (20,)
    high: tuple
    simulator_only: bool = False  # the data generator's: it may read the simulator's obs and task state


    @property
    def stacks_in_turn(self) -> bool:
        """The wrapped policy's (sim_data.policies.bc.stacked): a convolutional network stays in turn."""
        return bool(getattr(self.policy, "stacks_in_turn", False))

    def _key(self) -> tuple:
        return type(self.policy), self.policy, self.low, self.high, self.simulator_only

    def _view(self, obs: dict) -> dict:
        return obs if self.simulator_only else plugin_view(obs)

    def __eq__(self, other):
        return self._key() == other._key() if type(other) is ClippedPolicy else NotImplemented

    def __hash__(self):
        return hash(self._key())

    def init_carry(self, params, obs, task_state, rng):
        """The wrapped policy's carry, from what it sees in the world model too (plugin_view, no task
        state), unless simulator_only."""
        return self.policy.init_carry(params, self._view(obs), task_state if self.simulator_only else None, rng)

    def act(self, params, obs, carry, rng):
        """The wrapped policy's action (B, 20) on what it sees (as init_carry), a NaN as 0 and clipped to
        [low, high], and its carry: the simulator on either engine and the world model then take the same
        action (the C engine would zero every control of a step with a NaN, MJX carry it into the state,
        the world model's imagination diverge)."""
        action, carry = self.policy.act(params, self._view(obs), carry, rng)
        return clip_action(action, self.low, self.high), carry


PLUGIN_OBS = ("image", "proprio")  # what a policy sees, in the simulator as in the world model


def applied_policy(policy) -> ClippedPolicy:
    """policy as imagination runs it: its actions as the robot applies them (a NaN as 0, clipped to the
    robot's ranges; sim_data.sim.robot.applied_action), as a rollout records them and the world model
    was trained on them, its observations unchanged. A ClippedPolicy (a plug-in) is returned as it is."""
    if isinstance(policy, ClippedPolicy):
        return policy
    return ClippedPolicy(policy, *action_bounds(), simulator_only=True)  # sees what imagination gives it


@functools.lru_cache(maxsize=1)
def action_bounds() -> tuple:
    """(low, high): the robot's action ranges (robot_index's action_low, action_high), each a (20,) tuple."""
    idx = robot_index(load_model())
    return tuple(idx.action_low.tolist()), tuple(idx.action_high.tolist())


def plugin_view(obs: dict) -> dict:
    """obs cut down to PLUGIN_OBS: the simulator's rollout also carries privileged state (qpos, qvel,
    time) that the world model cannot give, so a plug-in that read it would run otherwise in each."""
    return {k: obs[k] for k in PLUGIN_OBS if k in obs}


def _source_file(obj) -> str | None:
    """The source file of a module or class; None for a built-in one."""
    try:
        return inspect.getsourcefile(obj)
    except TypeError:
        return None


def check_protocol(spec: str, policy, params, batch: int = 2, size: int = 64,
                   task_state_optional: bool = False) -> str:
    """Traces (jax.make_jaxpr: nothing is compiled or run) init_carry and act on a batch of `batch`
    blank observations, as the world model gives them (task_state None), and raises an error naming
    the plug-in where the policy fails (RuntimeError, the user's traceback kept), where its action is
    not (batch, 20) or where act returns a carry of another structure, shape or dtype than it was given
    (ValueError; the rollouts run it in lax.scan). Returns a digest of the traced programs and their
    constants, which follow the functions and arrays the policy calls wherever they live (code_digest);
    where task_state_optional (the simulator alone, which gives the policy its task state, will run
    it), a policy that fails here is not checked: a warning says so and the digest is "".
    size: the frames' side, 64 as in every preset. The policy is traced at a second batch, batch + 1,
    too: the rollouts run it on batches of every size, so a batch fixed in its code fails here; and
    stacked (sim_data.policies.bc.stacked), as every rollout and imagination runs it: under jax.vmap
    (unless its stacks_in_turn), its parameters stacked into arrays."""
    traced = _check_batch(spec, policy, params, batch, size, task_state_optional)
    if traced is None:
        return ""
    _check_batch(spec, policy, params, batch + 1, size, task_state_optional=False, hint=FIXED_BATCH)
    _check_batch(spec, *stacked(policy, [params], [0]), batch, size, task_state_optional=False, hint=STACKED)
    init_jaxpr, act_jaxpr = traced
    h = hashlib.sha256(f"{init_jaxpr}\n{act_jaxpr}".encode())
    hash_arrays(h, [*init_jaxpr.consts, *act_jaxpr.consts])  # the printed program names them, not their values
    return h.hexdigest()


def trace_on_blank_batch(policy, params, batch: int, size: int):
    """(init_carry's program, its carry's shapes, act's program, act's output shapes), traced
    (jax.make_jaxpr: nothing is compiled or run) on a blank batch as the world model gives it: image
    (batch, size, size, 3) uint8, proprio (batch, 37) float32, task_state None."""
    obs = {"image": jax.ShapeDtypeStruct((batch, size, size, 3), jnp.uint8),
           "proprio": jax.ShapeDtypeStruct((batch, PROPRIO_DIM), jnp.float32)}
    rng = jax.random.PRNGKey(0)
    init = lambda p, o, k: policy.init_carry(p, o, None, k)  # noqa: E731
    init_jaxpr, carry = jax.make_jaxpr(init, return_shape=True)(params, obs, rng)
    act_jaxpr, out = jax.make_jaxpr(policy.act, return_shape=True)(params, obs, carry, rng)
    return init_jaxpr, carry, act_jaxpr, out


FIXED_BATCH = " (is the batch size fixed in its code? the rollouts run batches of every size)"
STACKED = (" (as the rollouts and imagination run it: stacked, under jax.vmap unless the policy's stacks_in_turn is "
           "true, its parameters as arrays; a jax.pure_callback needs a vmap_method, and a Python number among "
           "the parameters becomes a float32 or int32 array)")


def _described(out) -> str:
    """What a policy's act returned, for an error: an array as "an array of shape (B, 20)", a tuple or list of
    another length as its length and its items' shapes."""
    if hasattr(out, "shape"):
        return f"an array of shape {tuple(out.shape)}"
    if isinstance(out, (tuple, list)):
        shapes = [tuple(x.shape) if hasattr(x, "shape") else type(x).__name__ for x in out]
        return f"a {type(out).__name__} of {len(out)}: {shapes}"
    return f"a {type(out).__name__}"


def _check_batch(spec: str, policy, params, batch: int, size: int, task_state_optional: bool, hint: str = ""):
    """check_protocol at one batch size: (init_carry's and act's traced programs), or None where the
    policy fails without a task state and task_state_optional (a warning says so). hint: what a failure
    most likely means (a second batch size: a batch fixed in the policy's code; stacked: vmap)."""
    try:
        init_jaxpr, carry, act_jaxpr, out = trace_on_blank_batch(policy, params, batch, size)
    except Exception as e:
        if task_state_optional:
            print(f"warning: plug-in {spec!r} is not checked: it fails without the simulator's task state "
                  f"({type(e).__name__}: {e}); the simulator runs it with one", file=sys.stderr)
            return None
        raise RuntimeError(f"plug-in {spec!r}: the policy fails on a batch of {batch} observations "
                           f"(image ({batch}, {size}, {size}, 3) uint8, proprio ({batch}, {PROPRIO_DIM}) float32, "
                           f"task_state None, as in the world model){hint}: {type(e).__name__}: {e}") from e
    if not (isinstance(out, (tuple, list)) and len(out) == 2):
        raise ValueError(f"plug-in {spec!r}: act must return a pair (action, carry), got {_described(out)}")
    action, after = out
    if getattr(action, "shape", None) != (batch, ACTION_DIM):
        raise ValueError(f"plug-in {spec!r}: act must return actions of shape ({batch}, {ACTION_DIM}) for a "
                         f"batch of {batch}, got {getattr(action, 'shape', type(action).__name__)}{hint}")
    before_s, after_s = (jax.tree.map(lambda x: (x.shape, str(x.dtype)), c) for c in (carry, after))
    if jax.tree.structure(carry) != jax.tree.structure(after) or before_s != after_s:
        raise ValueError(f"plug-in {spec!r}: act must return its carry with the structure, shapes and dtypes it "
                         f"was given (the rollouts run it inside lax.scan){hint}: given {before_s}, returned {after_s}")
    return init_jaxpr, act_jaxpr


def code_digest(files, traced: str) -> str:
    """A digest of a plug-in's code: its source files (its module's and its policy class's) and the
    programs its methods trace to (check_protocol's digest, which follows the helpers and constants
    they call wherever they live): what a result of the plug-in is computed with, beside its parameters."""
    h = hashlib.sha256(traced.encode())
    for f in files:
        h.update(Path(f).read_bytes())
    return h.hexdigest()[:16]


def describe(x) -> str:
    """A description of a policy object that is the same in every process: its repr, with a dataclass's
    fields described in turn and memory addresses (a default repr's) left out."""
    if dataclasses.is_dataclass(x) and not isinstance(x, type):
        fields = ", ".join(f"{f.name}={describe(getattr(x, f.name))}" for f in dataclasses.fields(x))
        return f"{type(x).__module__}.{type(x).__qualname__}({fields})"
    if isinstance(x, (tuple, list)):
        return "(" + ", ".join(map(describe, x)) + ")"
    return re.sub(r" at 0x[0-9a-fA-F]+", "", repr(x))


def fingerprint(source: PolicySource) -> str:
    """A digest of what the policy computes: its description, its parameters and, for a plug-in of a
    class of its own, its code when it was loaded (code_digest); a rerun into the same output compares
    it. A plug-in that serves one of the project's policies (is_project_policy) with a zoo checkpoint's
    parameters is that checkpoint. A plug-in is described without its ClippedPolicy, whose
    simulator_only differs between the data generator and the evaluation: the same plug-in is one
    policy in both."""
    policy = source.policy.policy if isinstance(source.policy, ClippedPolicy) else source.policy
    h = hashlib.sha256(describe(policy).encode())
    hash_arrays(h, source.params)
    h.update(source.code.encode())
    return h.hexdigest()[:16]


REGISTRY, PLAN = "policies.json", "plan.json"  # a zoo's registry, and the one it plans before training


def load_registry_sources(spec: str, planned: bool = False) -> list[PolicySource]:
    """`PATH[#selector+...]` -> the registry's checkpoints whose name, lineage or task is selected.
    planned: those of the zoo's plan (PLAN, written before it trains), with stand-in parameters of
    their checkpoints' shapes (bc.stand_in_params): what compiles their programs while they train."""
    path, hashed, sel = spec.partition("#")
    terms = [s.strip() for s in sel.split("+") if s.strip()]
    if hashed and not terms:
        raise ValueError(f"{spec!r}: nothing follows '#'; name lineages, tasks or policies after it "
                         "(joined by +), or leave out the '#' for the whole zoo")
    wanted = {s for s in terms if not s.startswith("@")}
    file = registry_file(Path(path), PLAN if planned else REGISTRY)
    records = load_registry(Path(path), PLAN if planned else REGISTRY)
    known = {k for r in records for k in (r["name"], r["lineage"], r["task"])}
    unknown = sorted(wanted - known)
    if unknown:  # a misspelt term beside a right one would otherwise select fewer policies silently
        close = list(dict.fromkeys(c for t in unknown for c in difflib.get_close_matches(t, sorted(known), n=3)))
        raise ValueError(f"{spec!r}: {', '.join(map(repr, unknown))} names no policy, lineage or task of {file}"
                         + (f"; did you mean {' or '.join(close)}?" if close else "")
                         + f" (its lineages: {', '.join(sorted({r['lineage'] for r in records}))}; "
                         f"tasks: {', '.join(sorted({r['task'] for r in records}))})")
    chosen = [r for r in records if not wanted or wanted & {r["name"], r["lineage"], r["task"]}]
    for term in terms:
        if term.startswith("@"):
            chosen = every_nth_checkpoint(chosen, term, spec)
    if not chosen:
        raise ValueError(f"{spec!r} selects no policy; the registry has lineages "
                         f"{sorted({r['lineage'] for r in records})} and tasks {sorted({r['task'] for r in records})}")
    out = []
    for r in chosen:
        if not planned and not Path(r["checkpoint"]).is_file():
            raise FileNotFoundError(f"{file}: policy {r['name']!r}: its checkpoint {r['checkpoint']} is missing")
        policy, params = load_policy(r, stand_in_params(PolicyNetConfig(**r["net"]), r["variant"]["proprio"])
                                     if planned else None)
        out.append(PolicySource(name=r["name"], kind="learned", task=r["task"], policy=policy, params=params, record=r))
    if not planned:
        for group in group_by_policy(out):  # one trace per network and parameter shapes
            _check_checkpoint(file, group[0])
    return out


def _check_checkpoint(file: Path, source: PolicySource) -> None:
    """Traces a registry policy on a blank batch of 2 (trace_on_blank_batch), raising a ValueError naming
    the registry, the policy and its net where the checkpoint's parameters do not fit the network its
    record describes (another architecture or width): what would otherwise fail deep inside the
    evaluation's first rollout."""
    try:
        trace_on_blank_batch(source.policy, source.params, 2, source.record["net"].get("size", 64))
    except Exception as e:
        first = (str(e).splitlines() or [""])[0]
        raise ValueError(f"{file}: policy {source.name!r}: its checkpoint {source.record['checkpoint']} does not fit "
                         f"its net {source.record['net']} ({type(e).__name__}: {first})") from e


def every_nth_checkpoint(records: list[dict], term: str, spec: str = "") -> list[dict]:
    """The records a `@K/N` selector keeps: of each (task, lineage), sorted by training step, the
    K-th, (K+N)-th, ... checkpoints; in the registry's order."""
    try:
        k, n = (int(x) for x in term[1:].split("/"))
    except ValueError:
        raise ValueError(f"{spec or term!r}: a checkpoint selector is @K/N (every N-th from the K-th), "
                         f"got {term!r}") from None
    if not 0 <= k < n:
        raise ValueError(f"{spec or term!r}: @K/N needs 0 <= K < N, got {term!r}")
    groups: dict = {}
    for r in records:
        groups.setdefault((r["task"], r["lineage"]), []).append(r)
    keep = set()
    for group in groups.values():
        keep |= {r["name"] for r in sorted(group, key=lambda r: r.get("step") or 0)[k::n]}
    return [r for r in records if r["name"] in keep]


def resolve(specs, world_model: bool = True, planned: bool = False) -> list[PolicySource]:
    """Every policy the specs name (see the module doc), names unique; world_model: whether they will
    also run in a world model (load_plugin); planned: a zoo's checkpoints as its plan names them, with
    stand-in parameters (load_registry_sources)."""
    out, origin = [], {}
    for spec in (s.strip() for s in specs):  # "a, b" on a command line leaves a space before b
        if not spec:
            continue
        module_file = re.fullmatch(r"(?:[^=]*=)?(.+)\.py:(\w+)", spec)
        if module_file:
            module = module_file.group(1).replace("/", ".").replace("\\", ".")
            raise ValueError(f"{spec!r} names a file: name a plug-in by its module, importable from the working "
                             f"directory, as {module}:{module_file.group(2)}")
        called = re.fullmatch(r"(?:[^=:(]*=)?[\w.]+:\w+\(.*\)", spec)
        if called and not Path(spec.split("#")[0]).exists():
            raise ValueError(f"{spec!r}: a spec cannot pass arguments to a plug-in; write a function without "
                             "arguments in your module that calls it with them (or bind them with "
                             "functools.partial) and name that function")
        got = [load_plugin(spec, world_model)] if is_plugin(spec) else load_registry_sources(spec, planned)
        for source in got:
            origin.setdefault(source.name, []).append(spec)
        out += got
    names = [s.name for s in out]
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise ValueError("policy names repeat: " + "; ".join(f"{n!r} from {' and '.join(origin[n])}" for n in dup)
                         + "; give plug-ins distinct names with name=module:attribute, and select a zoo's policies "
                         "once (one spec per zoo, its selectors joined with +)")
    slugs = [s.slug for s in out]  # the names' file-name forms (episode files, videos)
    clash = sorted({n for s, n in zip(slugs, names) if slugs.count(s) > 1})
    if clash:
        raise ValueError(f"policy names {clash} differ only in punctuation, which file names drop; "
                         "rename them with name=module:attribute")
    return out


def registry_file(path, name: str = REGISTRY) -> Path:
    """The file a zoo spec's path names: a directory's (or a path without `.json`'s) file `name`
    (REGISTRY, or PLAN); the zoo's other file of the two where the path names one of them; else the
    path itself."""
    path = Path(path)
    if path.is_dir() or path.suffix != ".json":
        return path / name
    return path.with_name(name) if path.name in (REGISTRY, PLAN) else path


def load_registry(path: Path, name: str = REGISTRY) -> list[dict]:
    """The registry's records, each with `checkpoint` made absolute and the zoo's `data` directory.
    path: the registry file or its directory (registry_file: the file `name` there, REGISTRY or PLAN)."""
    path = registry_file(path, name)
    if not path.exists():
        if _names_a_module(str(path).removesuffix(f"/{name}")):
            raise ValueError(f"{str(path).removesuffix(f'/{name}')}: neither a zoo registry nor a plug-in (a "
                             "plug-in is package.module:attribute, the attribute a callable returning (policy, params))")
        raise FileNotFoundError(f"{path} is missing: " + ("train a zoo first (make policies)" if name == REGISTRY else
                                                          "the zoo has not started (it writes its plan first)"))
    registry = read_json(path, "a zoo registry lists its checkpoints; copy it again or retrain the zoo")
    records = registry.get("policies")
    if not isinstance(records, list):
        raise ValueError(f"{path}: a zoo registry is a JSON object whose \"policies\" lists one record per "
                         "checkpoint (and whose \"data\" names the dataset it learned from)")
    first = {}
    for i, r in enumerate(records):
        check_record(path, i, r)
        if r["name"] in first:
            raise ValueError(f"{path}: records {first[r['name']]} and {i} are both named {r['name']!r}; "
                             "a registry names each policy once")
        first[r["name"]] = i
    for r in records:
        r["checkpoint"] = str(path.parent / r["checkpoint"])
        r["data"] = registry.get("data")  # None: the zoo's dataset is not known (its seeds are not excluded)
    return records


# a registry record's required fields and their JSON types (zoo.py writes them, with step, variant, val_loss, ...)
RECORD_FIELDS = {"name": str, "task": str, "lineage": str, "checkpoint": str, "net": dict}


def check_record(path: Path, i: int, r) -> None:
    """Raises a ValueError naming the registry `path`, the record (its index and name) and the field,
    where record i lacks a required field (RECORD_FIELDS) or holds one of another type, names an unknown
    task, describes a network PolicyNetConfig refuses (an unknown field or encoder) or a degradation
    degrade_params refuses (an unknown knob, a level out of range), or names a lineage with "~" (a
    counterfactual family's mark) without a degradation."""
    named = f" ({r['name']!r})" if isinstance(r, dict) and isinstance(r.get("name"), str) else ""
    where = f"{path}: record {i}{named}"
    if not isinstance(r, dict):
        raise ValueError(f"{where} is not a JSON object")
    for field, kind in RECORD_FIELDS.items():
        if field not in r:
            raise ValueError(f"{where} lacks the field {field!r} (every record has {', '.join(RECORD_FIELDS)})")
        if not isinstance(r[field], kind):
            raise ValueError(f"{where}: {field!r} must be a {'JSON object' if kind is dict else kind.__name__}, "
                             f"got {r[field]!r}")
    if r["task"] not in TASK_NAMES:
        raise ValueError(f"{where}: unknown task {r['task']!r}; the tasks are {', '.join(TASK_NAMES)}")
    if "~" in r["lineage"] and r.get("degrade") is None:
        raise ValueError(f"{where}: '~' in the lineage {r['lineage']!r} marks a counterfactual family (a checkpoint "
                         "degraded by its 'degrade' knobs, which this record lacks); name the lineage without it")
    try:
        PolicyNetConfig(**r["net"]).validate()
    except (TypeError, ValueError) as e:
        raise ValueError(f"{where}: 'net' {r['net']} is not a policy network ({e}; its fields: "
                         f"{', '.join(f.name for f in dataclasses.fields(PolicyNetConfig))})") from None
    if r.get("degrade") is not None:
        if not isinstance(r["degrade"], dict):
            raise ValueError(f"{where}: 'degrade' must be a JSON object of knobs and levels, got {r['degrade']!r}")
        try:
            degrade_params(None, **r["degrade"])
        except (TypeError, ValueError) as e:
            raise ValueError(f"{where}: 'degrade' {r['degrade']}: {e}") from None


def _names_a_module(name: str) -> bool:
    """Whether name is a dotted Python name that imports (a plug-in spec without its `:attribute`)."""
    if not re.fullmatch(r"[A-Za-z_]\w*(\.[A-Za-z_]\w*)*", name):
        return False
    try:
        return importlib.util.find_spec(name) is not None
    except (ImportError, ValueError):
        return False


def load_policy(record: dict, params=None) -> tuple:
    """(policy, params) of one registry record: a BCPolicy, or for a family's record the
    DegradedPolicy around it; params: the network's parameters in place of its checkpoint's."""
    net = PolicyNetConfig(**record["net"])
    params = load_params(Path(record["checkpoint"])) if params is None else params
    if record.get("degrade"):
        return DegradedPolicy(BCPolicy(net)), degrade_params(params, **record["degrade"])
    return BCPolicy(net), params


# ---- where and how policies are run -------------------------------------------------------------

def stack_key(source: PolicySource) -> tuple:
    """What sources must share to run stacked (sim_data.policies.bc.stacked): one policy object and
    parameters of one structure, shapes and dtypes (an equal policy may take parameters of any size)."""
    leaves, tree = jax.tree_util.tree_flatten(source.params)
    return source.policy, tree, tuple((np.shape(x), str(getattr(x, "dtype", None) or np.asarray(x).dtype))
                                      for x in leaves)


def group_by_policy(sources):
    """Sources that run stacked (stack_key: and so one compiled rollout), in a fixed order."""
    groups: dict = {}
    for s in sources:
        groups.setdefault(stack_key(s), []).append(s)
    return list(groups.values())


def stacked_sources(sources) -> tuple:
    """(policy, params) running sources of one policy object side by side (sim_data.policies.bc.stacked),
    each salted by its name: a stochastic policy draws the same numbers whatever shares its batch."""
    return stacked(sources[0].policy, [s.params for s in sources], [s.salt for s in sources])


def policy_chunks(group, n: int, batch: int):
    """(policies, padded) chunks of at most batch // n policies, as even as possible (even_pieces), the
    last padded to the others' size by repeating its last policy: one batch shape, and fewer padded
    policies than chunks."""
    pieces, size = even_pieces(list(group), max(1, batch // n))
    for part in pieces:
        yield part, pad_with_last(part, size)


def used_seeds(*datasets) -> set:
    """Every initial-state seed in the manifests of the given dataset directories."""
    seeds = set()
    for d in datasets:
        manifest = Path(d) / "manifest.jsonl"
        if manifest.exists():
            seeds |= {json.loads(line)["seed"] for line in manifest.read_text().splitlines() if line}
    return seeds


SEEN_KINDS = ("learned", "plugin")  # the kinds of policy whose rollouts make an evaluated policy seen


def _seen_rows(datasets) -> list[dict]:
    rows = []
    for d in datasets:
        manifest = Path(d) / "manifest.jsonl"
        if manifest.exists():
            rows += [r for line in manifest.read_text().splitlines() if line
                     if (r := json.loads(line)).get("policy_kind") in SEEN_KINDS]
    return rows


def used_policies(*datasets) -> set:
    """The names of the learned policies and plug-ins whose rollouts are in the manifests of the given
    dataset directories (a world model trained on them has seen those policies act)."""
    return {r["policy"].split(":", 1)[1] for r in _seen_rows(datasets)}


def used_fingerprints(*datasets) -> set:
    """The fingerprints (what each computes) of the same policies, where the manifests record them: a
    policy evaluated under another name than its rollouts' is seen all the same."""
    return {r["policy_fingerprint"] for r in _seen_rows(datasets) if r.get("policy_fingerprint")}


def reset_keys_of(seeds) -> np.ndarray:
    """(n, 2) uint32: the reset keys of n initial-state seeds."""
    return np.stack([np.asarray(jax.random.PRNGKey(s)) for s in seeds])


def heldout_seeds(task: str, n: int, seed: int, used: set) -> list[int]:
    """n initial-state seeds of task that no training dataset used (a seed space of its own, with
    the rare collision skipped)."""
    out, i = [], 0
    while len(out) < n:
        digest = hashlib.sha256(f"heldout-eval/{seed}/{task}/{i}".encode()).digest()
        s = int.from_bytes(digest[:4], "little") & 0x7FFFFFFF
        if s not in used:
            out.append(s)
        i += 1
    return out
