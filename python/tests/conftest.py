"""Shared fixtures: a small synthetic dataset made and converted by the arkit-tool binary."""

import os
import pathlib
import subprocess

import pytest

ROOT = pathlib.Path(__file__).resolve().parents[2]
BIN = pathlib.Path(os.environ.get("ARKIT_TOOL_BIN", ROOT / "target" / "release" / "arkit-tool"))
RESOURCES = pathlib.Path(
    os.environ.get("ARKIT_RESOURCES", ROOT.parent / "shared" / "arkitface-resources")
)


def run(*args):
    subprocess.run([str(a) for a in args], check=True, stdout=subprocess.DEVNULL)


def make_dataset(base: pathlib.Path, resources: bool, size: str = "400x400", subjects: int = 3):
    if not BIN.exists():
        pytest.skip(f"SKIPPED: no arkit-tool binary at {BIN} (cargo build --release, or set ARKIT_TOOL_BIN)")
    res = ["--resources", RESOURCES] if resources else []
    run(BIN, "synth", "--output", base / "release", "--subjects", subjects,
        "--images-per-subject", 4, "--size", size, "--seed", 3, "--test-fraction", 0.34, *res)
    run(BIN, "convert", "--input", base / "release", "--output", base / "converted",
        "--rows-per-shard", 5, *res)
    return base / "converted"


@pytest.fixture(scope="session")
def dataset(tmp_path_factory):
    """The built-in face (no resource files needed)."""
    return make_dataset(tmp_path_factory.mktemp("builtin"), resources=False)


@pytest.fixture(scope="session")
def real_dataset(tmp_path_factory):
    """The real ARKit topology (skips without ../shared/arkitface-resources)."""
    if not (RESOURCES / "triangles.npy").exists():
        pytest.skip(f"SKIPPED: no ARKit resource files at {RESOURCES} (set ARKIT_RESOURCES)")
    return make_dataset(tmp_path_factory.mktemp("real"), resources=True, size="800x800")
