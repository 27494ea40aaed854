import json

import pytest

from sim_data.bench import compile as C


def test_unknown_pieces_and_batches_are_refused_before_anything_compiles():
    with pytest.raises(ValueError, match="unknown pieces"):
        C.profile(2, ("scan", "physics"))
    with pytest.raises(ValueError, match="batch must be >= 1"):
        C.profile(0, ("scan",))


@pytest.mark.slow
def test_each_piece_is_compiled_alone_and_written_as_json(tmp_path):
    out = tmp_path / "compile.json"
    assert C.main(["--out", str(out), "--batch", "2", "--pieces", "task_checks,bc_act_conv"]) == 0
    got = json.loads(out.read_text())
    assert got["batch"] == 2 and [r["piece"] for r in got["pieces"]] == ["task_checks", "bc_act_conv"]
    for row in got["pieces"]:
        assert row["lines"] > 100 and row["compile_s"] > 0 and row["what"]
