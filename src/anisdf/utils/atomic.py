"""Atomic file writing: a crash or an exception never leaves a half-written output file."""

from __future__ import annotations

import contextlib
import os
import tempfile
from collections.abc import Iterator
from pathlib import Path


def file_mode() -> int:
    """The mode a plain ``open(path, "w")`` gives under the current umask. ``mkstemp`` makes its files private
    (0600); outputs such as a web page must stay readable by a web server or another user like any file written."""
    mask = os.umask(0)
    os.umask(mask)
    return 0o666 & ~mask


def temp_file(path: Path) -> Path:
    """A new empty file beside ``path`` (keeping its suffix) with the ordinary mode (:func:`file_mode`)."""
    fd, tmp_name = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=f".tmp{path.suffix}", dir=path.parent)
    os.close(fd)
    os.chmod(tmp_name, file_mode())
    return Path(tmp_name)


@contextlib.contextmanager
def atomic_path(path: str | Path) -> Iterator[Path]:
    """Yield a temporary path in the same folder as ``path``; on success move it onto ``path``.

    The temporary file keeps the suffix of ``path`` (writers that pick a format from it still work).
    On an exception the temporary file is removed and ``path`` is left untouched.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = temp_file(path)
    try:
        yield tmp
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            tmp.unlink()
        raise


def write_text_atomic(path: str | Path, text: str) -> Path:
    """Write ``text`` (UTF-8) to ``path`` atomically and return the path."""
    with atomic_path(path) as tmp:
        tmp.write_text(text, encoding="utf-8")
    return Path(path)
