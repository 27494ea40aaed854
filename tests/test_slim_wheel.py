import subprocess
import sys
import zipfile

import pytest

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
