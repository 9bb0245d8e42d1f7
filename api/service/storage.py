"""Files by location: a plain path, a ``file://`` URL, or an object-store URL read through fsspec.

Jobs carry locations, never bytes. A worker replays a local file: a remote recording is
copied to a temporary file first (the MCAP reader seeks), and a remote run directory is
written locally and uploaded, file by file, when the run ends (failed runs too: their
manifest and log say why). Local locations are used in place, so the default set-up needs
no fsspec. Other schemes (``s3://``, ``gs://``, ``memory://`` ...) need fsspec, which comes
with the ray extra (``pip install -e '.[ray]'``), plus the scheme's own fsspec package (``s3fs`` for ``s3://``).
Nothing here downloads code or data at import time.
"""

from __future__ import annotations

import os
import shutil
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any
from urllib.parse import unquote, urlparse

from slamreplay.recorder.files import replacing

LOCAL_SCHEMES = ("", "file")


class StorageError(Exception):
    """A location that cannot be read or written; the message names it and says why."""


def is_local(url: str | Path) -> bool:
    """True for a plain path or a ``file://`` URL."""
    text = str(url)
    scheme = urlparse(text).scheme
    return scheme in LOCAL_SCHEMES or (len(scheme) == 1 and os.name == "nt")  # "C:\..." on Windows


def local_path(url: str | Path) -> Path:
    """The path of a local location (``file:///a/b`` -> ``/a/b``)."""
    text = str(url)
    if text.startswith("file://"):
        return Path(unquote(urlparse(text).path))
    return Path(text)


def join(base: str, *parts: str) -> str:
    """``base`` with ``parts`` appended, for paths and URLs alike."""
    if is_local(base):
        return str(local_path(base).joinpath(*parts))
    return "/".join([base.rstrip("/"), *parts])


def _fs(url: str) -> tuple[Any, str]:
    """The fsspec filesystem of ``url`` and the path within it."""
    try:
        import fsspec  # type: ignore[import-untyped]
    except ImportError as err:
        msg = f"{url}: object-store locations need fsspec: `pip install -e '.[ray]'` in the slamreplay checkout"
        raise StorageError(msg) from err
    try:
        fs, path = fsspec.core.url_to_fs(url)
    except (ImportError, ValueError) as err:  # e.g. s3:// without s3fs installed
        msg = f"{url}: no filesystem for this URL ({err})"
        raise StorageError(msg) from err
    return fs, path


def exists(url: str) -> bool:
    """Whether a file is at ``url``."""
    if is_local(url):
        return local_path(url).is_file()
    fs, path = _fs(url)
    return bool(fs.isfile(path))


def put_file(src: Path, url: str) -> None:
    """Copy the local file ``src`` to ``url`` (written under a temporary name first where it is local)."""
    try:
        if is_local(url):
            dst = local_path(url)
            dst.parent.mkdir(parents=True, exist_ok=True)
            with replacing(dst) as tmp:
                shutil.copyfile(src, tmp)
            return
        fs, path = _fs(url)
        fs.put_file(str(src), path)
    except OSError as err:
        msg = f"could not write {url}: {err}"
        raise StorageError(msg) from err


def get_file(url: str, dst: Path) -> None:
    """Copy the file at ``url`` to the local path ``dst``."""
    try:
        if is_local(url):
            shutil.copyfile(local_path(url), dst)
            return
        fs, path = _fs(url)
        fs.get_file(path, str(dst))
    except (OSError, KeyError) as err:  # fsspec's memory filesystem raises FileNotFoundError; some raise KeyError
        msg = f"could not read {url}: {err}"
        raise StorageError(msg) from err


def list_files(url: str) -> list[str]:
    """Names (relative, ``/``-separated) of the files under the directory ``url``; empty when it is missing."""
    if is_local(url):
        root = local_path(url)
        if not root.is_dir():
            return []
        return sorted(p.relative_to(root).as_posix() for p in root.rglob("*") if p.is_file())
    fs, path = _fs(url)
    if not fs.isdir(path):
        return []
    base = path.rstrip("/") + "/"
    return sorted(f[len(base):] for f in fs.find(path) if f.startswith(base))


def remove_dir(url: str) -> None:
    """Delete the directory ``url`` and everything in it, if it is there."""
    if is_local(url):
        shutil.rmtree(local_path(url), ignore_errors=True)
        return
    fs, path = _fs(url)
    if fs.exists(path):
        fs.rm(path, recursive=True)


def put_dir(src: Path, url: str) -> None:
    """Copy the files of the local directory ``src`` into ``url``, replacing what was there."""
    remove_dir(url)
    for f in sorted(p for p in src.rglob("*") if p.is_file()):
        put_file(f, join(url, *f.relative_to(src).parts))


def get_dir(url: str, dst: Path) -> None:
    """Copy the files under ``url`` into the local directory ``dst`` (created; files in it are replaced)."""
    dst.mkdir(parents=True, exist_ok=True)
    for name in list_files(url):
        out = dst.joinpath(*name.split("/"))
        out.parent.mkdir(parents=True, exist_ok=True)
        with replacing(out) as tmp:
            get_file(join(url, *name.split("/")), tmp)


@contextmanager
def staged_recording(url: str) -> Iterator[Path]:
    """A local, seekable copy of the recording at ``url`` (the file itself when it is local)."""
    if is_local(url):
        yield local_path(url)
        return
    with tempfile.TemporaryDirectory(prefix="slamreplay-rec-") as tmp:
        path = Path(tmp) / (url.rstrip("/").rsplit("/", 1)[-1] or "recording.mcap")
        get_file(url, path)
        yield path


@contextmanager
def staged_run_dir(url: str) -> Iterator[Path]:
    """A fresh local run directory for ``url``: the directory itself when local (a stale one is
    removed), else a temporary one whose files are uploaded to ``url`` however the run ends."""
    if is_local(url):
        path = local_path(url)
        if path.exists():
            shutil.rmtree(path)  # left by an attempt that a server stop interrupted
        path.parent.mkdir(parents=True, exist_ok=True)  # a fresh storage location has no runs/ yet
        yield path
        return
    with tempfile.TemporaryDirectory(prefix="slamreplay-run-") as tmp:
        path = Path(tmp) / "run"
        try:
            yield path
        finally:
            if path.is_dir():
                put_dir(path, url)
