import subprocess
import sys
import zipfile

import pytest

from experiments import slim_wheel
from experiments.slim_wheel import slim


def _wheel(path, members: dict) -> None:
    record = "".join(f"{name},sha256=x,{len(data)}\n" for name, data in members.items()) + "pkg-1.0.dist-info/RECORD,,\n"
    with zipfile.ZipFile(path, "w") as z:
        for name, data in members.items():
            z.writestr(name, data)
        z.writestr("pkg-1.0.dist-info/RECORD", record)


def test_a_slimmed_wheel_keeps_every_other_member_and_record_line(tmp_path):
    members = {"pkg/__init__.py": b"x = 1\n", "pkg/weights/small.ckpt": b"a" * 10, "pkg/weights/big.ckpt": b"b" * 1000}
    wheel = tmp_path / "pkg-1.0-py3-none-any.whl"
    _wheel(wheel, members)
    out = slim(wheel, ["pkg/weights/big.ckpt"], tmp_path / "out")
    assert out == tmp_path / "out" / wheel.name
    with zipfile.ZipFile(out) as z:
        assert sorted(z.namelist()) == ["pkg-1.0.dist-info/RECORD", "pkg/__init__.py", "pkg/weights/small.ckpt"]
        assert z.read("pkg/weights/small.ckpt") == b"a" * 10 and z.read("pkg/__init__.py") == b"x = 1\n"
        record = z.read("pkg-1.0.dist-info/RECORD").decode().splitlines()
    assert [ln.split(",")[0] for ln in record] == ["pkg/__init__.py", "pkg/weights/small.ckpt",
                                                   "pkg-1.0.dist-info/RECORD"]
    assert not list((tmp_path / "out").glob("*.partial"))


def test_a_member_the_wheel_lacks_is_refused(tmp_path):
    wheel = tmp_path / "pkg-1.0-py3-none-any.whl"
    _wheel(wheel, {"pkg/__init__.py": b""})
    with pytest.raises(ValueError, match="holds no pkg/weights/vgg16.ckpt"):
        slim(wheel, ["pkg/weights/vgg16.ckpt"], tmp_path / "out")
    assert not (tmp_path / "out" / wheel.name).exists()


def test_pip_installs_a_slimmed_wheel_as_any_other(tmp_path):
    members = {"pkg/__init__.py": b"VALUE = 7\n", "pkg/big.bin": b"b" * 100,
               "pkg-1.0.dist-info/METADATA": b"Metadata-Version: 2.1\nName: pkg\nVersion: 1.0\n",
               "pkg-1.0.dist-info/WHEEL": b"Wheel-Version: 1.0\nGenerator: test\nRoot-Is-Purelib: true\nTag: py3-none-any\n"}
    wheel = tmp_path / "pkg-1.0-py3-none-any.whl"
    _wheel(wheel, members)
    out = slim(wheel, ["pkg/big.bin"], tmp_path / "out")
    site = tmp_path / "site"
    subprocess.run([sys.executable, "-m", "pip", "install", "-q", "--no-index", "--no-deps", "--target", str(site),
                    str(out)], check=True)
    assert (site / "pkg" / "__init__.py").read_text() == "VALUE = 7\n" and not (site / "pkg" / "big.bin").exists()


def test_a_pattern_drops_every_member_under_it_and_one_matching_none_is_refused(tmp_path):
    members = {"pkg/__init__.py": b"", "pkg/test_data/a.xml": b"a", "pkg/test_data/sub/b.stl": b"b",
               "pkg/_cffi.cpython-312-x86_64-linux-gnu.so": b"c"}
    wheel = tmp_path / "pkg-1.0-py3-none-any.whl"
    _wheel(wheel, members)
    out = slim(wheel, ["pkg/test_data/*", "pkg/_cffi.*"], tmp_path / "out")
    with zipfile.ZipFile(out) as z:
        assert sorted(z.namelist()) == ["pkg-1.0.dist-info/RECORD", "pkg/__init__.py"]
        record = z.read("pkg-1.0.dist-info/RECORD").decode().splitlines()
    assert [ln.split(",")[0] for ln in record] == ["pkg/__init__.py", "pkg-1.0.dist-info/RECORD"]
    with pytest.raises(ValueError, match=r"holds no pkg/weights/\*"):
        slim(wheel, ["pkg/test_data/*", "pkg/weights/*"], tmp_path / "out2")


def test_the_fetched_wheels_are_slimmed_in_place_once(tmp_path, monkeypatch):
    monkeypatch.setattr(slim_wheel, "FETCHED_UNREAD", {"mujoco_mjx": ("mujoco/mjx/test_data/*",)})
    mjx = tmp_path / "mujoco_mjx-3.17.0-py3-none-any.whl"
    other = tmp_path / "mcap-1.6.0-py3-none-any.whl"
    _wheel(mjx, {"mujoco/mjx/__init__.py": b"x", "mujoco/mjx/test_data/model.xml": b"m" * 100})
    _wheel(other, {"mcap/__init__.py": b"y"})
    before = other.read_bytes()
    assert slim_wheel.slim_fetched(tmp_path) == [mjx]
    with zipfile.ZipFile(mjx) as z:
        assert sorted(z.namelist()) == ["mujoco/mjx/__init__.py", "pkg-1.0.dist-info/RECORD"]
    assert other.read_bytes() == before
    (tmp_path / (other.name + ".partial")).write_bytes(b"killed mid-write")
    assert slim_wheel.slim_fetched(tmp_path) == []  # already slim: left as it is
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted([mjx.name, other.name])


def test_a_write_that_fails_leaves_the_wheel_whole(tmp_path, monkeypatch):
    wheel = tmp_path / "pkg-1.0-py3-none-any.whl"
    _wheel(wheel, {"pkg/__init__.py": b"x", "pkg/big.bin": b"b" * 100})
    before = wheel.read_bytes()

    def broken(self, *args, **kwargs):
        raise OSError("disk full")

    monkeypatch.setattr(zipfile.ZipFile, "writestr", broken)
    with pytest.raises(OSError, match="disk full"):
        slim(wheel, ["pkg/big.bin"], tmp_path)
    assert wheel.read_bytes() == before and sorted(p.name for p in tmp_path.iterdir()) == [wheel.name]
