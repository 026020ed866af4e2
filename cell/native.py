"""C built on first use: the project's few hot loops that Python cannot run fast enough (the SnP
modules' cycle, the controller's loop model) are C sources beside their Python, compiled with the
system's C compiler (`cc`, or $CC) into a cache keyed by the sources' hash and loaded with ctypes
(a call releases the GIL).  Where no compiler works, NativeUnavailable says why and the Python
version runs instead."""

from __future__ import annotations

import ctypes
import hashlib
import os
import shutil
import subprocess
import tempfile
from collections.abc import Callable
from pathlib import Path

CFLAGS = ("-O2", "-shared", "-fPIC", "-Wall", "-Werror")


class NativeUnavailable(RuntimeError):
    """No C compiler, or the build failed: the message says which."""


def unavailable(load: Callable[[], object]) -> str:
    """ "" if load() builds (or finds) its library, else why not."""
    try:
        load()
    except NativeUnavailable as exc:
        return str(exc)
    return ""


def cache_dir() -> Path:
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "cell"


def build(name: str, sources: tuple[Path, ...], headers: tuple[Path, ...] = (), cflags=CFLAGS) -> ctypes.CDLL:
    """The library built from these sources (built now if its cached copy is missing; earlier builds
    of the same name are removed)."""
    source = b"".join(f.read_bytes() for f in (*sources, *headers))
    cc = os.environ.get("CC") or shutil.which("cc") or shutil.which("gcc") or shutil.which("clang")
    if cc is None:
        raise NativeUnavailable("no C compiler (cc, gcc or clang) on PATH")
    digest = hashlib.sha256(source + " ".join(cflags).encode()).hexdigest()[:16]
    out = cache_dir() / f"{name}-{digest}.so"
    if not out.exists():
        out.parent.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryDirectory(dir=out.parent) as tmp:
            so = Path(tmp) / out.name
            cmd = [cc, *cflags, "-o", str(so), *(str(f) for f in sources), "-lm"]
            done = subprocess.run(cmd, capture_output=True, text=True)
            if done.returncode != 0:
                names = ", ".join(f.name for f in sources)
                raise NativeUnavailable(f"{cc} failed on {names}: {done.stderr.strip()[:2000]}")
            os.replace(so, out)  # (atomic: another process building it at once is harmless)
        for old in out.parent.glob(f"{name}-*.so"):  # builds of earlier sources
            if old != out:
                old.unlink(missing_ok=True)
    return ctypes.CDLL(str(out))
