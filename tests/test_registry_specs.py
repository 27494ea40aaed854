"""Zoo specs as outside users write them: every valid form resolves, and a wrong one (a misspelt
selector, a hand-edited registry, a checkpoint of another network) is refused before anything runs,
with an error naming the spec, the registry file, the record and the field."""

import dataclasses
import json
import shutil

import jax
import numpy as np
import pytest

from experiments import evaluate as E
from sim_data.policies.bc import PolicyNetConfig, init_params, save_params
from sim_data.policies.registry import resolve
from sim_data.sim.robot import ACTION_DIM, PROPRIO_DIM
from sim_data.util import run_cli

NET = PolicyNetConfig(encoder="conv", width=4, depth=1, hidden=8, chunk=2, size=64)
NORM = {"proprio_mean": np.zeros(PROPRIO_DIM), "proprio_std": np.ones(PROPRIO_DIM),
        "action_mean": np.zeros(ACTION_DIM), "action_std": np.ones(ACTION_DIM)}


def record(name, lineage, step, **extra):
    return {"name": name, "task": "mug", "lineage": lineage, "step": step, "val_loss": 0.1,
            "checkpoint": f"ckpt/{lineage}-{step}.msgpack", "net": dataclasses.asdict(NET),
            "variant": {"proprio": False}, **extra}


@pytest.fixture(scope="module")
def zoo(tmp_path_factory):
    """A registry of tiny networks: lineages conv_a and conv_b (two checkpoints each) and a noise family."""
    d = tmp_path_factory.mktemp("zoo")
    records = [record(f"mug/{lin}/{s}", lin, s) for lin in ("conv_a", "conv_b") for s in (1, 2)]
    records.append(record("mug/conv_a~noise/0.2", "conv_a~noise", None, degrade={"noise": 0.2},
                          checkpoint="ckpt/conv_a-2.msgpack"))
    for r in records[:4]:
        save_params(d / r["checkpoint"], init_params(NET, jax.random.PRNGKey(r["step"]), NORM, False))
    (d / "policies.json").write_text(json.dumps({"data": "runs/data/none", "policies": records}))
    return d


def edited(zoo, tmp_path, edit=None, text=None):
    """A copy of the zoo whose registry is edited (edit(registry dict)) or replaced by text."""
    d = tmp_path / "edited"
    shutil.copytree(zoo, d)
    if text is None:
        reg = json.loads((zoo / "policies.json").read_text())
        edit(reg)
        text = json.dumps(reg)
    (d / "policies.json").write_text(text)
    return d


def names(specs):
    return [s.name for s in resolve(specs)]


def test_every_valid_form_of_a_zoo_spec_resolves(zoo, tmp_path, monkeypatch):
    assert len(names([str(zoo)])) == 5
    assert names([f"{zoo}#conv_b"]) == ["mug/conv_b/1", "mug/conv_b/2"]
    assert len(names([f"{zoo}#conv_a+conv_b"])) == 4
    assert names([f"{zoo}/#mug/conv_a/2+ conv_a~noise"]) == ["mug/conv_a/2", "mug/conv_a~noise/0.2"]
    assert names([f"{zoo}/policies.json#@1/2"]) == ["mug/conv_a/2", "mug/conv_b/2"]
    spaced = tmp_path / "my zoo"
    shutil.copytree(zoo, spaced)
    monkeypatch.chdir(tmp_path)
    assert names(["my zoo#conv_b", "./my zoo/#mug/conv_a/1"]) == ["mug/conv_b/1", "mug/conv_b/2", "mug/conv_a/1"]
    # fields it does not know are kept; a registry without its dataset resolves (no seeds to exclude)
    extra = edited(zoo, tmp_path, lambda r: (r.pop("data"), r["policies"][0].update(note="hand-made")))
    (first,) = resolve([f"{extra}#mug/conv_a/1"])
    assert first.record["note"] == "hand-made" and first.record["data"] is None


def test_a_selector_term_that_names_nothing_is_refused_even_beside_one_that_does(zoo):
    for sel, bad in (("conv_a+conv_bb", "'conv_bb'"), ("conv_a+mug/conv_a/3", "'mug/conv_a/3'"),
                     ("conv_a~noise+conv_a~nosie", "'conv_a~nosie'"), ("conv_b#mug", "'conv_b#mug'")):
        with pytest.raises(ValueError, match=f"{bad} names no policy, lineage or task of {zoo}/policies.json"):
            resolve([f"{zoo}#{sel}"])
    with pytest.raises(ValueError, match="did you mean conv_b"):
        resolve([f"{zoo}#conv_a+conv_bb"])
    for empty in ("#", "#+", "# "):
        with pytest.raises(ValueError, match="nothing follows '#'"):
            resolve([f"{zoo}{empty}"])


def test_the_evaluator_refuses_a_misspelt_selector_in_one_line(zoo, capsys):
    # run_cli's one line and exit status 2, before the world model (absent here) is even read
    assert run_cli(lambda: E.main(["--out", "unused", "wm=no/such/wm", f"policies={zoo}#conv_a+conv_bb"])) == 2
    assert "'conv_bb' names no policy" in capsys.readouterr().err


@pytest.mark.parametrize("edit, message", [
    (lambda r: r["policies"][1].pop("lineage"), r"record 1 \('mug/conv_a/2'\) lacks the field 'lineage'"),
    (lambda r: r["policies"][0].pop("net"), r"record 0 \('mug/conv_a/1'\) lacks the field 'net'"),
    (lambda r: r["policies"][2].pop("name"), r"record 2 lacks the field 'name'"),
    (lambda r: r["policies"][0].update(checkpoint=None), r"'checkpoint' must be a str"),
    (lambda r: r.pop("policies"), r"\"policies\" lists one record per checkpoint"),
    (lambda r: r["policies"][0].update(task="mugg"), r"unknown task 'mugg'"),
    (lambda r: r["policies"][0]["net"].update(dropout=0.1), r"record 0 .*'net' .*dropout"),
    (lambda r: r["policies"][0]["net"].update(encoder="resnet"), r"record 0 .*encoder must be one of"),
    (lambda r: r["policies"][1].update(name="mug/conv_a/1"), r"records 0 and 1 are both named 'mug/conv_a/1'"),
    (lambda r: r["policies"][4].update(degrade={"nosie": 0.2}), r"record 4 .*unknown degradation \['nosie'\]"),
    (lambda r: r["policies"][4].update(degrade={"delay": 20}), r"record 4 .*delay must be whole control steps"),
    (lambda r: r["policies"][4].update(degrade={"noise": -0.2}), r"record 4 .*must be >= 0"),
    (lambda r: r["policies"][4].update(degrade={"noise": float("nan")}), r"record 4 .*noise must be finite"),
    (lambda r: r["policies"][4].update(degrade={"noise": "0.2"}), r"record 4 .*noise must be finite"),
    (lambda r: r["policies"][4].update(degrade=[0.2]), r"record 4 .*'degrade' must be a JSON object"),
    (lambda r: r["policies"][0].update(lineage="conv~v2"), r"record 0 .*'~' in the lineage 'conv~v2' marks a counterfactual"),
])
def test_a_hand_edited_registry_is_refused_naming_its_file_record_and_field(zoo, tmp_path, edit, message):
    d = edited(zoo, tmp_path, edit)
    with pytest.raises(ValueError, match=message) as e:
        resolve([str(d)])
    assert str(d / "policies.json") in str(e.value)


def test_a_broken_registry_file_or_checkpoint_is_refused_before_anything_runs(zoo, tmp_path):
    text = (zoo / "policies.json").read_text()
    with pytest.raises(ValueError, match=f"{tmp_path}/edited/policies.json is not valid JSON"):
        resolve([str(edited(zoo, tmp_path, text=text[:-2]))])
    shutil.rmtree(tmp_path / "edited")
    d = edited(zoo, tmp_path, lambda r: r["policies"][1].update(checkpoint="ckpt/conv_a-3.msgpack"))
    with pytest.raises(FileNotFoundError, match="policy 'mug/conv_a/2': its checkpoint .*conv_a-3.msgpack is missing"):
        resolve([str(d)])
    assert len(resolve([f"{d}#conv_b"])) == 2  # a missing checkpoint that is not selected is no matter
    shutil.rmtree(d)
    # a checkpoint of another network than its record describes: found by tracing, not in the first rollout
    for net in ({"width": 8}, {"encoder": "vit"}):
        d = edited(zoo, tmp_path, lambda r: r["policies"][0]["net"].update(net))
        with pytest.raises(ValueError, match=r"policy 'mug/conv_a/1': its checkpoint .*conv_a-1.msgpack does not fit"):
            resolve([f"{d}#mug/conv_a/1"])
        shutil.rmtree(d)


def test_repeated_policy_names_say_which_specs_gave_them(zoo, tmp_path):
    other = tmp_path / "other"
    shutil.copytree(zoo, other)
    with pytest.raises(ValueError, match=rf"'mug/conv_b/1' from {zoo}#conv_b and {zoo}#@0/2"):
        resolve([f"{zoo}#conv_b", f"{zoo}#@0/2"])
    with pytest.raises(ValueError, match=rf"'mug/conv_a/1' from {zoo}#conv_a and {other}#conv_a"):
        resolve([f"{zoo}#conv_a", f"{other}#conv_a"])
