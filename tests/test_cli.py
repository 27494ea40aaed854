"""The `wmlab` console script: its commands list, dispatch and mistakes."""

import importlib

import pytest

from experiments import cli


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
