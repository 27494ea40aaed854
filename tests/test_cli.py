"""The `wmlab` console script: its commands list, dispatch and mistakes; the configuration helpers
behind its commands (settings, config.json saved and checked)."""

import dataclasses
import importlib
import json

import pytest

from experiments import cli
from sim_data.config import as_json, differing_fields, flat_settings, save_or_check


def test_help_lists_every_command_and_each_module_has_a_main(capsys):
    assert cli.main(["--help"]) == 0
    out = capsys.readouterr().out
    for name, (module, _) in cli.COMMANDS.items():
        assert f"  {name} " in out and module in out
        assert callable(importlib.import_module(module).main)


def test_a_command_runs_its_module_and_an_unknown_one_is_refused(capsys):
    with pytest.raises(SystemExit) as e:
        cli.main(["report", "--help"])
    assert e.value.code == 0 and "usage: wmlab report" in capsys.readouterr().out
    assert cli.main(["nosuch"]) == 2
    assert "unknown command 'nosuch'" in capsys.readouterr().err


@pytest.mark.parametrize("command, presets", [("data", "sim_data.dataset.generate"), ("policies", "sim_data.policies.zoo"),
                                              ("train", "wm.config"), ("eval", "experiments.evaluate")])
def test_a_preset_commands_help_lists_its_presets_and_every_setting_with_its_values(command, presets, capsys):
    table = importlib.import_module(presets).PRESETS
    with pytest.raises(SystemExit) as e:
        cli.main([command, "--help"])
    out = capsys.readouterr().out
    assert e.value.code == 0 and f"presets (--config): {', '.join(table)}." in out
    first, *others = table.values()
    keys = [line.split(" = ")[0].strip() for line in out.splitlines() if line.startswith("  ") and " = " in line]
    assert keys == [k for k, _ in flat_settings(first)]
    for (key, value), *rest in zip(flat_settings(first), *(flat_settings(o) for o in others)):
        line = next(x for x in out.splitlines() if x.startswith(f"  {key} = "))
        shown = ",".join(map(str, value)) if isinstance(value, tuple) else str(value)
        assert shown in line and (len(table) == 1 or all(r[1] == value for r in rest) or "; " in line)


def test_a_saved_configuration_is_compared_field_by_field_with_defaults_for_fields_added_since(tmp_path):
    @dataclasses.dataclass(frozen=True)
    class Inner:
        width: int = 4
        names: tuple = ("a", "b")

    @dataclasses.dataclass(frozen=True)
    class Outer:
        lr: float = 1e-3
        minutes: float = 5.0
        inner: Inner = Inner()

    assert as_json(Outer()) == {"lr": 1e-3, "minutes": 5.0, "inner": {"width": 4, "names": ["a", "b"]}}
    mine = as_json({"run": Outer(), "data": "d"})
    assert differing_fields(mine, mine) == []
    saved = as_json({"run": Outer(lr=2e-3, inner=Inner(width=8)), "data": "e"})
    assert differing_fields(saved, mine) == ["data", "run.inner.width", "run.lr"]
    del saved["run"]["inner"]["names"]  # written before the field existed: it ran with the default
    defaults = as_json({"run": Outer()})
    assert differing_fields(saved, mine, defaults) == ["data", "run.inner.width", "run.lr"]
    assert "run.inner.names" in differing_fields(saved, mine)  # without defaults a missing field differs
    path = tmp_path / "config.json"
    save_or_check(path, mine, "a run")
    assert json.loads(path.read_text()) == mine
    save_or_check(path, mine, "a run")  # the same configuration resumes
    other = as_json({"run": Outer(minutes=9.0), "data": "d"})
    save_or_check(path, other, "a run", ignore=("run.minutes",))  # a setting that changes nothing computed
    with pytest.raises(ValueError, match=r"holds a run of another configuration \(differs: run.minutes\)"):
        save_or_check(path, other, "a run")
