"""The success-table command and the Wilson interval."""

import json
import math

import pytest

from sim_data.bench.success_table import main, wilson_interval


def test_wilson_interval_hand_computed():
    # p = 0.8, n = 100, z = 1.96: centre = (0.8 + 1.96^2/200) / (1 + 1.96^2/100)
    z = 1.959964
    den = 1 + z * z / 100
    centre = (0.8 + z * z / 200) / den
    half = z * math.sqrt(0.8 * 0.2 / 100 + z * z / 40000) / den
    lo, hi = wilson_interval(80, 100)
    assert lo == pytest.approx(centre - half) and hi == pytest.approx(centre + half)
    assert lo == pytest.approx(0.7112, abs=1e-4) and hi == pytest.approx(0.8666, abs=1e-4)
    assert wilson_interval(0, 10)[0] == pytest.approx(0.0, abs=1e-12)
    assert wilson_interval(10, 10)[1] == pytest.approx(1.0, abs=1e-12)
    assert wilson_interval(10, 10)[0] == pytest.approx(0.7225, abs=1e-4)  # 10/10: lower bound


def test_command_writes_task_skill_rates(tmp_path):
    out = tmp_path / "t.json"
    assert main(["--backend", "cpu", "--episodes", "2", "--skills", "1.0,0.0", "--tasks", "step_back", "--out", str(out)]) == 0
    table = json.loads(out.read_text())
    assert {k: table[k] for k in ("engine", "episodes", "grip", "seed")} == {"engine": "cpu", "episodes": 2,
                                                                            "grip": 1.0, "seed": 0}
    rates = table["rates"]
    assert list(rates) == ["step_back"] and list(rates["step_back"]) == ["1.0", "0.0"]
    assert rates["step_back"]["1.0"] == 1.0
    assert table["intervals"]["step_back"]["1.0"] == pytest.approx(list(wilson_interval(2, 2)))
    assert table["failed_progress"]["step_back"]["1.0"] is None  # no failure to measure


def test_a_weak_grip_drops_the_mug_that_the_scripts_full_grip_lifts(tmp_path):
    rates = {}
    for grip in ("1.0", "0.2"):
        out = tmp_path / f"g{grip}.json"
        assert main(["--backend", "cpu", "--episodes", "2", "--skills", "1.0", "--tasks", "mug", "--grip", grip,
                     "--out", str(out)]) == 0
        table = json.loads(out.read_text())
        assert table["grip"] == float(grip)
        rates[grip] = table["rates"]["mug"]["1.0"]
    assert rates == {"1.0": 1.0, "0.2": 0.0}


def test_bad_arguments_are_refused(tmp_path):
    with pytest.raises(SystemExit, match="outside"):
        main(["--skills", "1.5", "--out", str(tmp_path / "x.json")])
    with pytest.raises(SystemExit, match="unknown"):
        main(["--tasks", "mug,fly", "--out", str(tmp_path / "x.json")])
    with pytest.raises(SystemExit, match="outside"):
        main(["--grip", "1.5", "--out", str(tmp_path / "x.json")])


def test_the_air_fryers_weak_grip_fails_a_few_millimetres_short_of_its_line(tmp_path):
    # the hand hooks the tray's handle whatever its closure: a grip of 0.2 still drags the tray about
    # 95% of the 10 cm, and the failures' progress says so
    out = tmp_path / "fryer.json"
    assert main(["--backend", "cpu", "--episodes", "2", "--skills", "1.0", "--tasks", "airfryer", "--grip", "0.2",
                 "--out", str(out)]) == 0
    table = json.loads(out.read_text())
    assert table["rates"]["airfryer"]["1.0"] == 0.0
    mean, top = table["failed_progress"]["airfryer"]["1.0"]
    assert 0.9 < mean <= top < 1.0


def test_with_the_two_state_tray_the_air_fryers_failures_end_shut(tmp_path):
    # over the centre the tray snaps open: the weak grip that fails 5 mm short above now succeeds; and
    # the low-skill script's failures end with the tray shut (progress 0), not part-way (the plain
    # slide leaves them at 0.19 of the line on average and up to 0.96, docs/results.md)
    out = tmp_path / "spring.json"
    assert main(["--backend", "cpu", "--episodes", "2", "--skills", "1.0,0.2", "--tasks", "airfryer", "--grip", "0.2",
                 "--tray-spring", "300,0.07", "--out", str(out)]) == 0
    table = json.loads(out.read_text())
    assert table["tray_spring"] == [300.0, 0.07] and table["rates"]["airfryer"] == {"1.0": 1.0, "0.2": 0.0}
    assert table["failed_progress"]["airfryer"] == {"1.0": None, "0.2": [0.0, 0.0]}
    for bad, message in (("300", "is not K,X"), ("300,0.5", "inside the tray's travel"), ("0,0.07", "must be > 0")):
        with pytest.raises(SystemExit, match=message):
            main(["--tray-spring", bad, "--out", str(tmp_path / "x.json")])
