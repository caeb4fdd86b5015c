"""A real S3 server for the object-storage tests: `arkit-s3-testbed` (s3s-fs with SigV4
on, and a fault-injecting proxy in front of it, both on 127.0.0.1), started as a
process whose stdin is a pipe (it stops when the test process goes), and the
environment that points the native client at its proxy."""

from __future__ import annotations

import json
import os
import pathlib
import subprocess
import urllib.request
from typing import Any, Dict, List, Optional

import pytest

from conftest import BIN, ROOT

TESTBED = pathlib.Path(os.environ.get("ARKIT_S3_TESTBED_BIN", ROOT / "target" / "release" / "arkit-s3-testbed"))
ACCESS = "arkit-py-access"
SECRET = "arkit-py-secret-7Hq2x"
BUCKET = "arkit"


class S3:
    """The test bed: its endpoints, its environment, and its proxy's controls."""

    def __init__(self, root: pathlib.Path, cache: pathlib.Path, latency_ms: int = 0, bandwidth_mbit: int = 0):
        if not TESTBED.exists():
            pytest.skip(f"SKIPPED: no arkit-s3-testbed binary at {TESTBED} (cargo build --release --workspace)")
        args = [str(TESTBED), "--root", str(root), "--access-key", ACCESS, "--secret-key", SECRET,
                "--bucket", BUCKET]
        if latency_ms:
            args += ["--latency-ms", str(latency_ms)]
        if bandwidth_mbit:
            args += ["--bandwidth-mbit", str(bandwidth_mbit)]
        self.process = subprocess.Popen(args, stdin=subprocess.PIPE, stdout=subprocess.PIPE)
        assert self.process.stdout is not None
        info = json.loads(self.process.stdout.readline())
        self.server: str = info["s3"]
        self.proxy: str = info["proxy"]
        self.cache = cache
        self.env: Dict[str, str] = {
            "AWS_ENDPOINT_URL": self.proxy,
            "AWS_ACCESS_KEY_ID": ACCESS,
            "AWS_SECRET_ACCESS_KEY": SECRET,
            "AWS_REGION": "us-east-1",
            "ARKIT_CACHE_DIR": str(cache),
            "ARKIT_STORAGE_RETRIES": "4",
            "ARKIT_STORAGE_TIMEOUT_MS": "3000",
        }

    def url(self, prefix: str) -> str:
        return f"s3://{BUCKET}/{prefix}"

    def stop(self) -> None:
        if self.process.stdin:
            self.process.stdin.close()
        self.process.wait(timeout=30)

    def _control(self, path: str, body: Optional[Dict[str, Any]] = None) -> Any:
        data = None if body is None else json.dumps(body).encode()
        req = urllib.request.Request(self.proxy + "/__testbed/" + path, data=data,
                                     method="GET" if body is None else "POST")
        with urllib.request.urlopen(req, timeout=10) as r:
            text = r.read()
        return json.loads(text) if text else None

    def faults(self, rules: List[Dict[str, Any]]) -> None:
        self._control("faults", {"rules": rules})

    def stats(self) -> Dict[str, Any]:
        stats: Dict[str, Any] = self._control("stats")
        return stats

    def reset(self) -> None:
        self._control("reset", {})

    def config(self, latency_ms: int = 0, bandwidth_bytes_per_sec: int = 0) -> None:
        self._control("config", {"latency_ms": latency_ms, "bandwidth_bytes_per_sec": bandwidth_bytes_per_sec})

    def push(self, dataset: pathlib.Path, prefix: str, *extra: str) -> Dict[str, Any]:
        out = subprocess.run([str(BIN), "push", str(dataset), self.url(prefix), "--json", *extra],
                             env=dict(os.environ, **self.env), capture_output=True, text=True, timeout=300)
        assert out.returncode == 0, out.stderr
        summary: Dict[str, Any] = json.loads(out.stdout)
        return summary
