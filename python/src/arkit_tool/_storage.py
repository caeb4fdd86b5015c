"""Where a dataset lives: a local folder, or a bucket URL read by the native layer
(`s3://bucket/prefix`; `gs://`, `az://` and `https://` where the backend allows)."""

from __future__ import annotations

import os
from typing import Any

# The schemes the native layer reads as object storage (arkit_data::storage).
URL_SCHEMES = ("s3", "s3a", "gs", "az", "abfs", "abfss", "http", "https")


def is_url(path: Any) -> bool:
    """Whether `path` names a dataset in object storage rather than a local folder."""
    if not isinstance(path, str):
        try:
            path = os.fspath(path)
        except TypeError:
            return False
    scheme, sep, _ = str(path).partition("://")
    return bool(sep) and scheme.lower() in URL_SCHEMES
