"""Outputs that never destroy inputs and never leave a fragment (issue 27).

* :func:`atomic_write` writes a file under a unique temporary name in the target's folder
  (``tempfile.mkstemp``), fsyncs it and renames it over the target with ``os.replace``: a reader sees the
  old file or the new one, never a part.  Any failure (disk full, file too large, a signal) removes the
  temporary file and leaves the previous output as it was; an ``OSError`` becomes a one-line
  :class:`~rflscm.errors.DataError`.  Two runs writing one path each write their own temporary file, so
  both complete whole and the last rename wins.
* :func:`guard_outputs` runs at the top of a command, before any work: an output that resolves (symlinks,
  hard links) to one of the command's inputs is refused, an existing output is kept unless ``--force``
  (or ``--resume``) says otherwise, and each output's folder is probed by creating and removing a
  temporary file there (a read-only disk, ``/proc``, a missing permission fail now, not after the work).
"""

from __future__ import annotations

import contextlib
import os
import stat
import tempfile
import zipfile
from collections.abc import Callable, Iterable, Mapping
from pathlib import Path

from rflscm.errors import ConfigError, DataError

TEMP_SUFFIX = ".tmp"


def _reason(exc: OSError) -> str:
    return exc.strerror or type(exc).__name__


def temp_name(path: Path) -> tuple[int, Path]:
    """A new, unique temporary file next to ``path`` (open descriptor, path); an ``OSError`` if the folder
    cannot take one."""
    fd, name = tempfile.mkstemp(prefix=f".{path.name}.{os.getpid()}.", suffix=TEMP_SUFFIX, dir=path.parent)
    return fd, Path(name)


def discard_stale_temps(path: str | Path | None) -> list[Path]:
    """Remove the temporary files of writes to ``path`` whose process is gone (kill -9 during a save), and the
    fixed-name ``<path>.tmp`` of older versions; a temporary file of a live process (a concurrent run on the
    same output) is left alone.  Returns the files removed."""
    if path is None:
        return []
    path = Path(path)
    removed: list[Path] = []
    candidates = [path.with_name(path.name + TEMP_SUFFIX)]
    with contextlib.suppress(OSError):
        candidates += list(path.parent.glob(f".{glob_escape(path.name)}.*{TEMP_SUFFIX}"))
    for tmp in candidates:
        pid = tmp.name[len(path.name) + 2 :].split(".", 1)[0] if tmp.name.startswith(".") else ""
        if pid.isdigit() and _alive(int(pid)):
            continue
        with contextlib.suppress(OSError):
            if tmp.is_file():
                tmp.unlink()
                removed.append(tmp)
    return removed


def is_zip_archive(path: str | Path) -> bool:
    """Whether ``path`` looks like a zip archive (a PyTorch file); False for a damaged one whose end record
    ``zipfile.is_zipfile`` itself chokes on (``BadZipFile``: a flipped byte can make it claim several disks).
    Raises ``OSError`` when the file cannot be read."""
    try:
        return zipfile.is_zipfile(path)
    except zipfile.BadZipFile:
        return False


def glob_escape(name: str) -> str:
    return "".join(f"[{c}]" if c in "*?[" else c for c in name)


def _alive(pid: int) -> bool:
    if pid == os.getpid():
        return False  # this process is not writing while it cleans up
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def atomic_write(path: str | Path, write_fn: Callable[[Path], object], what: str = "output") -> Path:
    """Call ``write_fn(temporary path)``, fsync the file and rename it to ``path`` atomically.

    ``write_fn`` writes the whole content to the path it is given (a file that exists, empty).  On any
    failure the temporary file is removed and ``path`` keeps its previous content; an ``OSError`` is a
    :class:`DataError` naming ``path`` and the reason (e.g. "No space left on device").
    """
    path = Path(path)
    if path.is_dir():
        raise DataError(f"{path}: is a folder; give the {what} a file name.")
    tmp: Path | None = None
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = temp_name(path)
        os.close(fd)
        write_fn(tmp)
        with open(tmp, "rb+") as f:
            os.fsync(f.fileno())
        os.replace(tmp, path)
        tmp = None
        with contextlib.suppress(OSError):  # the rename itself durable; not every file system allows it
            dir_fd = os.open(path.parent, os.O_RDONLY)
            try:
                os.fsync(dir_fd)
            finally:
                os.close(dir_fd)
    except OSError as exc:
        kept = "the previous file is kept" if path.exists() else "nothing was written"
        raise DataError(f"{path}: cannot write the {what} ({_reason(exc)}); {kept}.") from None
    finally:
        if tmp is not None:
            with contextlib.suppress(OSError):
                tmp.unlink()
    return path


def write_text_atomic(path: str | Path, text: str, what: str = "output") -> Path:
    """:func:`atomic_write` of UTF-8 text."""
    return atomic_write(path, lambda tmp: tmp.write_text(text, encoding="utf-8"), what)


def _same(a: Path, b: Path) -> bool:
    if os.path.realpath(a) == os.path.realpath(b):
        return True
    try:
        return a.exists() and b.exists() and os.path.samefile(a, b)
    except OSError:
        return False


def _inside(path: Path, folder: Path) -> bool:
    real, root = os.path.realpath(path), os.path.realpath(folder)
    return real == root or real.startswith(root.rstrip(os.sep) + os.sep)


def guard_outputs(
    outputs: Mapping[str, str | Path | None],
    inputs: Iterable[str | Path | None],
    force: bool = False,
    resume: bool = False,
    folders: Iterable[str] = (),
) -> None:
    """Check every output of a command before it does any work.

    ``outputs`` maps an option name (``--out``) to its path (None: not asked for); ``inputs`` are the files
    and folders the command reads (an input folder protects everything inside it).  Options named in
    ``folders`` are output folders (created if needed); the others are files.

    Raises:
        ConfigError: an output is an input (or inside an input folder), two outputs are the same file, an
            output exists and neither ``force`` nor ``resume`` is set, an output is not a regular file, or
            its folder cannot take a new file.
    """
    given = [Path(p) for p in inputs if p is not None]
    seen: dict[str, str] = {}
    for option, value in outputs.items():
        if value is None:
            continue
        path = Path(value).expanduser()
        for source in given:
            if _same(path, source) or (source.is_dir() and _inside(path, source)):
                raise ConfigError(
                    f"{option} {path}: is {'inside ' if not _same(path, source) else ''}an input of this command "
                    f"({source}); writing there would destroy it — choose another path."
                )
        key = os.path.realpath(path)
        if key in seen:
            raise ConfigError(f"{option} {path}: the same file as {seen[key]}; give each output its own path.")
        seen[key] = option
        if option in folders:
            _check_folder(path, option)
            continue
        _check_file(path, option, force or resume)


def _check_file(path: Path, option: str, replace: bool) -> None:
    try:
        st = path.stat()
    except FileNotFoundError:
        st = None
    except OSError as exc:
        raise ConfigError(f"{option} {path}: cannot be used ({_reason(exc)}).") from None
    if st is not None:
        if stat.S_ISDIR(st.st_mode):
            raise ConfigError(f"{option} {path}: is a folder; give a file name (e.g. {path / 'out'}…).")
        if not stat.S_ISREG(st.st_mode):
            raise ConfigError(f"{option} {path}: is not a regular file (a device, a pipe or a socket); give a file.")
        if not replace:
            raise ConfigError(f"{option} {path}: exists already; add --force to replace it (or choose another path).")
    _probe(path.parent, f"{option} {path}")


def _check_folder(path: Path, option: str) -> None:
    if path.exists() and not path.is_dir():
        raise ConfigError(f"{option} {path}: is a file; give a folder.")
    _probe(path, f"{option} {path}")


def _probe(folder: Path, label: str) -> None:
    """Create and remove a temporary file in ``folder``, or in its nearest existing ancestor when it does not
    exist yet (nothing is created for good): the writes that come later can succeed."""
    existing = Path(os.path.abspath(folder))
    while not existing.exists() and existing != existing.parent:
        existing = existing.parent
    if not existing.is_dir():
        raise ConfigError(f"{label}: {existing} is not a folder.")
    try:
        fd, tmp = temp_name(existing / "probe")
        os.close(fd)
        tmp.unlink()
    except OSError as exc:
        raise ConfigError(f"{label}: its folder cannot take a new file ({_reason(exc)}).") from None
