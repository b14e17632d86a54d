"""Files shared by every layer: atomic writes (a reader never sees a half-written file, and a failed write leaves
the previous file untouched; a write the disk refuses — full, read-only — is an OutputError naming the file) and
text reading that refuses binary input in one line."""

from __future__ import annotations

import errno
import os
import tempfile
from contextlib import contextmanager
from pathlib import Path

# mkstemp creates files 0600; a finished output should get the usual 0666 & ~umask. Read the umask once (setting
# it is process-wide, so not something to do on every write).
_UMASK = os.umask(0)
os.umask(_UMASK)
_FILE_MODE = 0o666 & ~_UMASK


@contextmanager
def atomic_path(path: str | os.PathLike):
    """Yield a temporary path beside `path`; on success it replaces `path` in one rename, on error it is removed."""
    path = Path(path)
    _check_writable_file(path)
    try:
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=path.suffix or ".tmp", dir=path.parent)
    except OSError as e:
        raise refused_write(path, e) from None
    os.close(fd)
    try:
        yield Path(tmp)
        os.chmod(tmp, _FILE_MODE)
        os.replace(tmp, path)
    except BaseException as e:
        try:
            os.unlink(tmp)
        except FileNotFoundError:
            pass
        if _refused(e):
            raise refused_write(path, e) from None  # the file the user knows, not the temporary one
        raise


# A write the disk refuses (as opposed to an OSError of something the caller reads while it writes).
_FULL = {errno.ENOSPC: "the disk is full", errno.EDQUOT: "the disk quota is used up"}
_REFUSED = {*_FULL, errno.EROFS, errno.EFBIG}


def _refused(e: BaseException) -> bool:
    from .errors import OutputError

    return isinstance(e, OSError) and not isinstance(e, OutputError) and e.errno in _REFUSED


def refused_write(path: str | os.PathLike, e: OSError):
    """The OutputError of a write of `path` that failed with `e`: one line naming the file and saying why ("the disk
    is full" for ENOSPC)."""
    from .errors import OutputError

    if isinstance(e, OutputError):
        return e
    why = e.strerror or str(e)
    if e.errno in _FULL:
        return OutputError(f"cannot write {path}: {_FULL[e.errno]} ({why})", full=True, errno=e.errno)
    return OutputError(f"cannot write {path}: {why}", errno=e.errno)


def _check_writable_file(path: Path) -> None:
    """Create `path`'s folder; InputError (one line naming the path) when `path` is a folder or lies under a file,
    before anything is written."""
    from .errors import InputError

    if path.is_dir():
        raise InputError(f"cannot write {path}: it is a folder, expected a file name")
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
    except (FileExistsError, NotADirectoryError):
        blocker = next((p for p in path.parents if p.exists() and not p.is_dir()), path.parent)
        raise InputError(f"cannot write {path}: {blocker} is a file, expected a folder") from None
    except OSError as e:  # a full disk, a read-only place
        raise refused_write(path, e) from None


def remove_leftovers(folder: str | os.PathLike, name: str = "*", suffix: str = "") -> None:
    """Remove the temporary files that `atomic_path` writes of `folder`/`name``suffix` (`name` may be a glob) and
    that a kill left behind (SIGKILL leaves no time to remove them). Only for a folder one process owns."""
    for stale in Path(folder).glob(f".{name}.*{suffix or '.tmp'}"):
        stale.unlink(missing_ok=True)


def atomic_write_text(path: str | os.PathLike, text: str) -> Path:
    with atomic_path(path) as tmp:
        tmp.write_text(text)
    return Path(path)


def atomic_write_bytes(path: str | os.PathLike, data: bytes) -> Path:
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)
    return Path(path)


def output_dir(path: str | os.PathLike, what: str = "output folder", *, create: bool = True) -> Path:
    """Create folder `path` (and its parents) for a run's outputs; InputError, naming `what`, when it is a file,
    lies under a file, or cannot be written. create=False: only check, creating nothing (the nearest existing
    folder must be writable)."""
    from .errors import InputError

    path = Path(path)
    for p in (path, *path.parents):
        if p.exists() and not p.is_dir():
            where = "" if p == path else f": {p}"
            raise InputError(f"{what} {path}{where} is a file, expected a folder")
        if p.exists():
            if not create and not os.access(p, os.W_OK | os.X_OK):
                why = "read-only file system" if _read_only_fs(p) else "permission denied"
                raise InputError(f"{what} {path}: cannot write in {p} ({why})")
            break
    if not create:
        return path
    try:
        path.mkdir(parents=True, exist_ok=True)
        fd, probe = tempfile.mkstemp(prefix=".write-test.", dir=path)
        os.close(fd)
        os.unlink(probe)
    except OSError as e:
        why = f": {_FULL[e.errno]} ({e.strerror})" if e.errno in _FULL else f" ({e.strerror or e})"
        raise InputError(f"{what} {path}: cannot write there{why}") from None
    return path


def _read_only_fs(path: Path) -> bool:
    try:
        return bool(os.statvfs(path).f_flag & os.ST_RDONLY)
    except (OSError, AttributeError):  # AttributeError: no statvfs (Windows)
        return False


def output_file(path: str | os.PathLike, what: str = "output file", *, create: bool = True) -> Path:
    """Check that file `path` can be written (its folder is created unless create=False); InputError naming
    `what` when it is a folder, lies under a file, or its folder cannot be written. `path` itself is not touched."""
    from .errors import InputError

    path = Path(path)
    if path.is_dir():
        raise InputError(f"{what} {path} is a folder, expected a file name")
    output_dir(path.parent, what=what, create=create)
    return path


def text_lines(path: str | os.PathLike, what: str):
    """(line number, line) of a UTF-8 text file, one at a time; InputError naming the file and line at the first
    bytes that are not text (an image or a binary file given where a `what` file belongs)."""
    from .errors import InputError

    with open(path, encoding="utf-8", errors="replace") as f:
        for lineno, line in enumerate(f, 1):
            if "\ufffd" in line:
                raise InputError(f"{path}:{lineno}: not a text {what} file (bytes that are not UTF-8 text)")
            yield lineno, line


def is_file(path: str | os.PathLike, where: str = "", *, folder: bool = False) -> bool:
    """Path.is_file() (is_dir() with `folder`) for a path read from a file or given by a user: a name the system
    refuses outright (longer than the file system allows, ...) is an InputError naming `where` (the file:line that
    listed it) and the reason, not an OSError from deep inside a loader; a path that does not exist is False."""
    from .errors import InputError

    p = Path(path)
    try:
        return p.is_dir() if folder else p.is_file()
    except OSError as e:
        raise InputError(f"{where + ': ' if where else ''}{'folder' if folder else 'file'} name cannot be used: "
                         f"{os.strerror(e.errno) if e.errno else e} ({str(p)[:120]}{'...' if len(str(p)) > 120 else ''})"
                         ) from None
