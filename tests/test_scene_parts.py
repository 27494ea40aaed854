"""The v0 scene composed from home.xml with MjSpec (sim_data.sim.scene_v0)."""

import mujoco
import numpy as np

from sim_data.sim import scene as S
from sim_data.sim import scene_v0

OLD_FILE = S.MODEL_PATH.parent / "variant_v0_box_fingers.xml"


def _fields(m: mujoco.MjModel) -> dict:
    """Every array, number and the names of a compiled model, its options and statistics included."""
    out = {}
    for name in dir(m):
        value = getattr(m, name) if not name.startswith("_") else None
        if isinstance(value, (np.ndarray, bytes)) or (isinstance(value, (int, float)) and not isinstance(value, bool)):
            out[name] = value
    for sub in ("opt", "stat"):
        for name in dir(getattr(m, sub)):
            value = getattr(getattr(m, sub), name)
            if not name.startswith("_") and isinstance(value, (np.ndarray, int, float)):
                out[f"{sub}.{name}"] = value
    return out


def test_composed_v0_compiles_to_the_old_files_model():
    composed, old = _fields(scene_v0.spec().compile()), _fields(mujoco.MjModel.from_xml_path(str(OLD_FILE)))
    assert composed.keys() == old.keys() and len(composed) > 500
    differ = [k for k in old if np.shape(composed[k]) != np.shape(old[k]) or not np.array_equal(composed[k], old[k])]
    assert not differ, differ
