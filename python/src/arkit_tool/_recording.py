"""The Rerun recording the viewers (`view`, `video_view`) write.

A recording is either sent to a spawned viewer or saved: then to `PATH.partial`, renamed
to `PATH` once complete (`finish`), or removed when the run fails (`abandon`), so no
half-written recording survives under the name the user gave.
"""

from __future__ import annotations

import os
from typing import Any, Optional, Tuple, cast

from .types import PathLike


def rerun_module(install_hint: str) -> Any:
    """The `rerun` module, or an ImportError saying how to install it."""
    try:
        import rerun as rr  # type: ignore[import-untyped,import-not-found,unused-ignore]
    except ImportError:
        raise ImportError(install_hint) from None
    return rr


def open_recording(
    rr: Any, application: str, path: Optional[PathLike], spawn: bool, recording: Any
) -> Tuple[Any, Optional[str]]:
    """The stream to log to and its `.partial` file (None when spawned or given)."""
    if recording is not None:
        return recording, None
    rec = rr.RecordingStream(application)
    if spawn:
        rec.spawn()
        return rec, None
    tmp = os.fspath(cast(PathLike, path)) + ".partial"
    rec.save(tmp)
    return rec, tmp


def finish(rec: Any, tmp: Optional[str], path: Optional[PathLike]) -> Optional[str]:
    """The saved recording renamed into place; its path (None when not saved)."""
    if tmp is None:
        return None
    rec.flush()
    rec.disconnect()
    os.replace(tmp, os.fspath(cast(PathLike, path)))
    return os.fspath(cast(PathLike, path))


def abandon(rec: Any, tmp: Optional[str]) -> None:
    """A failed run's partial recording removed."""
    if tmp is None:
        return
    rec.disconnect()
    if os.path.exists(tmp):
        os.remove(tmp)
