"""Dataset generation: episodes of tasks x policies x seeds into MCAP files, a manifest and stats.

    python -m sim_data.dataset.generate --config smoke --out runs/data/smoke [key=value ...]
    make data CONFIG=demo OUT=runs/data/demo

Each episode is one MCAP file (`episodes/<episode_id>.mcap`); its channels and metadata record
are described in `sim_data.dataset.episodes`.

Episodes are written under a temporary name and renamed when whole, so a rerun of the same
command skips finished episodes and completes the dataset. `manifest.jsonl` (one line per
episode) and `stats.json` are rebuilt from the episode files at the end.
"""

from __future__ import annotations

import argparse
import concurrent.futures as cf
import dataclasses
import functools
import hashlib
import json
import math
import multiprocessing
import os
import shutil
import sys
import time
from pathlib import Path

import jax
import numpy as np
from tqdm import tqdm

from sim_data.config import as_json, preset_config, preset_help, save_or_check
from sim_data.dataset.cache import build_cache
from sim_data.dataset.episodes import (  # noqa: F401 (re-exported)
    CorruptEpisode,
    read_episode_meta,
    write_episode_mcap,
)
from sim_data.parts import add_part_argument, config_and_part, exclusive, take
from sim_data.policies.bc import stacked
from sim_data.policies.degrade import GOLDEN, perturbation
from sim_data.policies.registry import (
    PERTURBED,
    PLAN,
    SEEN_KINDS,
    PolicySource,
    fingerprint,
    is_plugin,
    perturbed_copy,
    registry_file,
    stack_key,
)
from sim_data.policies.registry import resolve as resolve_sources
from sim_data.policies.scripted import (
    PROGRAMS,
    ScriptOrProgramPolicy,
    action_program,
    pad_programs,
    play_params,
    program_params,
    script_or_program_params,
)
from sim_data.sim.engines import ENGINES, default_engine
from sim_data.sim.env import HomeEnv, cached_env
from sim_data.sim.render import CAMERAS, HEAD_CAMERA, cached_renderers
from sim_data.sim.robot import ACTION_DIM, FORWARD_SPEED, MAX_FORWARD_SPEED
from sim_data.sim.rollout import WARM_STEPS, record_episodes
from sim_data.sim.scene import load_model
from sim_data.sim.tasks import CONTROL_DT, MAX_EPISODE_STEPS, TASK_NAMES
from sim_data.util import (
    device_name,
    even_pieces,
    make_output_dir,
    package_versions,
    pad_with_last,
    read_json,
    run_cli,
    wait_for_files,
    wilson_interval,
    write_json_atomic,
)

SPLITS = ("train", "val", "test", "programs")
PLAY = "play"  # the source of random play episodes (sim_data.policies.scripted.play_program)
WEAK_GRIP = "weak_grip"  # the source of scripted episodes whose hand closes only part-way (DataConfig.weak_grip)
WEAK_GRIP_RANGE = (0.1, 0.7)  # the factors on a weak grip's closures
DRIVE = "drive"  # the source of episodes that back away for a set time (DataConfig.drive)
DRIVE_SECONDS = (0.0, 6.0)  # how long a drive episode backs away at the scripted 0.3 m/s: none to 1.8 m
DRIVE_SPEED = 0.3  # m/s: the scripted back-away's speed, a drive's unless it is varied
DRIVE_SEGMENT_SECONDS = (0.2, 1.0)  # a varied drive's segments of one speed
DRIVE_STOP_SHARE = 0.2  # of a varied drive's segments, those standing still
DRIVE_PROFILE_SEED = 7919  # the varied drives' profiles draw from (this, episode index)
SQRT2_FRACTION = math.sqrt(2) - 1  # picks the varied drives, a sequence unlike drive_seconds' GOLDEN
SOURCES_NAMED = (PLAY, WEAK_GRIP, DRIVE)  # sources that are their own policy name and kind


@dataclasses.dataclass(frozen=True)
class DataConfig:
    """What to generate.

    Attributes:
      tasks: task names. skills: scripted-policy skills (each a policy "scripted@<skill>").
      episodes: episodes per task and skill; episode i of a task starts from the same initial
        state (seed) at every skill.
      seed: the dataset's seed; initial-state seeds derive from (seed, task, i).
      engine: "cpu", "mjx" or "" (mjx where a GPU is present).
      size: frame height = width (64 or 128). cameras: cameras to record.
      heldout: scenes with the held-out plant.
      batch: episodes simulated together. val_frac, test_frac: shares of initial states per split.
      jpeg_quality: 1..100. workers: processes encoding and writing files.
      cache: build the training cache (sim_data.dataset.cache) at the end.
      programs: initial states per task (split "programs", never train/val/test) from which every
        action program of `sim_data.policies.scripted.PROGRAMS` is recorded: the world model's controllability set.
      play: episodes per task of random play (`sim_data.policies.scripted.play_program`, policy "play"), in
        train/val/test like the scripted ones: they show the world model what every action does.
      play_nod: the chance that a play episode's neck also nods or shakes at 0.5-2 Hz (play_program's
        nod), which the knots alone never do: a model that has not seen a fast neck draws the view of
        the controllability panel's `air_guitar` program still (docs/world-model.md).
      policies: policy specs (`sim_data.policies.registry`: zoo registries, plug-ins) whose own rollouts join
        the dataset, failures included; policy_episodes: episodes per policy and task (0: `episodes`),
        from the same initial states as the scripted episodes 0, 1, ...
      perturbed: registry specs whose checkpoints' perturbed copies (sim_data.policies.registry.perturbed_copy,
        policy "perturbed:<name>~perturbed") join the dataset, perturb_episodes episodes each (0:
        policy_episodes): from the same initial states as the checkpoint's own rollouts, each episode
        with one knob of sim_data.policies.degrade at its own level (noise, latency, a weak grip, a
        shortened or lengthened drive), so the world model sees the outcomes of actions a little off
        a policy's own. Keep the evaluation's counterfactual families' base lineage out of them.
      weak_grip: episodes per task of the scripted policy at skill 1 whose every closure is scaled by
        a factor spread over WEAK_GRIP_RANGE (weak_grip_factor), from the initial states of the
        scripted episodes 0, 1, ... (policy "weak_grip", in train/val/test): the scripted closures
        are 0 or 1, and these show what a hand closed part-way does to what it holds. They run in
        the chunks of the programs and play (on the GPU, in rows those chunks would pad) and are
        not scripted demonstrations (policy_kind "weak_grip"), so the zoo never learns from them.
      drive: episodes per task that hold the ready pose and back away at the scripted speed for a
        time spread over DRIVE_SECONDS (drive_seconds: from standing still to 1.8 m), from the initial
        states of the scripted episodes 0, 1, ... (policy "drive", in train/val/test; action tables,
        run with the programs). On step_back the scripted drives all stop near the band that succeeds,
        and a policy acting on imagined frames may stop short or drive on; on every other task no
        drive succeeds. So these show the world model and its judge what every distance does, and that
        backing away alone achieves nothing else. Not demonstrations (policy_kind "drive").
      drive_by_split: the drives' durations spread over each split's drives by their order among them
        (drive_of_split) rather than over all the drives by index, so that the training split holds the
        whole range of distances (by index, a split's few drives may all miss the longest ones).
      drive_varied: the share of the drives (drive_is_varied) that cover their distance at a varied speed
        instead (drive_profile: segments of random speeds and stops), so that the world model and its
        judge learn a distance as the sum of the speeds, not as a time at the scripted speed.
    """

    tasks: tuple = TASK_NAMES
    skills: tuple = (0.2, 0.6, 1.0)
    episodes: int = 8
    seed: int = 0
    engine: str = ""
    size: int = 64
    cameras: tuple = CAMERAS
    heldout: bool = False
    batch: int = 8
    val_frac: float = 0.1
    test_frac: float = 0.1
    jpeg_quality: int = 90
    workers: int = 2
    cache: bool = True
    programs: int = 0
    play: int = 0
    play_nod: float = 0.0
    policies: tuple = ()
    policy_episodes: int = 0
    weak_grip: int = 0
    drive: int = 0
    drive_by_split: bool = False
    drive_varied: float = 0.0
    perturbed: tuple = ()
    perturb_episodes: int = 0

    def validate(self) -> None:
        """Raises ValueError where a setting is out of range: no or unknown tasks, skills outside [0, 1], counts
        below their minimum, an unknown engine or camera, a size other than 64 or 128, val_frac and test_frac
        not summing below 1, or jpeg_quality outside 1..100."""
        bad = [t for t in self.tasks if t not in TASK_NAMES]
        if bad or not self.tasks:
            raise ValueError(f"tasks {bad or '(none)'} unknown; choose from {', '.join(TASK_NAMES)}")
        if not self.skills or any(not 0.0 <= float(s) <= 1.0 for s in self.skills):
            raise ValueError(f"skills must be in [0, 1], got {self.skills}")
        if len(set(self.tasks)) < len(self.tasks):
            raise ValueError(f"tasks names a task twice: {self.tasks}")
        if len({round(float(s) * 100) for s in self.skills}) < len(self.skills):  # episode_id's skill in percent
            raise ValueError(f"skills must differ by at least 0.01 (each names its episodes in percent), got {self.skills}")
        if self.episodes < 1 or self.batch < 1 or self.workers < 1:
            raise ValueError("episodes, batch and workers must be >= 1")
        if min(self.programs, self.play, self.policy_episodes, self.weak_grip, self.drive, self.perturb_episodes) < 0:
            raise ValueError("programs, play, policy_episodes, weak_grip, drive and perturb_episodes must be >= 0, "
                             f"got {self.programs}, {self.play}, {self.policy_episodes}, {self.weak_grip}, "
                             f"{self.drive}, {self.perturb_episodes}")
        if not 0.0 <= self.play_nod <= 1.0:
            raise ValueError(f"play_nod is a chance, in [0, 1]; got {self.play_nod}")
        if not 0.0 <= self.drive_varied <= 1.0:
            raise ValueError(f"drive_varied is a share of the drives, in [0, 1]; got {self.drive_varied}")
        if self.engine not in ("",) + ENGINES:
            raise ValueError(f"engine must be one of {ENGINES} or empty, got {self.engine!r}")
        if self.size not in (64, 128):
            raise ValueError(f"size must be 64 or 128, got {self.size}")
        if not self.cameras or any(c not in CAMERAS for c in self.cameras):
            raise ValueError(f"cameras must be among {CAMERAS}, got {self.cameras}")
        if not (0 <= self.val_frac < 1 and 0 <= self.test_frac < 1 and self.val_frac + self.test_frac < 1):
            raise ValueError("val_frac and test_frac must be in [0, 1) and sum below 1")
        if not 1 <= self.jpeg_quality <= 100:
            raise ValueError(f"jpeg_quality must be in 1..100, got {self.jpeg_quality}")


PRESETS = {
    "default": DataConfig(),
    "smoke": DataConfig(tasks=("mug",), skills=(1.0,), episodes=2, batch=2, programs=1),
    # the CPU chain's set: the demo zoo's two tasks, two skills, random play, the programs, head camera
    # 24 episodes a skill: about 18 demonstrations of skill 1.0 a task for the zoo, from which its
    # image-only lineages learn the mug (docs/results.md, the demo zoo); 16 drives a task, without which
    # the judge reads backing away, on either task, as a success (docs/world-model.md)
    "demo": DataConfig(tasks=("mug", "step_back"), skills=(0.3, 1.0), episodes=24, batch=8, programs=1, play=8,
                       drive=16, cameras=(HEAD_CAMERA,), test_frac=0.25),
    "full": DataConfig(skills=(0.0, 0.2, 0.4, 0.6, 0.8, 1.0), episodes=600, batch=1200, workers=12, programs=32),
    # the world model's and the zoo's GPU set: three tasks, a spread of skills (1.0 for the zoo's
    # demonstrations, 0.5 and 0.75 for its low-skill lineage), random play, the controllability programs,
    # head camera; about 611k frames, so that the data stage fits a 10-minute command on one GPU.
    # batch 960: per task 1x960 scripted, 1x368 program+play padded to 960 (one compiled rollout for both),
    # and the pipeline's rollouts (24 checkpoints x 32 episodes) padded to 960 (learned_slots): one batch
    # size, so that the programs that do not depend on the policy compile once; an H200 simulates 960
    # scripted rows a step in about 1.2 times the time of 480 (docs/benchmarks.md)
    "wm_full": DataConfig(tasks=("mug", "wipe", "airfryer"), skills=(0.0, 0.5, 0.75, 1.0), episodes=240, batch=960,
                          cameras=(HEAD_CAMERA,), workers=14, programs=32, play=240),
    # wm_full with 112 weak-grip episodes a task, in the rows of its program and play chunk (480 of
    # 960): the `full_grip` pipeline's world-model data
    "wm_full_grip": DataConfig(tasks=("mug", "wipe", "airfryer"), skills=(0.0, 0.5, 0.75, 1.0), episodes=240,
                               batch=960, cameras=(HEAD_CAMERA,), workers=14, programs=32, play=240, weak_grip=112),
    "heldout_plant": DataConfig(heldout=True, episodes=100, batch=600, workers=12),
    "shelf": DataConfig(tasks=("shelf",), skills=(0.0, 0.2, 0.4, 0.6, 0.8, 1.0), episodes=600, batch=1200, workers=12),
    "shelf_arcade": DataConfig(tasks=("shelf", "arcade"), skills=(0.0, 0.2, 0.4, 0.6, 0.8, 1.0), episodes=300,
                               batch=1200, workers=12),
    "airfryer": DataConfig(tasks=("airfryer",), skills=(0.0, 0.2, 0.4, 0.6, 0.8, 1.0), episodes=600, batch=1200,
                           workers=12),
}


def make_config(preset: str, overrides=()) -> DataConfig:
    """The preset with `key=value` overrides applied, validated."""
    return preset_config(PRESETS, preset, overrides)


# ---- episode identity ---------------------------------------------------------------------------

def initial_seed(cfg: DataConfig, task: str, i: int) -> int:
    """The initial-state seed of episode i of task (the same at every skill)."""
    digest = hashlib.sha256(f"{cfg.seed}/{task}/{i}/{cfg.heldout}".encode()).digest()
    return int.from_bytes(digest[:4], "little") & 0x7FFFFFFF


def split_of(cfg: DataConfig, seed: int) -> str:
    """train / val / test by initial-state seed, so no initial state is in two splits."""
    u = int.from_bytes(hashlib.sha256(f"split/{seed}".encode()).digest()[:4], "little") / 2**32
    return "test" if u < cfg.test_frac else "val" if u < cfg.test_frac + cfg.val_frac else "train"


def policy_name(source) -> str:
    """A source is a scripted skill (float), PLAY, WEAK_GRIP, DRIVE, an action program's name (str) or a
    PolicySource."""
    if isinstance(source, PolicySource):
        return f"{source.kind}:{source.name}"
    if source in SOURCES_NAMED:
        return source
    return f"program:{source}" if isinstance(source, str) else f"scripted@{float(source):.2f}"


def policy_kind(source) -> str:
    """The kind of a source (see policy_name) recorded with its episodes: a PolicySource's kind, PLAY, WEAK_GRIP
    or DRIVE itself, "program" for an action program, else "scripted"."""
    if isinstance(source, PolicySource):
        return source.kind
    return source if source in SOURCES_NAMED else "program" if isinstance(source, str) else "scripted"


def episode_id(task: str, source, i: int) -> str:
    """The id of episode i of task from source (see policy_name), unique within a dataset, e.g.
    "mug-s030-000004" for skill 0.3, "mug-play-000004", or "mug-l<slug>-000004" for a PolicySource."""
    if isinstance(source, PolicySource):
        return f"{task}-l{source.slug}-{i:06d}"
    if source == PLAY:
        return f"{task}-play-{i:06d}"
    if source == WEAK_GRIP:
        return f"{task}-weak-{i:06d}"
    if source == DRIVE:
        return f"{task}-drive-{i:06d}"
    if isinstance(source, str):
        return f"{task}-p{PROGRAMS.index(source)}{source}-{i:06d}"
    return f"{task}-s{round(float(source) * 100):03d}-{i:06d}"


def _initial_seed_of(cfg, task, source, i) -> int:
    if source in (WEAK_GRIP, DRIVE):  # the scripted episode i's initial state: the same start, other actions
        return initial_seed(cfg, task, i)
    if source == PLAY:
        return initial_seed(cfg, f"{task}/play", i)
    return initial_seed(cfg, f"{task}/programs" if isinstance(source, str) else task, i)


def _source_key(source) -> str:
    """The chunk seed's name of a source."""
    return source.name if isinstance(source, PolicySource) else str(source)


# ---- the run ------------------------------------------------------------------------------------

def _sources(cfg: DataConfig, task: str, learned=()) -> list:
    """[(source, episodes)] of task in the plan's order: the scripted skills, the programs, random
    play, the weak grips, the drives, then the PolicySources of `learned` (learned_sources(cfg)) that run on
    task."""
    sources = [(float(s), cfg.episodes) for s in cfg.skills] + [(p, cfg.programs) for p in PROGRAMS if cfg.programs]
    sources += [(PLAY, cfg.play)] if cfg.play else []
    sources += [(WEAK_GRIP, cfg.weak_grip)] if cfg.weak_grip else []
    sources += [(DRIVE, cfg.drive)] if cfg.drive else []
    own = cfg.policy_episodes or cfg.episodes
    return sources + [(src, cfg.perturb_episodes or own if src.kind == PERTURBED else own)
                      for src in learned if src.runs_on(task)]


def learned_sources(cfg: DataConfig, planned: bool = False) -> list:
    """The PolicySources whose rollouts the dataset holds: cfg.policies, then the perturbed copies of
    cfg.perturbed; planned: a zoo's as its plan names them, with stand-in parameters (warm)."""
    # the simulator alone runs them here: a plug-in may read its task state
    return (resolve_sources(cfg.policies, world_model=False, planned=planned)
            + [perturbed_copy(s) for s in resolve_sources(cfg.perturbed, world_model=False, planned=planned)])


def _episodes(cfg: DataConfig, learned=()):
    """Every episode of cfg's plan as (task, source, i), in the manifest's order."""
    for task in cfg.tasks:
        for source, n in _sources(cfg, task, learned):
            for i in range(n):
                yield task, source, i


@dataclasses.dataclass(frozen=True)
class Chunk:
    """Episodes of one task simulated as one batch by one compiled rollout.

    Attributes:
      task: the task. key: the rollout_key of every source in it.
      slots: ((source, (episode index, ...)), ...), in row order. A learned policy's chunk stacks one
        checkpoint's parameters per slot (StackedPolicy: slot k fills rows [k*width, (k+1)*width));
        the other chunks hold one episode a slot.
      width: rows a slot fills (1 for the scripted, program and play sources).
      size: the slots it is padded to (the `mjx` engine), the same for every chunk of its key in its
        task, and so in every task, and for the program and play sources that of the scripted ones
        (one compiled rollout serves them all).
    """

    task: str
    key: object
    slots: tuple
    width: int
    size: int

    @property
    def first(self) -> tuple:
        """(source, episode index) of the chunk's first row: what seeds its policy noise."""
        return self.slots[0][0], self.slots[0][1][0]

    def episode_ids(self) -> list[str]:
        return [episode_id(self.task, src, i) for src, idx in self.slots for i in idx]

    def rows(self, padded: bool) -> list:
        """[(source, episode index)] of the simulated batch (B = width * size padded, rows of the
        same slot consecutive): padded, each slot is filled to width by repeating its last episode
        and the slots to size by repeating the last slot, whose copies are simulated and discarded."""
        slots = [(src, list(idx)) for src, idx in self.slots]
        if padded:
            slots = pad_with_last([(src, pad_with_last(idx, self.width)) for src, idx in slots], self.size)
        return [(src, i) for src, idx in slots for i in idx]


def _task_chunks(task: str, key, group: list, batch: int) -> list[Chunk]:
    """The chunks of the sources `group` ([(source, episodes)]) of one rollout key in task, of at
    most `batch` rows each (even_pieces). The scripted, program and play sources' episodes are cut
    as one list of rows, skills or programs side by side in a chunk. A learned policy's checkpoints
    run whole, at most batch // n of them a chunk (StackedPolicy needs the same n episodes of each),
    or, where n > batch, each over several chunks of its own."""
    if not isinstance(group[0][0], PolicySource):
        rows = [(src, (i,)) for src, n in group for i in range(n)]
        pieces, size = even_pieces(rows, batch)
        return [Chunk(task, key, tuple(p), 1, size) for p in pieces]
    n = group[0][1]  # policy_episodes, the same for every learned source
    if n <= batch:
        pieces, size = even_pieces([(src, tuple(range(n))) for src, _ in group], batch // n)
        return [Chunk(task, key, tuple(p), n, size) for p in pieces]
    pieces, width = even_pieces(list(range(n)), batch)
    return [Chunk(task, key, ((src, tuple(p)),), width, 1) for src, _ in group for p in pieces]


def _plan(cfg: DataConfig, learned=()) -> list[Chunk]:
    """The chunks of work in a fixed order: per task, its sources grouped by rollout key (in the
    order of _sources), each key's rows cut into chunks of at most cfg.batch rows (_task_chunks).
    A task's learned sources are grouped by policy object; the scripted skills apart from the
    programs and play, though one ScriptOrProgramPolicy runs both: the programs and play are cut
    into chunks of at most the scripted chunks' size and padded to it, so that every chunk of them
    is one batch shape of one compiled rollout (on the `mjx` engine a compile costs far more than
    simulating the padding rows), and the scripted chunks, whose policy noise depends on their
    batch, are those they would be alone. A learned policy's chunks are padded with checkpoints to
    the scripted chunks' rows where whole checkpoints fill them (learned_slots): every chunk of the
    plan then has one batch size, whose programs that do not depend on the policy (the initial
    states, the physics' first positions, the observation) compile once for every rollout."""
    out = []
    for task in cfg.tasks:
        groups: dict = {}
        for source, n in _sources(cfg, task, learned):
            groups.setdefault(rollout_key(source), []).append((source, n))
        size = cfg.batch
        for key, group in groups.items():  # "scripted" first: _sources' order
            chunks = _task_chunks(task, key, group, size if key == "program" else cfg.batch)
            if key == "scripted":
                size = chunks[0].size
            if key == "program":
                chunks = [dataclasses.replace(c, size=size) for c in chunks]
            elif key != "scripted":
                chunks = [dataclasses.replace(c, size=learned_slots(c, size)) for c in chunks]
            out += chunks
    return out


def learned_slots(chunk: Chunk, rows: int) -> int:
    """The slots a learned policy's chunk is padded to: enough whole checkpoints (chunk.width rows
    each) to fill `rows` (the scripted chunks' batch) where they fill it exactly and the chunk's
    own slots fit, else the chunk's own."""
    if rows % chunk.width or rows // chunk.width < chunk.size:
        return chunk.size
    return rows // chunk.width


def rollout_key(source) -> object:
    """The group whose rows a task's chunks cut together: the scripted skills ("scripted"), the
    programs, random play, the weak grips and the drives ("program"), or a learned policy's
    checkpoints (stack_key: one policy object, one layout of parameters). The task is data in the
    rollout, so one compiled rollout serves a key in every task; the "scripted" and "program" groups share one too
    (ScriptOrProgramPolicy), and stay apart so that each chunk's rows, and with them the policy noise
    its rng draws, are its own."""
    if isinstance(source, PolicySource):
        return stack_key(source)
    return "program" if isinstance(source, str) else "scripted"


def staggered(chunks: list, key, keys: list, part: tuple[int, int] | None) -> list:
    """Chunks grouped by compiled rollout, in the order of `keys` (every chunk's key(chunk), in the
    whole plan's order), each key's chunks in their order, so that each rollout compiles and runs
    through every task at once; a part (K, N) starts K/N of the way through `keys`, so that the parts
    begin on different rollouts. The parts compile side by side, and with JAX's persistent
    compilation cache (experiments.pipeline sets one) a part that comes to a rollout another has
    compiled loads it instead."""
    shift = 0 if part is None else part[0] * len(keys) // part[1]
    rank = {k: (i - shift) % len(keys) for i, k in enumerate(keys)}
    return sorted(chunks, key=lambda c: rank[key(c)])


def _episode_meta(cfg, task, source, i, success, num_steps, engine):
    seed = _initial_seed_of(cfg, task, source, i)
    kind = policy_kind(source)
    program = kind == "program"
    return {
        "episode_id": episode_id(task, source, i), "task": task, "policy": policy_name(source),
        "policy_kind": kind, "skill": float(source) if kind == "scripted" else None,
        "seed": seed, "success": bool(success), "num_steps": int(num_steps),
        "split": "programs" if program else split_of(cfg, seed), "file": f"episodes/{episode_id(task, source, i)}.mcap",
        "engine": engine,
        "renderer": "sim_data.sim.render (JAX ray casting)", "heldout": cfg.heldout, "size": cfg.size,
        "cameras": list(cfg.cameras),
        "policy_source": source.record if isinstance(source, PolicySource) else None,
        "degrade": perturbation(i) if kind == PERTURBED else None,
    }


# settings that change which episodes a dataset holds but not the bytes of an episode both hold
_ADDITIONS = ("policies", "policy_episodes", "perturbed", "perturb_episodes", "drive", "workers")


def link_shared_episodes(cfg: DataConfig, out: Path, reuse: Path, learned=()) -> int:
    """Hard-links (or copies) into out the episode files of the dataset in `reuse` that cfg's plan
    also holds, so they are not simulated again; returns how many. The reused dataset's configuration
    must equal cfg apart from the learned policies and drives it adds (and the worker count): the same
    seeds then give the same bytes (a drive plays an action table, and a table's row gives the
    episode it gives alone), except beside weak-grip episodes, whose script draws its noise by their
    row in the chunk the drives share: there the drives must be the same too."""
    reuse = Path(reuse)
    if not (reuse / "config.json").exists():
        raise FileNotFoundError(f"{reuse} holds no dataset (config.json): generate it first")
    theirs = json.loads((reuse / "config.json").read_text())
    mine = json.loads(json.dumps(dataclasses.asdict(cfg)))
    additions = tuple(k for k in _ADDITIONS if not (k == "drive" and cfg.weak_grip))
    diff = sorted(k for k in mine if k not in additions and theirs.get(k) != mine[k])
    if diff:
        raise ValueError(f"{reuse} was generated with other settings ({diff}); its episodes cannot be reused")
    linked = 0
    for task, source, i in _episodes(cfg, learned):
        name = f"{episode_id(task, source, i)}.mcap"
        src, dst = reuse / "episodes" / name, out / "episodes" / name
        if dst.exists() or not src.exists():
            continue
        tmp = dst.with_name(name + ".tmp")
        try:
            os.link(src, tmp)
        except OSError:
            shutil.copyfile(src, tmp)
        os.replace(tmp, dst)
        linked += 1
    return linked


def generate(cfg: DataConfig, out: Path, progress: bool = True, reuse: Path | None = None,
             part: tuple[int, int] | None = None) -> dict | None:
    """Generates (or completes) the dataset of cfg in out; returns the stats written to stats.json.
    reuse: a dataset whose shared episodes are linked instead of simulated (link_shared_episodes).
    part: (K, N) simulates every N-th chunk from the K-th and returns None, leaving the manifest,
    the cache and stats.json to a run without a part (sim_data.parts: one process per GPU)."""
    cfg.validate()
    out = Path(out)
    make_output_dir(out / "episodes")
    engine = cfg.engine or default_engine()
    learned = learned_sources(cfg)
    with exclusive(out / "episodes.lock"):  # the parts of one dataset start together
        _check_config_matches(cfg, out)
        _check_sources_match(out, learned, engine, reuse)
        if part is None:  # (a part's writers may be busy with theirs)
            for stale in (out / "episodes").glob("*.tmp"):
                stale.unlink()  # a killed run's half-written file
        if reuse is not None:
            n = link_shared_episodes(cfg, out, reuse, learned)
            if progress:
                print(f"reused {n} episodes of {reuse}", file=sys.stderr)
    # a chunk with any episode missing is simulated whole (its batch fixes every episode's noise) and
    # only the missing episodes are written
    todo = [(chunk, {e for e in chunk.episode_ids() if not (out / "episodes" / f"{e}.mcap").exists()})
            for chunk in _plan(cfg, learned)]
    keys = list(dict.fromkeys(chunk.key for chunk, _ in todo))
    todo = [c for c in take(todo, part) if c[1]]  # a part's share of the whole plan, whatever is done
    todo = staggered(todo, lambda c: c[0].key, keys, part)
    total = sum(len(missing) for _, missing in todo)
    bar = tqdm(total=total, unit="ep", desc="episodes", disable=not progress or total == 0)
    t0, frames_done, steps_done = time.perf_counter(), 0, 0
    sim_s = wait_s = 0.0  # simulating and rendering (with the copy to the host); waiting on writers
    # worker processes: JSON and zstd hold the GIL, and the cpu engine's step loop needs it
    pool = cf.ProcessPoolExecutor(cfg.workers, mp_context=multiprocessing.get_context("spawn"))
    pending = []
    versions = package_versions()
    for chunk, missing in todo:
        ts = time.perf_counter()
        rows, rec = simulate_chunk(cfg, chunk, engine)
        sim_s += time.perf_counter() - ts
        submitted = _submit_episodes(pool, cfg, out, chunk.task, rows, rec, missing, engine, versions)
        pending += submitted
        steps_done += len(submitted) * (rec.action.shape[1] + 1)  # the episodes written, not the padding
        frames_done += len(submitted) * (rec.action.shape[1] + 1) * len(cfg.cameras)
        tw = time.perf_counter()
        pending = _drain(pending, bar, wait_all=False)
        while len(pending) > cfg.batch:  # at most one chunk waits for the writers while the next simulates
            pending = _drain(pending[:1], bar, wait_all=True) + pending[1:]
        wait_s += time.perf_counter() - tw
        dt = time.perf_counter() - t0
        bar.set_postfix(frames_per_s=f"{frames_done / dt:.0f}")
    tw = time.perf_counter()
    _drain(pending, bar, wait_all=True)
    wait_s += time.perf_counter() - tw
    pool.shutdown()
    bar.close()
    wall = time.perf_counter() - t0
    throughput = {"wall_s": wall, "episodes_generated": total, "steps_generated": steps_done,
                  "frames_generated": frames_done, "frames_per_s": frames_done / wall if total else None,
                  "episodes_per_s": total / wall if total else None, "engine": engine, "simulate_s": sim_s,
                  "wait_for_writers_s": wait_s, "workers": cfg.workers, "device": device_name()}
    parts_dir = out / "parts"
    if part is not None:  # what this part did, for the gathering run's stats.json
        parts_dir.mkdir(exist_ok=True)
        write_json_atomic(parts_dir / f"part-{part[0]}-of-{part[1]}.json", throughput)
        return None
    manifest = build_manifest(cfg, out, learned)
    if parts_dir.is_dir():
        throughput["parts"] = [json.loads(f.read_text()) for f in sorted(parts_dir.glob("part-*.json"))]
    stats = _stats(manifest, throughput)
    if cfg.cache:
        t1 = time.perf_counter()
        index = build_cache(out, workers=cfg.workers, progress=progress, reuse=reuse)
        stats["throughput"].update(cache_s=time.perf_counter() - t1, cache_frames=index["frames"])
    write_json_atomic(out / "stats.json", stats)
    return stats


def _submit_episodes(pool, cfg: DataConfig, out: Path, task: str, rows: list, rec, missing: set, engine: str,
                     versions: dict) -> list:
    """Hands the writers each episode of `missing` (ids) found in the simulated rows ([(source,
    episode index)], rec's (B, ...) leaves), from its first row: a padding copy comes after it.
    Returns the writers' futures, one per episode."""
    futures, seen = [], set()
    for row, (source, i) in enumerate(rows):
        eid = episode_id(task, source, i)
        if eid not in missing or eid in seen:
            continue
        seen.add(eid)
        ep = jax.tree_util.tree_map(lambda x, row=row: x[row], rec)
        meta = _episode_meta(cfg, task, source, i, ep.success[-1], ep.action.shape[0], engine)
        meta.update(config=dataclasses.asdict(cfg), versions=versions)
        episode = {"frames": ep.frames, "proprio": ep.proprio, "qpos": ep.qpos, "qvel": ep.qvel,
                   "mocap_pos": ep.mocap_pos, "success": ep.success, "progress": ep.progress, "action": ep.action}
        futures.append(pool.submit(write_episode_mcap, out / meta["file"], episode, meta, cfg.jpeg_quality))
    return futures


WARM_WAIT_S = 900  # for a zoo's plan, which it writes before training


def warm(cfg: DataConfig, wait_s: float = 0.0, progress: bool = True) -> None:
    """Runs one chunk of each compiled rollout of cfg's learned policies (cfg.policies and
    cfg.perturbed; per policy object and batch shape) for its first WARM_STEPS steps, so that JAX's
    persistent compilation cache holds the programs that generate then loads. A zoo's policies need
    only be planned (its plan.json, written before it trains: sim_data.policies.zoo): they run with
    stand-in parameters of their checkpoints' shapes, so the warm-up runs beside the zoo's training.
    Not warmed: on the `mjx` engine the joining of an episode's segments (`_recording_of`, a program
    per episode length, about a second each). wait_s: how long to wait for each zoo's plan. Writes
    nothing but the cache."""
    cfg.validate()
    specs = [s.strip() for s in (*cfg.policies, *cfg.perturbed)]
    plans = [registry_file(s.partition("#")[0], PLAN) for s in specs if s and not is_plugin(s)]
    wait_for_files(plans, wait_s, ", ".join(map(str, plans)))
    engine = cfg.engine or default_engine()
    learned = learned_sources(cfg, planned=True)
    # a module's private functions are shared as the jaxprs already traced in the process allow, so its
    # text (and its persistent-cache key) follows what the process traced before: the stand-ins'
    # initialisation is traced here and not in the rollouts' own process, which starts bare
    jax.clear_caches()
    t0, seen = time.perf_counter(), set()
    for chunk in _plan(cfg, learned):
        shape = (chunk.key, len(chunk.rows(padded=engine == "mjx")))
        if isinstance(chunk.key, str) or shape in seen:  # the scripted skills' and programs': the data's own
            continue
        seen.add(shape)
        simulate_chunk(cfg, chunk, engine, steps=WARM_STEPS)
    if progress:
        print(f"the rollouts' programs ran once in {time.perf_counter() - t0:.0f} s ({len(seen)} chunks)",
              file=sys.stderr)


def simulate_chunk(cfg: DataConfig, chunk: Chunk, engine: str, steps: int | None = None) -> tuple[list, object]:
    """Simulates and renders one chunk: ([(source, episode index)] of its B rows, the Recording
    with (B, ...) numpy leaves). With the `mjx` engine the chunk runs padded (Chunk.rows): one
    compilation then serves every chunk of a rollout key of that size in every task, and compiling,
    not simulating, is most of a chunk's time there. On the `cpu` engine only the chunks of programs
    and play are padded: their rows play tables and draw nothing from the batch's keys, so a padded
    chunk gives each row the episode it gives alone, and their chunks, shorter than the scripted
    ones, would otherwise compile the whole rollout again (about 40 s of the demo's 2 cores)."""
    rows = chunk.rows(padded=engine == "mjx" or _plays_tables(chunk))
    env = cached_env(chunk.task, len(rows), engine, cfg.heldout)
    policy, params = _policy_and_params(cfg, chunk, rows, env)
    reset_keys = jax.numpy.stack([jax.random.PRNGKey(_initial_seed_of(cfg, chunk.task, src, i)) for src, i in rows])
    source, i = chunk.first
    chunk_key = jax.random.PRNGKey(initial_seed(cfg, f"{chunk.task}/{_source_key(source)}", i))
    # the scripted skills' and programs' rollout is the data's own, which no warm-up compiles
    _, rec = record_episodes(env, policy, params, chunk_key, cached_renderers(cfg.size, tuple(cfg.cameras)),
                             reset_keys=reset_keys, steps=steps, compile_ahead=isinstance(chunk.key, str))
    return rows, jax.tree_util.tree_map(np.asarray, rec)


def _plays_tables(chunk: Chunk) -> bool:
    """Whether every row of chunk plays an action table (programs and random play; a weak grip runs
    the script, whose noise the batch's keys draw)."""
    return chunk.key == "program" and all(src != WEAK_GRIP for src, _ in chunk.slots)


def _policy_and_params(cfg: DataConfig, chunk: Chunk, rows: list, env: HomeEnv) -> tuple:
    """(policy, params) running the B rows ([(source, episode index)]) of chunk in env: for the
    scripted skills, the weak grips, the programs and random play one ScriptOrProgramPolicy, each row
    a skill and a grip (weak_grip_factor), or an action table (params {"program": (B,), "skill": (B,),
    "grip": (B,), "table": (B, MAX_EPISODE_STEPS, 20)}, one structure for every kind: one compiled
    rollout); or a policy's checkpoints stacked (one per slot of chunk.width rows)."""
    if isinstance(chunk.key, str):  # "scripted" or "program"
        program = [isinstance(src, str) and src != WEAK_GRIP for src, _ in rows]
        blank = np.zeros((env.episode_steps, ACTION_DIM), np.float32)  # a scripted row's table, never played
        table = np.stack([_program_table(cfg, chunk.task, src, i, env) if p else blank
                          for (src, i), p in zip(rows, program)])
        skill = [1.0 if isinstance(src, str) else float(src) for src, _ in rows]
        grip = [weak_grip_factor(i) if src == WEAK_GRIP else 1.0 for src, i in rows]
        params = pad_programs(script_or_program_params(skill, table, program, grip), MAX_EPISODE_STEPS)
        return _policy(), params
    slots = [rows[k:k + chunk.width] for k in range(0, len(rows), chunk.width)]
    return stacked(slots[0][0][0].policy, [slot[0][0].episodes_params([i for _, i in slot]) for slot in slots])


def weak_grip_factor(i: int) -> float:
    """The factor on the closures of weak-grip episode i: spread evenly over WEAK_GRIP_RANGE (a
    golden-ratio sequence), so that any first n episodes cover the range."""
    lo, hi = WEAK_GRIP_RANGE
    return lo + (hi - lo) * ((i * GOLDEN) % 1.0)


def drive_seconds(i: int) -> float:
    """How long drive episode i backs away: spread evenly over DRIVE_SECONDS (a golden-ratio sequence),
    so that any first n episodes cover the range."""
    lo, hi = DRIVE_SECONDS
    return lo + (hi - lo) * ((i * GOLDEN) % 1.0)


def drive_of_split(cfg: DataConfig, task: str, i: int) -> int:
    """Drive episode i's order among the drives 0..i of task in its split (that of the scripted episode i's
    initial state): with cfg.drive_by_split its duration is drive_seconds of this, else of i."""
    if not cfg.drive_by_split:
        return i
    split = lambda j: split_of(cfg, initial_seed(cfg, task, j))
    mine = split(i)
    return sum(split(j) == mine for j in range(i))


def drive_is_varied(i: int, share: float) -> bool:
    """Whether drive episode i covers its distance at a varied speed: a share of the drives, spread over
    their indices (and so over their distances) by a sequence other than drive_seconds'."""
    return ((i * SQRT2_FRACTION) % 1.0) < share


def drive_profile(i: int, seconds: float, num_steps: int) -> np.ndarray:
    """(num_steps,) float32 backward speeds (m/s, in [0, MAX_FORWARD_SPEED]) of varied drive episode i:
    segments of DRIVE_SEGMENT_SECONDS, a DRIVE_STOP_SHARE of them standing, the others at a uniform speed
    from 0.05 m/s to the top speed, until the base has been commanded the distance the scripted drive
    covers (DRIVE_SPEED for `seconds`, or to the episode's end; the last step's speed cut to land on it), then
    none. Where the draws would not cover it within num_steps, the moving segments are sped up (to at most the
    top speed), and the drive ends short only where all of them at the top speed would not cover it (and
    stands still in the rare draw where every segment within the episode stands)."""
    rng = np.random.default_rng([DRIVE_PROFILE_SEED, i])
    speeds = np.zeros(num_steps)
    t = 0
    while t < num_steps:
        n = max(1, round(rng.uniform(*DRIVE_SEGMENT_SECONDS) / CONTROL_DT))
        stop = rng.random() < DRIVE_STOP_SHARE
        speeds[t:t + n] = 0.0 if stop else rng.uniform(0.05, MAX_FORWARD_SPEED)
        t += n
    target = DRIVE_SPEED * CONTROL_DT * min(round(seconds / CONTROL_DT), num_steps)  # drive_table's own distance
    if 0.0 < speeds.sum() * CONTROL_DT < target:  # the least factor on the speeds (capped) that covers it
        covers = lambda c: np.minimum(speeds * c, MAX_FORWARD_SPEED).sum() * CONTROL_DT >= target
        lo, hi = 1.0, MAX_FORWARD_SPEED / speeds[speeds > 0].min()
        for _ in range(60):
            lo, hi = (lo, (lo + hi) / 2) if covers((lo + hi) / 2) else ((lo + hi) / 2, hi)
        speeds = np.minimum(speeds * hi, MAX_FORWARD_SPEED)
    done = np.cumsum(speeds) * CONTROL_DT
    k = int(np.searchsorted(done, target))  # the first step at which the distance is reached
    if k < num_steps:
        speeds[k] = (target - (done[k - 1] if k else 0.0)) / CONTROL_DT
        speeds[k + 1:] = 0.0
    return speeds.astype(np.float32)


def drive_table(seconds: float, num_steps: int, profile=None) -> np.ndarray:
    """(num_steps, 20) float32: the ready pose held while the base backs away at the scripted
    DRIVE_SPEED for `seconds`, then stands (the step_backwards program with its own duration); or, given
    a profile (num_steps,) of backward speeds (drive_profile), at those."""
    table = action_program("step_backwards", num_steps)
    if profile is None:
        profile = np.where(np.arange(num_steps) < round(seconds / CONTROL_DT), DRIVE_SPEED, 0.0)
    table[:, FORWARD_SPEED] = -np.asarray(profile, np.float32)
    return table


def _program_table(cfg: DataConfig, task: str, source: str, i: int, env: HomeEnv) -> np.ndarray:
    """The action table (env.episode_steps, 20) of a program episode (source: a program's name), of
    play episode i (source PLAY) or of drive episode i (DRIVE)."""
    if source == DRIVE:
        seconds = drive_seconds(drive_of_split(cfg, task, i))
        varied = drive_is_varied(i, cfg.drive_varied)
        return drive_table(seconds, env.episode_steps, drive_profile(i, seconds, env.episode_steps) if varied else None)
    if source == PLAY:
        seed = _initial_seed_of(cfg, task, source, i) + 1  # not the initial state's own seed
        return play_params([seed], env.episode_steps, env.idx.robot.action_low, env.idx.robot.action_high,
                           cfg.play_nod)["table"][0]
    return program_params([source], env.episode_steps)["table"][0]


@functools.cache
def _policy() -> ScriptOrProgramPolicy:
    return ScriptOrProgramPolicy.create(MAX_EPISODE_STEPS, model=load_model())


def _drain(pending, bar, wait_all: bool):
    left = []
    for fut in pending:
        if wait_all or fut.done():
            fut.result()  # re-raises a writer's error here
            bar.update(1)
        else:
            left.append(fut)
    return left


def _check_config_matches(cfg: DataConfig, out: Path) -> None:
    """Saves the resolved config on first use; refuses to mix a different one into the same directory."""
    # the writer processes change no episode's content: a rerun may use fewer (out of memory) or more
    save_or_check(out / "config.json", as_json(cfg), "a dataset", defaults=as_json(DataConfig()), ignore=("workers",))


SOURCES_FILE = "sources.json"  # the engine a dataset's episodes are simulated with and what its learned policies compute
# how its episodes record actions: as the robot applies them (robot.applied_action), where a dataset
# without this entry holds its learned policies' rollouts as the policies asked (a drive past the top
# speed); its scripted, program and play episodes are the same either way (their commands stay in range)
ACTIONS_RECORDED = "applied"


def _check_sources_match(out: Path, learned, engine: str, reuse: Path | None = None) -> None:
    """Saves the engine, how actions are recorded (ACTIONS_RECORDED) and each learned policy's
    fingerprint (registry.fingerprint) on first use; refuses a rerun, or a reused dataset, that would
    mix episodes of another engine, of actions recorded otherwise, or of policies that now compute
    otherwise (a zoo trained again at the same path, a plug-in's code changed): the config names
    the policies only by their specs, and a finished episode is kept as it is."""
    mine = {"engine": engine, "actions": ACTIONS_RECORDED, "policies": {s.name: fingerprint(s) for s in learned}}
    for d, what in ((out, "holds"), (reuse, "(reused) holds")):
        path = None if d is None else Path(d) / SOURCES_FILE
        if path is None or not path.exists():
            continue
        theirs = read_json(path)
        if theirs.get("actions") != ACTIONS_RECORDED and theirs["policies"]:  # scripted actions stay in range
            raise ValueError(f"{d} {what} rollouts whose actions are recorded as the policies asked for them, and "
                             "this version records them as the robot applies them (clipped to their ranges): "
                             "generate into another OUT, or remove this one (`make clean` removes the demo's)")
        if theirs["engine"] != engine:
            raise ValueError(f"{d} {what} episodes simulated with the {theirs['engine']} engine, and this run "
                             f"would use {engine}: set engine={theirs['engine']} or use another OUT")
        if d == out and theirs["policies"] != mine["policies"]:
            changed = sorted(n for n in theirs["policies"].keys() | mine["policies"].keys()
                             if theirs["policies"].get(n) != mine["policies"].get(n))
            raise ValueError(f"{d} holds rollouts of policies that now compute otherwise or are no longer "
                             f"named ({changed[:5]}{' ...' if len(changed) > 5 else ''}: a zoo trained again, "
                             "a plug-in's code changed); use another OUT")
    if not (out / SOURCES_FILE).exists():
        write_json_atomic(out / SOURCES_FILE, mine)


def build_manifest(cfg: DataConfig, out: Path, learned=()) -> list:
    """Writes manifest.jsonl from the episode files of cfg's plan (each read back); returns its rows."""
    keys = ("episode_id", "task", "policy", "policy_kind", "skill", "seed", "success", "num_steps", "split", "file",
            "engine", "renderer", "heldout")
    # what each policy computes (sources.json, written as the run began), so that an evaluation under
    # another name still counts it seen
    prints = read_json(out / SOURCES_FILE)["policies"]
    rows = []
    for task, source, i in _episodes(cfg, learned):
        meta = read_episode_meta(out / "episodes" / f"{episode_id(task, source, i)}.mcap")
        row = {k: meta[k] for k in keys}
        if policy_kind(source) in SEEN_KINDS:
            row["policy_fingerprint"] = prints[source.name]
        rows.append(row)
    tmp = out / f"manifest.jsonl.tmp{os.getpid()}"
    tmp.write_text("".join(json.dumps(r) + "\n" for r in rows))
    os.replace(tmp, out / "manifest.jsonl")
    return rows


def _stats(rows: list, throughput: dict) -> dict:
    groups = {}
    for r in rows:
        groups.setdefault((r["task"], r["policy"]), []).append(r)
    per = []
    for (task, policy), rs in sorted(groups.items()):
        k, n = sum(r["success"] for r in rs), len(rs)
        per.append({"task": task, "policy": policy, "episodes": n, "success_rate": k / n,
                    "success_ci95": list(wilson_interval(k, n)),
                    "splits": {s: sum(r["split"] == s for r in rs) for s in SPLITS}})
    return {"episodes": len(rows), "per_task_policy": per, "throughput": throughput}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter,
                                epilog=preset_help(PRESETS))
    p.add_argument("--config", default="demo", help=f"preset: {', '.join(PRESETS)}")
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--reuse", type=Path, help="a dataset of the same settings whose episodes are linked, not simulated "
                                              "again (to add policies' rollouts to a generated dataset)")
    add_part_argument(p, "simulate every N-th chunk", "gather the dataset")
    p.add_argument("--warm", action="store_true",
                   help="only run each compiled rollout of the learned policies once, the zoos' planned "
                        "checkpoints with stand-in parameters, so that the compilation cache holds them (warm)")
    p.add_argument("overrides", nargs="*", help="key=value overrides of the preset (e.g. episodes=16 tasks=mug,wipe)")
    a = p.parse_intermixed_args(argv)  # key=value overrides before or after the options
    cfg, part = config_and_part(p, a, make_config)
    if a.warm:
        if part is not None:
            p.error("--warm compiles for this process's device: leave out --part")
        warm(cfg, wait_s=WARM_WAIT_S)
        return 0
    stats = generate(cfg, a.out, reuse=a.reuse, part=part)
    if stats is None:
        print(f"part {a.part} done; run without --part to gather the dataset", file=sys.stderr)
        return 0
    print(json.dumps({"episodes": stats["episodes"], **stats["throughput"]}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(run_cli(main))
