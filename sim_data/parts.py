"""A long job spread over the GPUs of one host, one process per GPU.

The data generator, the zoo and the evaluator take `--part K/N`: that process does every N-th piece
of the work (chunks of episodes, lineages, tasks) from the K-th, saves each piece as the whole job
would, and stops without gathering. A last run of the same command without `--part` then finds
every piece done and gathers them (manifest and cache, registry, results). `run_parallel` starts
the processes, one per GPU (`CUDA_VISIBLE_DEVICES`) or, on a host without one, one per CPU core
(pinned there with `taskset`, so that XLA sizes its thread pool to that core), and fails naming the
first that failed and the tail of its log.
"""

from __future__ import annotations

import contextlib
import fcntl
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path


@contextlib.contextmanager
def exclusive(lock: Path, wait: bool = True):
    """Holds an exclusive lock on the file `lock` (created if missing) across processes, yielding
    True; with wait=False, where another holds it, yields False at once instead of waiting."""
    with open(lock, "a") as f:
        try:
            fcntl.flock(f, fcntl.LOCK_EX | (0 if wait else fcntl.LOCK_NB))
        except BlockingIOError:
            yield False
            return
        try:
            yield True
        finally:
            fcntl.flock(f, fcntl.LOCK_UN)


def in_turn(items, attempt) -> list:
    """attempt(item, wait) for every item, results in items' order, taking first whatever no other
    process holds: each pass tries every pending item with wait=False (attempt returns None where
    another process holds it), and a pass that finished none waits for the first pending item
    (wait=True: attempt must then return its result). Processes working through the same items
    with locks per item so share them out instead of queueing behind one another."""
    out = [None] * len(items)
    pending = list(range(len(items)))
    while pending:
        left = []
        for i in pending:
            got = attempt(items[i], False)
            if got is None:
                left.append(i)
            else:
                out[i] = got
        if left and len(left) == len(pending):
            i = left.pop(0)
            out[i] = attempt(items[i], True)
        pending = left
    return out


def parse_part(text: str | None) -> tuple[int, int] | None:
    """'K/N' -> (K, N) with 0 <= K < N; None stays None."""
    if text is None:
        return None
    try:
        k, n = (int(x) for x in text.split("/"))
    except ValueError:
        raise ValueError(f"--part takes K/N (this process's index and the number of processes), got {text!r}") from None
    if not 0 <= k < n:
        raise ValueError(f"--part K/N needs 0 <= K < N, got {text!r}")
    return k, n


def config_and_part(parser, args, make_config) -> tuple:
    """(make_config(args.config, args.overrides), parse_part(args.part)) of a module's parsed
    arguments; a bad preset, override or part ends in parser.error, naming it."""
    try:
        return make_config(args.config, args.overrides), parse_part(args.part)
    except ValueError as e:
        parser.error(str(e))


def add_part_argument(parser, pieces: str, gather: str) -> None:
    """The `--part K/N` option of a module that spreads its `pieces` over processes and, run
    without it, does `gather`; read it with parse_part."""
    parser.add_argument("--part", help=f"K/N: {pieces} from the K-th and stop (one process per GPU; then run "
                                       f"without --part to {gather}: sim_data.parts)")


def take(items, part: tuple[int, int] | None) -> list:
    """The items of this part (every N-th from the K-th), or all of them without a part."""
    items = list(items)
    return items if part is None else items[part[0]::part[1]]


def local_gpus() -> list[str]:
    """The ids of this host's GPUs that a child process may be given (CUDA_VISIBLE_DEVICES where set,
    else nvidia-smi's list); [] without a GPU."""
    visible = os.environ.get("CUDA_VISIBLE_DEVICES")
    if visible is not None:
        return [g for g in visible.split(",") if g.strip() and g.strip() != "-1"]
    if shutil.which("nvidia-smi") is None:
        return []
    try:
        out = subprocess.run(["nvidia-smi", "-L"], capture_output=True, text=True, timeout=30).stdout
    except (OSError, subprocess.TimeoutExpired):
        return []
    return [str(i) for i, line in enumerate(out.splitlines()) if line.startswith("GPU ")]


def local_cores() -> list[str]:
    """The ids of the CPU cores this process may run on (its affinity), as strings."""
    if hasattr(os, "sched_getaffinity"):
        return [str(c) for c in sorted(os.sched_getaffinity(0))]
    return [str(c) for c in range(os.cpu_count() or 1)]


def can_pin_cores() -> bool:
    """Whether child processes can be pinned to a core each (the `taskset` command): unpinned, each JAX
    process would size its thread pool to every core and they would crowd one another."""
    return shutil.which("taskset") is not None


def on_slot(cmd: list[str], slot: str, on: str) -> tuple[list[str], dict]:
    """(argv, environment) of cmd run on one slot: a GPU's id (`on="gpu"`: CUDA_VISIBLE_DEVICES) or a
    CPU core's (`on="cpu"`: pinned by taskset; the child sees no GPU)."""
    if on == "gpu":
        return cmd, {**os.environ, "CUDA_VISIBLE_DEVICES": slot}
    if on != "cpu":
        raise ValueError(f"run_parallel runs on 'gpu' or 'cpu' slots, not {on!r}")
    if not can_pin_cores():
        raise RuntimeError("pinning a process to a CPU core needs the taskset command (util-linux)")
    return ["taskset", "-c", slot, *cmd], {**os.environ, "CUDA_VISIBLE_DEVICES": ""}


def run_parallel(commands: list[list[str]], slots: list[str], logs: Path, label: str = "part", on: str = "gpu") -> None:
    """Runs each command (an argv) in a child process given one of `slots` (GPU ids, or CPU core
    ids with on="cpu": on_slot), at most one per slot at a time, in order. The first child writes to
    this terminal; the others to logs/<label>-<i>.log. Raises RuntimeError with a log's tail if any
    fails (after the others end)."""
    if not slots:
        raise ValueError(f"run_parallel needs at least one {'GPU' if on == 'gpu' else 'core'}")
    logs.mkdir(parents=True, exist_ok=True)
    waiting = list(enumerate(commands))
    running: dict[str, tuple] = {}
    failed = []
    while waiting or running:
        for slot in [g for g in slots if g not in running]:
            if not waiting:
                break
            i, cmd = waiting.pop(0)
            log = logs / f"{label}-{i}.log"
            out = None if i == 0 else open(log, "w")
            argv, env = on_slot(cmd, slot, on)
            running[slot] = (i, subprocess.Popen(argv, env=env, stdout=out, stderr=subprocess.STDOUT if out else None),
                             out, log)
            print(f"{label} {i} on {'GPU' if on == 'gpu' else 'core'} {slot}" + (f" (log {log})" if out else ""),
                  file=sys.stderr, flush=True)
        time.sleep(1.0)
        for slot, (i, proc, out, log) in list(running.items()):
            if proc.poll() is None:
                continue
            del running[slot]
            if out is not None:
                out.close()
            if proc.returncode:
                failed.append((i, proc.returncode, log if out is not None else None))
    if failed:
        i, rc, log = failed[0]
        tail = "\n".join(log.read_text().splitlines()[-30:]) if log is not None else "(its output is above)"
        raise RuntimeError(f"{len(failed)} of {len(commands)} processes failed; {label} {i} exited with {rc}:\n{tail}")
