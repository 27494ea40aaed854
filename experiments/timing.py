"""Where a stage's time goes: JAX's compile events counted per process, and the pipeline's timing table.

    python -m experiments.timing OUT.json MODULE [ARGS...]   # runs MODULE's main(ARGS), writes its timing

Importing this module registers a listener on JAX's compile events (tracing, lowering to MLIR, the
backend's compilation), so every program this process compiles afterwards is counted, by name. The
pipeline runs a stage spread over several GPUs as child processes through the command above: each
child writes its own wall and compile seconds to OUT.json (`part_row`), and the stage's row in the
timing table (`stage_row`) joins them to the pipeline process's own, so a spread stage's compiling is
counted where it happens.
"""

from __future__ import annotations

import importlib
import json
import re
import sys
import time
from pathlib import Path

import jax

from sim_data.util import device_name, run_cli, write_json_atomic

# JAX's compile events (jax.monitoring): tracing, lowering to MLIR and the backend's compilation
COMPILE_EVENTS = ("/jax/core/compile/jaxpr_trace_duration", "/jax/core/compile/jaxpr_to_mlir_module_duration",
                  "/jax/core/compile/backend_compile_duration")
SLOWEST_COMPILES = 8  # a timing row names the programs that cost the most compile time
# the persistent compilation cache's events: a lookup, and a lookup that found the program compiled
CACHE_EVENTS = {"/jax/compilation_cache/compile_requests_use_cache": "cache_lookups",
                "/jax/compilation_cache/cache_hits": "cache_hits"}
# by_program: function name -> [compiles, seconds]
_compile = {"seconds": 0.0, "programs": 0, "by_program": {}, "cache_lookups": 0, "cache_hits": 0}


def _count_compile(event: str, seconds: float, fun_name: str = "?", **_) -> None:
    if event in COMPILE_EVENTS:
        last = event == COMPILE_EVENTS[-1]
        _compile["seconds"] += seconds
        _compile["programs"] += last
        count = _compile["by_program"].setdefault(_program_name(fun_name), [0, 0.0])
        count[0] += last
        count[1] += seconds


def _program_name(fun_name: str) -> str:
    """The traced function's name: lowering and compile events name it "jit(name)", tracing "name"."""
    m = re.fullmatch(r"(?:jit|pjit|pmap)\((.*)\)", fun_name)
    return m.group(1) if m else fun_name


def _count_cache(event: str, **_) -> None:
    if event in CACHE_EVENTS:
        _compile[CACHE_EVENTS[event]] += 1


jax.monitoring.register_event_duration_secs_listener(_count_compile)
jax.monitoring.register_event_listener(_count_cache)


def compile_snapshot() -> dict:
    """A copy of this process's compile totals so far, for `compiled_since`."""
    return {**_compile, "by_program": {k: list(v) for k, v in _compile["by_program"].items()}}


def slowest_compiles(before: dict, n: int = SLOWEST_COMPILES) -> list[dict]:
    """The n programs (jitted functions, by name) that spent the most seconds in tracing, lowering and
    the backend's compilation since the snapshot `before`: [{"program", "compiles", "s"}], slowest first."""
    rows = []
    for name, (count, secs) in _compile["by_program"].items():
        c0, s0 = before["by_program"].get(name, (0, 0.0))
        if secs > s0:
            rows.append({"program": name, "compiles": count - c0, "s": round(secs - s0, 3)})
    return sorted(rows, key=lambda r: -r["s"])[:n]


def compiled_since(before: dict) -> dict:
    """This process's compiling since the snapshot `before`: {"compile_s", "programs_compiled",
    "slowest_compiles", "cache_hits", "cache_misses"} (the programs the persistent compilation cache
    served and those it did not: a carried cache that misses shows here)."""
    hits = _compile["cache_hits"] - before["cache_hits"]
    return {"compile_s": round(_compile["seconds"] - before["seconds"], 3),
            "programs_compiled": _compile["programs"] - before["programs"],
            "slowest_compiles": slowest_compiles(before), "cache_hits": hits,
            "cache_misses": _compile["cache_lookups"] - before["cache_lookups"] - hits}


def record_timing(path: Path, row: dict) -> None:
    """Appends one stage command's row to the timing table at path (a JSON list, rewritten atomically)."""
    path = Path(path)
    rows = json.loads(path.read_text()) if path.exists() else []
    write_json_atomic(path, [*rows, row])


def part_command(out: Path, module: str, args) -> list[str]:
    """The argv that runs `module`'s main(args) in a child process that writes its timing to out."""
    return [sys.executable, "-m", "experiments.timing", str(out), module, *[str(a) for a in args]]


def read_parts(paths) -> list[dict]:
    """The part rows (part_row) that the child processes wrote, in order; a missing file (a child that
    never started, or one that failed before writing) is left out."""
    return [json.loads(Path(p).read_text()) for p in paths if Path(p).exists()]


def stage_row(own: dict, parts: list[dict]) -> dict:
    """A stage command's compile figures from this process's (compiled_since) and its child processes'
    rows: compile_s is this process's plus the most any one child spent (the children run side by
    side, so that is what compiling added to the stage's wall time); programs_compiled and the cache's
    hits and misses count every process's; slowest_compiles merges them (a child's entries name their
    part); parts keeps each child's wall and compile seconds."""
    if not parts:
        return own
    merged = own["slowest_compiles"] + [{**c, "part": k} for k, p in enumerate(parts) for c in p["slowest_compiles"]]
    return {"compile_s": round(own["compile_s"] + max(p["compile_s"] for p in parts), 3),
            "programs_compiled": own["programs_compiled"] + sum(p["programs_compiled"] for p in parts),
            **{k: own.get(k, 0) + sum(p.get(k, 0) for p in parts) for k in ("cache_hits", "cache_misses")},
            "slowest_compiles": sorted(merged, key=lambda c: -c["s"])[:SLOWEST_COMPILES],
            "parts": [{"part": k, "wall_s": p["wall_s"], "compile_s": p["compile_s"],
                       "programs_compiled": p["programs_compiled"]} for k, p in enumerate(parts)]}


def part_row(out: Path, module: str, args) -> int:
    """Runs `module`'s main(args) in this process and writes {"module", "wall_s", "compile_s",
    "programs_compiled", "slowest_compiles", "device", "status"} to out (also when main fails);
    returns main's exit status."""
    before, t0 = compile_snapshot(), time.perf_counter()
    status = 1
    try:
        status = run_cli(lambda: importlib.import_module(module).main(list(args))) or 0
    finally:
        write_json_atomic(Path(out), {"module": module, "wall_s": round(time.perf_counter() - t0, 3),
                                      **compiled_since(before), "device": device_name(), "status": status})
    return status


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    if len(argv) < 2:
        print("usage: python -m experiments.timing OUT.json MODULE [ARGS...]", file=sys.stderr)
        return 2
    return part_row(Path(argv[0]), argv[1], argv[2:])


if __name__ == "__main__":
    sys.exit(main())
