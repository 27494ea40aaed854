"""Configuration helpers shared by every preset-driven command: dotted `key=value` overrides of
frozen dataclasses (nested ones included), parsed to the type of the field they replace."""

from __future__ import annotations

import dataclasses


def parse_value(current, text: str, name: str):
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
