"""Small helpers every package uses: atomic JSON files, the device's name, the Wilson interval, XLA's
flags and the parameter initialisers' compilation."""

from __future__ import annotations

import contextlib
import functools
import glob
import io
import json
import logging
import os
import re
import sys
import tarfile
import tempfile
import time
import zlib
from importlib import metadata as importlib_metadata
from pathlib import Path

import jax
import numpy as np
from jax._src import cache_key as jax_cache_key
from scipy import stats as sps


def write_json_atomic(path: Path, obj) -> None:
    """Writes obj as JSON to path through a temporary file and a rename (a reader never sees half a file)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + f".tmp{os.getpid()}")
    tmp.write_text(json.dumps(obj, indent=2, sort_keys=False) + "\n")
    os.replace(tmp, path)


def read_json(path: Path, hint: str = "the copy is damaged; copy it again", nan_as_none: bool = False) -> dict:
    """The JSON object in path; one that does not parse (truncated, half copied) or is not an object is
    refused with a ValueError naming the file and ending in hint. nan_as_none: NaN and Infinity tokens
    (json.dump's default for an undefined float) read as None."""
    try:
        d = json.loads(Path(path).read_text(), **({"parse_constant": lambda token: None} if nan_as_none else {}))
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise ValueError(f"{path} is not valid JSON ({e}): {hint}") from None
    if not isinstance(d, dict):
        raise ValueError(f"{path} is not a JSON object ({type(d).__name__}): {hint}")
    return d


def is_key_array(x) -> bool:
    """Whether x is an array of typed random keys (jax.random.key), whose bits numpy reads only through
    jax.random.key_data."""
    return isinstance(x, jax.Array) and jax.dtypes.issubdtype(x.dtype, jax.dtypes.prng_key)


def hash_arrays(h, tree) -> None:
    """Feeds every array leaf of tree (its shape, dtype and bytes, on the host; a typed key's
    implementation and key data) into the hashlib object h: a digest of parameters or constants
    that any process reproduces."""
    for leaf in jax.tree_util.tree_leaves(tree):
        if is_key_array(leaf):
            h.update(str(jax.random.key_impl(leaf)).encode())
            leaf = jax.random.key_data(leaf)
        a = np.ascontiguousarray(np.asarray(leaf))
        h.update(str((a.shape, a.dtype)).encode())
        h.update(a.tobytes())


def device_name() -> str:
    """The first JAX device's kind ("NVIDIA H200", "cpu")."""
    d = jax.devices()[0]
    return getattr(d, "device_kind", d.platform)


def wilson_interval(successes: int, n: int) -> tuple[float, float]:
    """95% Wilson score interval of a binomial proportion (scipy's); (0, 1) for n = 0."""
    if n == 0:
        return (0.0, 1.0)
    ci = sps.binomtest(int(successes), int(n)).proportion_ci(0.95, method="wilson")
    return (float(ci.low), float(ci.high))


# XLA's flags every command runs with, however it is started, unless the user set one either way.
# XLA:CPU's multi-threaded Eigen pool can wedge on large vmapped MJX graphs (idle, never returns), and
# its matrix products round differently with and without it (the ViT policies' weights differ in the
# seventh digit after 100 steps). On a GPU, XLA's default kernels (atomic scatters, autotuned
# algorithms) let the same closed-loop batch differ between two runs, even in one process, from the
# first step (sim_data.bench.determinism: 128 of 128 episodes on an H200); deterministic ops make them
# bit-identical, here at no cost to the rollout and 6% to the world model's train step (docs/benchmarks.md).
XLA_DEFAULT_FLAGS = {"--xla_cpu_multi_thread_eigen": "false", "--xla_gpu_deterministic_ops": "true"}


def with_xla_flags(base: str, flags: str, override: bool = False) -> str:
    """XLA_FLAGS `base` with `flags` ("--name=value ..."): each replaces a flag of the same name in base
    where override, else joins only where base does not name it (a user's choice stands)."""
    def name(flag):
        return flag.split("=")[0]

    new = flags.split()
    if override:
        names = {name(f) for f in new}
        return " ".join([f for f in base.split() if name(f) not in names] + new)
    named = {name(f) for f in base.split()}
    return " ".join(base.split() + [f for f in new if name(f) not in named])


def set_xla_flags() -> None:
    """Adds each of XLA_DEFAULT_FLAGS to XLA_FLAGS unless the user set it either way. XLA reads its
    flags when JAX's backend starts, so call it before the first computation."""
    defaults = " ".join(f"{flag}={value}" for flag, value in XLA_DEFAULT_FLAGS.items())
    os.environ["XLA_FLAGS"] = with_xla_flags(os.environ.get("XLA_FLAGS", ""), defaults)


# A parameter initialiser runs once a model, so its compile is all it costs: XLA:CPU at backend
# optimisation level 1 compiles the world model's and the policy networks' initialisers in a quarter
# to two thirds of the time, with the same parameters bit for bit (every preset's networks,
# docs/benchmarks.md). On a GPU machine the initialiser runs on its host CPU with these options too: the
# `full` world model's compiled for the GPU in 27-33 s, against 4.3 s on a 2-core CPU.
CPU_INIT_OPTIONS = {"xla_backend_optimization_level": 1}


def host_cpu():
    """This process's CPU device, or None where JAX was started without the CPU platform (JAX_PLATFORMS)."""
    try:
        return jax.local_devices(backend="cpu")[0]
    except RuntimeError:
        return None


def default_device():
    """The device a computation of this process lands on: jax_default_device where it is set (a device,
    or a platform's name: that platform's first device here), else the first of this process's devices."""
    chosen = jax.config.jax_default_device
    if isinstance(chosen, jax.Device):
        return chosen
    return jax.local_devices(backend=chosen)[0] if isinstance(chosen, str) else jax.local_devices()[0]


def jit_initialiser(fun, static_argnums=()):
    """fun (returning fresh parameters) jitted as one program, compiled with CPU_INIT_OPTIONS and run
    on the host's CPU when it is called outside a trace; on another default backend (a GPU) the
    parameters are then placed on its default device. Inside jit or eval_shape it is part of the
    enclosing program, whose options and device are its own."""
    on_cpu = jax.jit(fun, static_argnums=static_argnums, compiler_options=CPU_INIT_OPTIONS)
    elsewhere = jax.jit(fun, static_argnums=static_argnums)

    def traced(args) -> bool:
        return any(isinstance(x, jax.core.Tracer) for x in jax.tree_util.tree_leaves(args))

    @functools.wraps(fun)
    def init(*args):
        if traced(args):
            return elsewhere(*args)
        if jax.default_backend() == "cpu":
            return on_cpu(*args)
        cpu = host_cpu()
        if cpu is None:
            return elsewhere(*args)
        on_host = jax.tree_util.tree_map(lambda x: jax.device_put(x, cpu) if isinstance(x, jax.Array) else x, args)
        with jax.default_device(cpu):
            params = on_cpu(*on_host)
        return jax.device_put(params, default_device())

    return init


# where a command logs the parts of its persistent compilation cache keys (record_cache_keys), when set:
# the pipeline sets it for itself and every process it starts
CACHE_KEY_LOG_ENV = "WMLAB_CACHE_KEY_LOG"
# what JAX's key computation and its cache lookups log at DEBUG level
_KEY_LOGGERS = ("jax._src.cache_key", "jax._src.compiler")
_KEY_PART_RE = re.compile(r"get_cache_key hash of serialized (.+): ([0-9a-f]+)$")
_LOOKUP_RE = re.compile(r"persistent compilation cache (hit|miss) for '(.+)' with key '(.+)'$", re.IGNORECASE)


class _CacheKeyLog(logging.Filter):
    """A logger filter that appends the key parts and lookups JAX logs at DEBUG level to a file, and
    drops every DEBUG record of its logger, so that the level turned down prints nothing new."""

    def __init__(self, path: Path):
        super().__init__()
        self.path = Path(path)

    def filter(self, record: logging.LogRecord) -> bool:
        if record.levelno > logging.DEBUG:
            return True
        msg = record.getMessage()
        part, lookup = _KEY_PART_RE.search(msg), _LOOKUP_RE.search(msg)
        line = (f"part\t{part[1]}\t{part[2]}" if part else
                f"{lookup[1].lower()}\t{lookup[2]}\t{lookup[3]}" if lookup else None)
        if line is not None:
            with open(self.path, "a") as f:
                f.write(f"{os.getpid()}\t{line}\n")
        return False


def record_cache_keys(path: Path) -> None:
    """From now on appends each persistent compilation cache key this process computes, part by part
    (the program, jaxlib's version, the backend's, the XLA flags, the compile options, the accelerator,
    ...), and its lookup, hit or miss, to the log at path: tab-separated lines "pid part NAME HASH" and
    "pid hit|miss PROGRAM KEY" (experiments.cache_keys reads and compares two). Idempotent per path."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    for name in _KEY_LOGGERS:
        logger = logging.getLogger(name)
        if not any(isinstance(f, _CacheKeyLog) and f.path == path for f in logger.filters):
            logger.addFilter(_CacheKeyLog(path))
        logger.setLevel(logging.DEBUG)


# JAX's own accelerator part of the key (the devices' topology fingerprint); None in a JAX without it
_HASH_TOPOLOGY = getattr(jax_cache_key, "_hash_accelerator_config", None)


def _hash_device_kinds(hash_obj, accelerators, platforms: tuple[str, ...]) -> None:
    devices = np.asarray(accelerators)
    if all(d.platform in platforms for d in devices.flat):
        jax_cache_key._hash_devices(hash_obj, devices)
    else:  # a CPU's kind does not name its instruction set (AVX-512 or not): the host's topology does
        _HASH_TOPOLOGY(hash_obj, accelerators)


def key_cache_by_device_kind(platforms: tuple[str, ...] = ("gpu",)) -> None:
    """Keys JAX's persistent compilation cache on GPUs by the devices' kinds ("NVIDIA H100 80GB HBM3", one a
    device) instead of their topology's fingerprint, which also hashes details of the host: two machines
    with the same GPU then share a carried cache (between two H100 hosts every program's key differed in
    that part alone; experiments.cache_keys). A GPU's kind fixes the instruction set the programs are
    compiled for, and is what JAX itself hashes on a backend without a topology; devices of other
    platforms than `platforms` keep JAX's key. Idempotent; for this process only; a JAX whose key has no
    such part is left as it is."""
    if _HASH_TOPOLOGY is not None:
        jax_cache_key._hash_accelerator_config = functools.partial(_hash_device_kinds, platforms=tuple(platforms))


def run_cli(main) -> int:
    """Runs a command's main() for `python -m`, with XLA's flags set (set_xla_flags), the persistent
    compilation cache keyed by device kind where JAX_COMPILATION_CACHE_DIR turns it on
    (key_cache_by_device_kind), and, where CACHE_KEY_LOG_ENV names a log, its keys recorded there: a user's
    mistake (a bad path, preset, value, plug-in or selector, raised as FileNotFoundError,
    NotADirectoryError or ValueError with a message that names the input) ends in that one line and
    exit status 2, without a traceback."""
    set_xla_flags()
    if os.environ.get("JAX_COMPILATION_CACHE_DIR"):
        key_cache_by_device_kind()
    if os.environ.get(CACHE_KEY_LOG_ENV):
        record_cache_keys(Path(os.environ[CACHE_KEY_LOG_ENV]))
    try:
        return main()
    except (FileNotFoundError, NotADirectoryError, ValueError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2


def make_output_dir(path: Path) -> Path:
    """Creates the output directory `path` (and its parents); a file or a non-directory on the way is
    refused with a message naming it."""
    path = Path(path)
    for p in (path, *path.parents):
        if p.exists() and not p.is_dir():
            raise NotADirectoryError(f"the output {path} cannot be a directory: {p} is a file; name another path")
    path.mkdir(parents=True, exist_ok=True)
    return path


def even_pieces(items: list, most: int) -> tuple[list, int]:
    """items cut into the fewest consecutive pieces of at most `most`, all of one size but the last,
    which is shorter by less than the number of pieces: (pieces, size). Padding the last piece to
    size then costs fewer rows than the pieces, where pieces of `most` would pad up to most - 1."""
    count = -(-len(items) // most)
    size = -(-len(items) // count)
    return [items[k:k + size] for k in range(0, len(items), size)], size


def pad_with_last(items: list, size: int) -> list:
    """items filled to `size` by repeating the last one: a batch of one shape (one compiled program) whose
    copies are computed and dropped."""
    return list(items) + [items[-1]] * (size - len(items))


def wait_for_files(paths, wait_s: float, what: str) -> None:
    """Waits up to wait_s seconds (0: not at all) for every one of paths to exist, polling every 2 s,
    saying once on stderr that it waits for `what`; returns at the deadline whatever is missing (the
    caller's reading of them then says what is)."""
    paths = [Path(p) for p in paths]
    if not wait_s or all(p.exists() for p in paths):
        return
    print(f"waiting up to {wait_s:.0f} s for {what}", file=sys.stderr, flush=True)
    deadline = time.monotonic() + wait_s
    while not all(p.exists() for p in paths) and time.monotonic() < deadline:
        time.sleep(2.0)


def folder_list(src) -> list[Path]:
    """The folders src names: "A,B" (a command-line value; empty names dropped), one path, or several."""
    if isinstance(src, str):
        return [Path(d) for d in src.split(",") if d]
    return [Path(src)] if isinstance(src, Path) else [Path(d) for d in src]


@contextlib.contextmanager
def unpacked_tar(joined: bytes, tops, scratch: Path, where: str, broken: str):
    """The tar.gz bytes `joined` extracted into a temporary folder under scratch, yielded as (folder,
    members) and removed after. Refuses with a ValueError starting "where: " an archive holding anything
    but files and folders under the top-level names `tops` (or a ".."), and one that does not unpack
    (`broken`, with the reason)."""
    Path(scratch).mkdir(parents=True, exist_ok=True)
    try:
        with tarfile.open(fileobj=io.BytesIO(joined), mode="r:gz") as tar, \
                tempfile.TemporaryDirectory(dir=scratch) as unpacked:
            members = tar.getmembers()
            foreign = [m.name for m in members if Path(m.name).parts[:1] not in [(t,) for t in tops]
                       or ".." in Path(m.name).parts or not (m.isfile() or m.isdir())]
            if foreign:
                raise ValueError(f"{where}: the archive holds {foreign[:3]}, outside {', '.join(tops)}")
            tar.extractall(unpacked, filter="data")
            yield Path(unpacked), members
    except (tarfile.TarError, EOFError, zlib.error) as e:
        raise ValueError(f"{where}: {broken} ({e})") from e


def write_parts(whole: Path, dest: Path, stem: str, part_bytes: int) -> list[Path]:
    """The file `whole` cut into dest/<stem>00, 01, ... of at most part_bytes each (a lent GPU brings back
    files of <= 16 MiB), each written under a temporary name and renamed once whole, after the parts of
    stem that dest held are removed; returns them. On an error no part of stem is left in dest."""
    dest.mkdir(parents=True, exist_ok=True)

    def remove_parts():
        for old in [*dest.glob(glob.escape(stem) + "[0-9][0-9]"), *dest.glob(glob.escape(stem) + "[0-9][0-9].tmp")]:
            old.unlink(missing_ok=True)

    remove_parts()
    parts = []
    try:
        with open(whole, "rb") as f:
            for k in range(max(-(-Path(whole).stat().st_size // part_bytes), 1)):
                tmp = dest / f"{stem}{k:02d}.tmp"
                tmp.write_bytes(f.read(part_bytes))
                parts.append(tmp.replace(dest / f"{stem}{k:02d}"))
    except OSError:
        remove_parts()
        raise
    return parts


def join_parts(folders, stem: str, hint: str = "") -> tuple[bytes, list[Path]]:
    """(the bytes, the files) of write_parts' parts of stem found in folders (folder_list's: a lease
    carries a packing larger than one call's load in several calls, each its own folder), joined
    in order of their numbers. Raises FileNotFoundError where the folders hold none (hint appended to
    the message) and ValueError where their numbers are not 0..n-1 (one missing or given twice)."""
    folders = folder_list(folders)
    parts = sorted((p for d in folders for p in d.glob(f"{glob.escape(stem)}[0-9][0-9]")), key=lambda p: p.name)
    where = ", ".join(map(str, folders))
    if not parts:
        raise FileNotFoundError(f"{where} holds no {stem}NN" + (f": {hint}" if hint else ""))
    numbers = [int(p.name[len(stem):]) for p in parts]
    if numbers != list(range(len(parts))):
        raise ValueError(f"{where}: the {stem}NN parts are {numbers}, not 0..{len(parts) - 1}: one is missing or "
                         "given twice")
    return b"".join(p.read_bytes() for p in parts), parts


def package_versions(packages=("mujoco", "mujoco-mjx", "jax", "numpy", "opencv-python-headless", "mcap")) -> dict:
    """{package: installed version or "absent"}."""
    out = {}
    for pkg in packages:
        try:
            out[pkg] = importlib_metadata.version(pkg)
        except importlib_metadata.PackageNotFoundError:
            out[pkg] = "absent"
    return out
