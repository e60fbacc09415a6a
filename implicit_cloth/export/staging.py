"""Staging of export files: each is written under a temporary name beside its target and renamed into place."""

from __future__ import annotations

import contextlib
import os
from pathlib import Path
from typing import IO, Iterator


@contextlib.contextmanager
def staged_path(target: str | os.PathLike[str]) -> Iterator[Path]:
    """A temporary path beside ``target`` with the same suffix (libraries pick the format from it); renamed to
    ``target`` when the block ends without an exception, removed otherwise."""
    target = Path(target)
    target.parent.mkdir(parents=True, exist_ok=True)
    tmp = target.with_name(f".{target.stem}.{os.getpid()}.tmp{target.suffix}")
    try:
        yield tmp
        os.replace(tmp, target)
    finally:
        with contextlib.suppress(OSError):
            tmp.unlink()


def write_bytes(target: str | os.PathLike[str], data: bytes) -> Path:
    """Write ``data`` to ``target`` atomically (:func:`implicit_cloth.files.atomic_write`)."""
    from ..files import atomic_write

    def write(fh: IO[bytes]) -> None:
        fh.write(data)
    return atomic_write(target, write)
