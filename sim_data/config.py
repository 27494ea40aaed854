"""Configuration helpers shared by every preset-driven command: dotted `key=value` overrides of
frozen dataclasses (nested ones included), parsed to the type of the field they replace."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

from sim_data.util import write_json_atomic


def parse_value(current, text: str, name: str):
    """text parsed to the type of the setting's current value: a comma list for a tuple (each item of the type of
    its first element, str if empty), true/false/1/0 for a bool, else the type's constructor; raises ValueError
    naming the setting `name` where it does not parse."""
    kind = type(current)
    if kind is tuple:
        items = [x for x in text.split(",") if x]
        elem = type(current[0]) if current else str
        return tuple(elem(x) for x in items)
    if kind is bool:
        if text.lower() not in ("true", "false", "1", "0"):
            raise ValueError(f"{name} must be true or false, got {text!r}")
        return text.lower() in ("true", "1")
    try:
        return kind(text)
    except ValueError:
        raise ValueError(f"{name} must be a {kind.__name__}, got {text!r}") from None


def override(cfg, items):
    """cfg with dotted `key=value` items applied (e.g. `model.dim=256`, `batch=32`)."""
    for item in items:
        key, sep, value = item.partition("=")
        if not sep:
            raise ValueError(f"override {item!r} must be key=value")
        cfg = _set(cfg, key.split("."), value, key)
    return cfg


def _set(obj, path, value, full):
    names = {f.name for f in dataclasses.fields(obj)}
    if path[0] not in names:
        raise ValueError(f"unknown setting {full!r}; {type(obj).__name__} has {', '.join(sorted(names))}")
    cur = getattr(obj, path[0])
    new = _set(cur, path[1:], value, full) if len(path) > 1 else parse_value(cur, value, full)
    return dataclasses.replace(obj, **{path[0]: new})


def preset_config(presets: dict, preset: str, overrides=()):
    """presets[preset] with dotted `key=value` overrides applied and validated (its `validate()`);
    an unknown preset names the known ones."""
    if preset not in presets:
        raise ValueError(f"unknown preset {preset!r}; choose from {', '.join(presets)}")
    cfg = override(presets[preset], overrides)
    cfg.validate()
    return cfg


def flat_settings(cfg, prefix: str = "") -> list:
    """[(dotted key, value)] of a dataclass's settings, nested dataclasses' included."""
    out = []
    for f in dataclasses.fields(cfg):
        value = getattr(cfg, f.name)
        if dataclasses.is_dataclass(value):
            out += flat_settings(value, f"{prefix}{f.name}.")
        else:
            out.append((f"{prefix}{f.name}", value))
    return out


def _show(value) -> str:
    return ",".join(map(str, value)) if isinstance(value, tuple) else str(value)


def preset_help(presets: dict) -> str:
    """The epilog of a preset-driven command's --help: its presets and every key a `key=value`
    override may set, with its value in each preset (one value where they agree)."""
    names = list(presets)
    values = {n: dict(flat_settings(presets[n])) for n in names}
    lines = [f"presets (--config): {', '.join(names)}. Settings, as key=value overrides, with each preset's value:"]
    for key, _ in flat_settings(presets[names[0]]):
        each = [values[n][key] for n in names]
        shown = _show(each[0]) if all(v == each[0] for v in each) else \
            "; ".join(f"{n}: {_show(v)}" for n, v in zip(names, each))
        lines.append(f"  {key} = {shown}")
    return "\n".join(lines)


def as_json(obj):
    """A config dataclass, or a dict or list holding them, as the plain JSON values config.json stores
    (tuples as lists)."""
    def plain(o):
        if dataclasses.is_dataclass(o) and not isinstance(o, type):
            return dataclasses.asdict(o)
        raise TypeError(f"{type(o).__name__} is not JSON")
    return json.loads(json.dumps(obj, default=plain))


def differing_fields(saved: dict, mine: dict, defaults: dict | None = None, prefix: str = "") -> list[str]:
    """The dotted names of the fields where a saved configuration differs from mine (both as_json).
    A field mine has and saved lacks takes its value from defaults (mine's layout, every field at its
    default): a configuration written before the field existed ran with its default."""
    out = []
    for k in sorted(saved.keys() | mine.keys()):
        default = (defaults or {}).get(k)
        theirs, ours = saved[k] if k in saved else default, mine.get(k)
        if isinstance(theirs, dict) and isinstance(ours, dict):
            out += differing_fields(theirs, ours, default if isinstance(default, dict) else None, f"{prefix}{k}.")
        elif theirs != ours:
            out.append(prefix + k)
    return out


def save_or_check(path: Path, mine: dict, what: str, defaults: dict | None = None, ignore: tuple = ()) -> None:
    """Saves the configuration `mine` (as_json) to path (config.json) on first use; on a rerun refuses one
    that differs from the saved one in any field but those named in `ignore` (dotted names of settings
    such as a safety time limit, which change nothing computed), naming the fields. `what`: the output's
    kind, for the message ("a dataset", "a run"); defaults: as differing_fields."""
    path = Path(path)
    if not path.exists():
        write_json_atomic(path, mine)
        return
    differs = [f for f in differing_fields(json.loads(path.read_text()), mine, defaults) if f not in ignore]
    if differs:
        raise ValueError(f"{path.parent} holds {what} of another configuration (differs: {', '.join(differs)}); "
                         "use another OUT")
