"""Atomic output: a file or folder appears complete under its final name, or not at all.

Everything is first written under a temporary name in the destination folder (same file system, so the final
``os.replace`` / ``os.rename`` is atomic) and renamed only once it is complete; on failure the temporary is
removed, so a failed run leaves neither a half file nor a stray temporary behind.
"""
from __future__ import annotations

import contextlib
import os
import shutil
import tempfile
from collections.abc import Iterator
from pathlib import Path


def _current_umask() -> int:
    # os.umask can only be read by setting it; done once at import, before any worker threads exist
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


_UMASK = _current_umask()


def atomic_write_bytes(path, data: bytes) -> Path:
    """Write ``data`` to ``path`` atomically (temporary file in the same folder, fsync, ``os.replace``).

    Parameters
    ----------
    path : str or Path
        Destination file; its folder must exist.  An existing file is replaced.
    data : bytes
        The complete file content.

    Returns
    -------
    Path
        ``path``.
    """
    path = Path(path)
    with atomic_file(path) as tmp, open(tmp, "wb") as f:
        f.write(data)
        f.flush()
        os.fsync(f.fileno())  # on disk before the rename makes it the file
    return path


@contextlib.contextmanager
def atomic_file(path) -> Iterator[Path]:
    """A temporary path beside ``path`` for a writer that wants a file name (open3d, numpy); renamed onto
    ``path`` when the block ends without error, removed otherwise.  The suffix is kept (writers choose the
    format from it)."""
    path = Path(path)
    fd, tmp_name = tempfile.mkstemp(dir=path.parent, prefix=f".{path.stem}.", suffix=path.suffix)
    os.close(fd)
    try:
        yield Path(tmp_name)
        os.chmod(tmp_name, 0o666 & ~_UMASK)  # mkstemp creates 0600; the mode an ordinary open() would give
        os.replace(tmp_name, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp_name)
        raise


def atomic_write_text(path, text: str, encoding: str = "utf-8") -> Path:
    """Write ``text`` to ``path`` atomically; see :func:`atomic_write_bytes`."""
    return atomic_write_bytes(path, text.encode(encoding))


def atomic_write_texts(texts: dict, encoding: str = "utf-8") -> list[Path]:
    """Write several files as one: every text goes to its temporary first (fsync'd), and only when all are complete
    are they renamed onto their paths, back to back; a failure before (a full disk, a signal) removes every
    temporary and leaves every path as it was (an audit's JSON and HTML: both or neither).

    Parameters
    ----------
    texts : dict
        path -> text.
    """
    with contextlib.ExitStack() as stack:
        for path, text in texts.items():
            tmp = stack.enter_context(atomic_file(path))
            with open(tmp, "wb") as f:
                f.write(text.encode(encoding))
                f.flush()
                os.fsync(f.fileno())
    return [Path(p) for p in texts]


@contextlib.contextmanager
def atomic_directory(path, overwrite: bool = False) -> Iterator[Path]:
    """Build a folder under a temporary sibling name; rename it to ``path`` only if the block succeeds.

    Parameters
    ----------
    path : str or Path
        Final folder.  Its parent folders are created if missing.
    overwrite : bool
        Replace an existing ``path``.  Without it an existing ``path`` raises FileExistsError, before the
        block runs (so no work is wasted) and again at the rename (in case it appeared meanwhile).

    Yields
    ------
    Path
        The temporary folder to fill.  On an exception it is removed and the exception propagates.
    """
    path = Path(path)
    if path.exists() and not overwrite:
        raise FileExistsError(f"{path}: already exists (pass overwrite=True / --overwrite to replace it)")
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp"))
    try:
        yield tmp
        os.chmod(tmp, 0o777 & ~_UMASK)  # mkdtemp creates 0700
        if path.exists() or path.is_symlink():
            if not overwrite:
                raise FileExistsError(f"{path}: already exists (pass overwrite=True / --overwrite to replace it)")
            # a non-empty folder cannot be the target of a rename: move the old one aside first, then drop it
            old = Path(tempfile.mkdtemp(dir=path.parent, prefix=f".{path.name}.", suffix=".old"))
            os.rename(path, old / "content")
            try:
                os.rename(tmp, path)
            except BaseException:
                os.rename(old / "content", path)
                shutil.rmtree(old, ignore_errors=True)
                raise
            shutil.rmtree(old, ignore_errors=True)
        else:
            os.rename(tmp, path)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
