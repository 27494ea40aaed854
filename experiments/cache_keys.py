"""Why a carried compilation cache missed: the parts of each program's persistent-cache key, logged and compared.

    python -m experiments.cache_keys A.log B.log     # which part of each program's key differs

JAX's persistent compilation cache keys a program by a hash of several parts (the canonical program,
the jaxlib version, the backend's version, the XLA flags, the compile options, the accelerator's
configuration, the compression, a custom hook). When a cache packed in one lease misses in the next
although the code did not change, the part whose hash moved says why. sim_data.util.record_cache_keys
writes every key's parts, and whether the cache held it, to a log as a process compiles; the pipeline
turns it on for itself and every process it starts (runs/logs/<chain>/cache_keys.log, collected with the
run), and `compare` lines up two such logs by program name.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from sim_data.util import run_cli


def read_cache_keys(path: Path) -> dict[str, dict]:
    """{program name: {"hit": bool, "key": str, "parts": {part name: hash}}} from a log of
    sim_data.util.record_cache_keys: each lookup takes the parts its process logged since its last
    lookup. A program looked up more than once (other shapes, other processes) keeps its first lookup
    under its name and the later ones under name#2, name#3, ... in the log's order."""
    pending, out = {}, {}
    for line in Path(path).read_text().splitlines():
        fields = line.split("\t")
        if len(fields) != 4:
            continue
        pid, kind, a, b = fields
        if kind == "part":
            pending.setdefault(pid, {})[a] = b
        elif kind in ("hit", "miss"):
            name, k = a, 2
            while name in out:
                name, k = f"{a}#{k}", k + 1
            out[name] = {"hit": kind == "hit", "key": b, "parts": pending.pop(pid, {})}
    return out


def compare(a: dict, b: dict) -> list[dict]:
    """For each program in both read_cache_keys dicts: {"program", "same_key", "differs": [the parts whose
    hashes differ]}; programs in one alone are left out."""
    rows = []
    for name in sorted(set(a) & set(b)):
        pa, pb = a[name]["parts"], b[name]["parts"]
        differs = [p for p in dict.fromkeys([*pa, *pb]) if pa.get(p) != pb.get(p)]
        rows.append({"program": name, "same_key": a[name]["key"] == b[name]["key"], "differs": differs})
    return rows


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("logs", nargs=2, type=Path, help="two logs of sim_data.util.record_cache_keys (runs/logs/<chain>/cache_keys.log)")
    a = ap.parse_args(argv)
    for p in a.logs:
        if not p.is_file():
            raise FileNotFoundError(f"{p} is not a file: the pipeline writes runs/logs/<chain>/cache_keys.log in each run")
    first, second = (read_cache_keys(p) for p in a.logs)
    rows = compare(first, second)
    if not rows:
        print("no program is in both logs")
    for r in rows:
        print(f"{r['program']:40s} {'same key' if r['same_key'] else 'differs: ' + ', '.join(r['differs'])}")
    print(f"{sum(r['same_key'] for r in rows)} of {len(rows)} programs in both logs have the same key; "
          f"{len(set(first) - set(second))} in the first alone, {len(set(second) - set(first))} in the second alone")
    return 0


if __name__ == "__main__":
    run_cli(main)
