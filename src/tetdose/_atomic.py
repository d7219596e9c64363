"""Atomic writes that never destroy input or foreign data.

Outputs appear whole or not at all: a temporary path in the same folder, renamed onto the target
only when the writer succeeds. Around that, every writer gets the same guards:

- an output that *is* an input, or a folder that *contains* one, is refused (inputs are declared
  per call with ``inputs=`` or for a whole command with :func:`output_policy`);
- a non-empty folder is replaced only if tetdose wrote it (it holds the marker file
  :data:`MARKER`), unless the caller allows it (``force=True``, or the CLI's ``--overwrite``
  through :func:`output_policy`);
- the current folder (``-o .``) or one of its parents is refused as an output folder;
- temporaries left by a killed run (``.NAME.PID-XXXX.part`` / ``.old`` beside the output, PID
  no longer running) are removed by the next write of the same output; a previous output caught
  between its two renames is put back first;
- OS failures (permission denied, read-only or full disk) become one-line :class:`OutputError`.
"""

from __future__ import annotations

import errno
import os
import re
import shutil
import tempfile
import time
from collections.abc import Callable, Iterable, Iterator, Sequence
from contextlib import contextmanager
from contextvars import ContextVar
from dataclasses import dataclass
from pathlib import Path

from tetdose.errors import OutputError

#: File written into every output folder: tetdose may replace a folder that holds it.
MARKER = ".tetdose-output"
#: Temporaries of the pre-PID naming (``.NAME.XXXXXXXX.part``) older than this are stale [s].
LEGACY_STALE_S = 600.0

PathLike = str | os.PathLike[str]


@dataclass(frozen=True)
class _Policy:
    inputs: tuple[Path, ...] = ()
    force: bool = False


_POLICY: ContextVar[_Policy] = ContextVar("tetdose_output_policy",
                                          default=_Policy())  # noqa: B039 - frozen


@contextmanager
def output_policy(*, inputs: Iterable[PathLike] = (), force: bool = False) -> Iterator[None]:
    """Within the block every atomic write refuses to touch ``inputs``; ``force`` lets it
    replace non-empty folders tetdose did not write (the CLI's ``--overwrite``)."""
    token = _POLICY.set(_Policy(tuple(_real(p) for p in inputs), force))
    try:
        yield
    finally:
        _POLICY.reset(token)


def check_output_file(path: PathLike, *, suffixes: Sequence[str] | None = None,
                      inputs: Iterable[PathLike] = (), what: str = "output") -> Path:
    """Validate a file output before any work; return it as an absolute path.

    ``suffixes``: accepted endings (case-insensitive, e.g. ``(".vtu", ".nii.gz")``).
    """
    target = Path(os.path.abspath(path))
    if target.is_dir():
        raise OutputError(f"{what} {path} is a folder; give a file name such as "
                          f"{Path(path) / ('out' + (suffixes[0] if suffixes else ''))}")
    if suffixes is not None and not target.name.lower().endswith(tuple(s.lower() for s in suffixes)):
        shown = ", ".join(suffixes[:6]) + (" …" if len(suffixes) > 6 else "")
        raise OutputError(f"{what} {path} has an unknown extension; end it with {shown}")
    _check_not_input(target, inputs, what, path)
    _check_parent(target, what)
    return target


def check_output_dir(path: PathLike, *, overwrite: bool = True, force: bool = False,
                     inputs: Iterable[PathLike] = (), what: str = "output folder",
                     owned: Callable[[Path], bool] | None = None) -> Path:
    """Validate a folder output before any work (see module docstring); return it absolute.

    ``owned(folder)`` may recognise a previous output by its contents (for folders that must
    hold nothing but their own files, e.g. a DICOM series), in place of the marker file.
    """
    target = Path(os.path.abspath(path))
    if target.exists() and not target.is_dir():
        raise OutputError(f"{what} {path} is an existing file; give a folder name (it is "
                          "created), or remove the file")
    cwd = Path(os.path.realpath(os.getcwd()))
    real = _real(target)
    if real == cwd or real in cwd.parents:
        raise OutputError(f"{what} {path} is the current folder (or holds it) and would be "
                          "replaced as a whole; give a new sub-folder, e.g. -o out")
    _check_not_input(target, inputs, what, path)
    if target.is_dir() and any(target.iterdir()):
        if not overwrite:
            raise OutputError(f"{what} {path} exists; remove it or choose another folder")
        ours = (target / MARKER).exists() or (owned is not None and owned(target))
        if not ours and not (force or _POLICY.get().force) and not _inside_temporary(target):
            raise OutputError(f"{what} {path} holds files tetdose did not write; choose a new "
                              "folder, or pass --overwrite to replace it as a whole")
    _check_parent(target, what)
    return target


@contextmanager
def atomic_write_file(path: PathLike, *, inputs: Iterable[PathLike] = ()) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; rename it onto ``path`` only if the block succeeds.

    The temporary name keeps the suffix of ``path`` so that writers choosing a format by
    extension (meshio, SimpleITK) pick the right one.
    """
    path = check_output_file(path, inputs=inputs)
    _make_parent(path)
    _clean_stale(path)
    suffix = "".join(path.suffixes[-2:])
    with _os_errors(path.parent):
        fd, tmp = tempfile.mkstemp(prefix=_temp_prefix(path), suffix=f".part{suffix}",
                                   dir=path.parent)
    os.close(fd)
    tmp_path = Path(tmp)
    try:
        yield tmp_path
        with _os_errors(path.parent):
            os.chmod(tmp_path, 0o666 & ~_umask())  # mkstemp creates 0600; give the usual mode
            os.replace(tmp_path, path)
    except BaseException:
        tmp_path.unlink(missing_ok=True)
        raise


@contextmanager
def atomic_write_dir(path: PathLike, *, overwrite: bool = True, force: bool = False,
                     inputs: Iterable[PathLike] = (), marker: bool = True,
                     owned: Callable[[Path], bool] | None = None) -> Iterator[Path]:
    """Yield a temporary folder beside ``path``; it replaces ``path`` only if the block succeeds.

    A failure (or Ctrl-C) removes the temporary folder, so no half-written series is left behind.
    An existing folder is replaced if it is empty or tetdose wrote it (``overwrite``; any folder
    with ``force``); the new folder gets the marker file :data:`MARKER` unless it is written
    inside another atomic folder (which carries it) or ``marker`` is false (then ``owned``
    recognises a previous output by its contents, see :func:`check_output_dir`).
    """
    path = check_output_dir(path, overwrite=overwrite, force=force, inputs=inputs, owned=owned)
    _make_parent(path)
    _clean_stale(path)
    with _os_errors(path.parent):
        tmp = Path(tempfile.mkdtemp(prefix=_temp_prefix(path), suffix=".part", dir=path.parent))
    try:
        yield tmp
        if marker and not _inside_temporary(path):
            (tmp / MARKER).write_text("written by tetdose; it may replace this folder as a whole\n")
        with _os_errors(path.parent):
            if path.exists():
                old = Path(tempfile.mkdtemp(prefix=_temp_prefix(path), suffix=".old",
                                            dir=path.parent))
                os.replace(path, old / "x")
                os.replace(tmp, path)
                shutil.rmtree(old, ignore_errors=True)
            else:
                os.replace(tmp, path)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise


def _real(p: PathLike) -> Path:
    return Path(os.path.realpath(os.fspath(p)))


def _check_not_input(target: Path, inputs: Iterable[PathLike], what: str, given: PathLike
                     ) -> None:
    real = _real(target)
    for p in (*(_real(i) for i in inputs), *_POLICY.get().inputs):
        if real == p:
            raise OutputError(f"{what} {given} is also an input; write to another path")
        if real in p.parents:
            raise OutputError(f"{what} {given} holds the input {p} and would replace it; "
                              "write to another folder")


def _check_parent(target: Path, what: str) -> None:
    """The nearest existing ancestor must be a writable folder."""
    parent = target.parent
    while not parent.exists() and parent != parent.parent:
        parent = parent.parent
    if not parent.is_dir():
        raise OutputError(f"cannot create {what} {target}: {parent} is a file, not a folder")
    if not os.access(parent, os.W_OK | os.X_OK):
        raise OutputError(f"cannot write in {parent} (permission denied); choose a folder you "
                          "can write to")


def _make_parent(path: Path) -> None:
    with _os_errors(path.parent):
        path.parent.mkdir(parents=True, exist_ok=True)


@contextmanager
def _os_errors(folder: Path) -> Iterator[None]:
    """Permission, read-only and full-disk failures → one-line :class:`OutputError`."""
    try:
        yield
    except OSError as exc:
        if exc.errno in (errno.EACCES, errno.EPERM):
            raise OutputError(f"cannot write in {folder} (permission denied); choose a folder "
                              "you can write to") from exc
        if exc.errno == errno.EROFS:
            raise OutputError(f"cannot write in {folder}: read-only file system; choose a "
                              "writable folder") from exc
        if exc.errno in (errno.ENOSPC, errno.EDQUOT):
            raise OutputError(f"no space left writing in {folder}; free some space or choose "
                              "another disk") from exc
        raise


def _temp_prefix(path: Path) -> str:
    return f".{path.name}.{os.getpid()}-"


def _stale_pattern(name: str) -> re.Pattern[str]:
    return re.compile(rf"^\.{re.escape(name)}\.(?:(?P<pid>\d+)-)?[A-Za-z0-9_]+\.(?P<kind>part|old)")


def _inside_temporary(path: Path) -> bool:
    """True if ``path`` lies inside another atomic write's temporary folder."""
    return any(re.match(r"^\..+\.\d+-[A-Za-z0-9_]+\.part$", p.name) for p in path.parents)


def _clean_stale(path: Path) -> None:
    """Remove temporaries of ``path`` left by runs that no longer exist (module docstring)."""
    pattern = _stale_pattern(path.name)
    try:
        entries = list(path.parent.iterdir())
    except OSError:
        return
    stale = []
    for entry in entries:
        m = pattern.match(entry.name)
        if m is None:
            continue
        if m["pid"] is not None:
            if _alive(int(m["pid"])):
                continue
        else:
            try:
                if time.time() - entry.lstat().st_mtime < LEGACY_STALE_S:
                    continue
            except OSError:
                continue
        stale.append((m["kind"], entry))
    for kind, entry in sorted(stale, key=lambda s: s[0] != "old"):  # restore before deleting
        if kind == "old" and (entry / "x").exists() and not path.exists():
            os.replace(entry / "x", path)  # killed between the two renames: put it back
        if entry.is_dir() and not entry.is_symlink():
            shutil.rmtree(entry, ignore_errors=True)
        else:
            entry.unlink(missing_ok=True)


def _alive(pid: int) -> bool:
    if pid == os.getpid():
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except (PermissionError, OverflowError):
        return True
    return True


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask
