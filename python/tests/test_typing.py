"""The package's type information: `py.typed` and `_native.pyi` ship with it, the stub
matches the built extension module (`mypy.stubtest`, which fails on a stub that names a
parameter wrongly), and mypy accepts the usage file and refuses wrong calls."""

import os
import pathlib
import shutil
import subprocess
import sys

import pytest

pytest.importorskip("mypy", reason="SKIPPED: mypy is not installed")

import arkit_tool  # noqa: E402

PACKAGE = pathlib.Path(arkit_tool.__file__).parent
HERE = pathlib.Path(__file__).parent


def run(args, cwd, pythonpath):
    env = dict(os.environ, PYTHONPATH=os.fspath(pythonpath))
    return subprocess.run([sys.executable, "-m", *args], cwd=cwd, env=env, capture_output=True, text=True)


def test_the_package_ships_its_types():
    assert (PACKAGE / "py.typed").is_file()
    assert (PACKAGE / "_native.pyi").is_file()


def test_the_stub_matches_the_extension_module(tmp_path):
    r = run(["mypy.stubtest", "arkit_tool._native"], tmp_path, PACKAGE.parent)
    assert r.returncode == 0, r.stdout + r.stderr
    # A stub with one parameter misnamed is caught.
    copy = tmp_path / "pkg"
    shutil.copytree(PACKAGE, copy / "arkit_tool")
    stub = copy / "arkit_tool" / "_native.pyi"
    text = stub.read_text()
    assert "iterations_count: int = 100" in text
    stub.write_text(text.replace("iterations_count: int = 100", "iterations: int = 100"))
    r = run(["mypy.stubtest", "arkit_tool._native"], tmp_path, copy)
    assert r.returncode != 0 and "solve_pnp_ransac" in r.stdout, r.stdout + r.stderr


def test_mypy_accepts_the_usage_and_refuses_wrong_calls(tmp_path):
    flags = ["mypy", "--no-incremental", "--cache-dir", os.fspath(tmp_path / "cache"),
             "--ignore-missing-imports", "--follow-imports=silent"]
    r = run([*flags, os.fspath(HERE / "typing_usage.py")], tmp_path, PACKAGE.parent)
    assert r.returncode == 0, r.stdout + r.stderr
    wrong = tmp_path / "wrong.py"
    wrong.write_text(
        "from arkit_tool import _native\n"
        "_native.solve_pnp_ransac(1, 2)\n"  # two arguments short
        "_native.Loader('d', None, 'train', 'official', '192', 1024, 0)\n"  # a str size
        "n: str = len(_native.Dataset('d'))\n"  # an int
        "from arkit_tool import conventions\n"
        "conventions.angles([[1.0]], 'opencv')\n"  # not a convention's name
    )
    r = run([*flags, os.fspath(wrong)], tmp_path, PACKAGE.parent)
    assert r.returncode != 0
    for line in [2, 3, 4, 6]:
        assert f"wrong.py:{line}:" in r.stdout, r.stdout
