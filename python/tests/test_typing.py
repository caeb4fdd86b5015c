"""The package's type information: `py.typed`, `types.py` and `_native.pyi` ship with it,
the stub matches the built extension module (`mypy.stubtest`, which fails on a stub that
names a parameter wrongly), `mypy --strict` accepts the usage file (a user's code) and
the package itself, and refuses wrong calls (a misspelt option, a key no item has)."""

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


@pytest.fixture(scope="module")
def cache(tmp_path_factory):
    """One mypy cache for this module's runs (made fresh: nothing stale)."""
    return tmp_path_factory.mktemp("mypy-cache")


def mypy(args, cwd, cache):
    return run(["mypy", "--strict", "--cache-dir", os.fspath(cache), *args], cwd, PACKAGE.parent)


def test_the_package_ships_its_types():
    assert (PACKAGE / "py.typed").is_file()
    assert (PACKAGE / "_native.pyi").is_file()
    assert (PACKAGE / "types.py").is_file()


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


def test_mypy_strict_accepts_the_usage_and_refuses_wrong_calls(tmp_path, cache):
    # The usage file runs torch's DataLoader over the dataset: its types come with torch.
    pytest.importorskip("torch", reason="SKIPPED: torch is not installed (the usage file types its DataLoader)")
    # --follow-imports=silent: the package's own modules are read, not reported on, as
    # mypy treats an installed package.
    r = mypy(["--follow-imports=silent", os.fspath(HERE / "typing_usage.py")], tmp_path, cache)
    assert r.returncode == 0, r.stdout + r.stderr
    wrong = tmp_path / "wrong.py"
    wrong.write_text(
        "from arkit_tool import _native\n"
        "_native.solve_pnp_ransac(1, 2)\n"  # two arguments short
        "_native.Loader('d', None, 'train', 'official', '192', 1024, 0)\n"  # a str size
        "n: str = len(_native.Dataset('d'))\n"  # an int
        "from arkit_tool import conventions, ARKitFaceDataset, evaluate\n"
        "conventions.angles([[1.0]], 'opencv')\n"  # not a convention's name
        "ARKitFaceDataset('d', compat='offical')\n"  # not a rule set
        "ARKitFaceDataset('d', mode='test')\n"  # a split, not a mode
        "ARKitFaceDataset('d', corr='sparse')[0]['corr_mat']\n"  # fine (the key may be there)
        "ARKitFaceDataset('d')[0]['imgg']\n"  # no such key
        "evaluate('d', 'p.parquet')['summary']['mae_r']\n"  # no such metric
        "ARKitFaceDataset('d').loader(8).state_dict()['epoch'].upper()\n"  # an int
    )
    r = mypy(["--follow-imports=silent", os.fspath(wrong)], tmp_path, cache)
    assert r.returncode != 0
    for line in [2, 3, 4, 6, 7, 8, 10, 11, 12]:
        assert f"wrong.py:{line}:" in r.stdout, r.stdout
    assert "wrong.py:9:" not in r.stdout, r.stdout


def test_the_package_is_mypy_strict_clean(tmp_path, cache):
    # Optional imports (torch, polars, pyarrow, rerun-sdk) may be missing here.
    r = mypy(["--ignore-missing-imports", "-p", "arkit_tool"], tmp_path, cache)
    assert r.returncode == 0, r.stdout + r.stderr
