"""Atomic writes that never destroy input or foreign data.

Outputs appear whole or not at all: a temporary path in the same folder, renamed onto the target
only when the writer succeeds. Around that, every writer gets the same guards:

- an output that *is* an input, a folder that *contains* one, or a path *inside* an input
  folder (a DICOM series folder would no longer read as one series) is refused (inputs are
  declared per call with ``inputs=`` or for a whole command with :func:`output_policy`);
- a non-empty folder is replaced only if tetdose wrote it (it holds the marker file
  :data:`MARKER`), unless the caller allows it (``force=True``, or the CLI's ``--overwrite``
  through :func:`output_policy`);
- the current folder (``-o .``) or one of its parents is refused as an output folder;
- temporaries left by a killed run (``.NAME.PID-XXXX.part`` / ``.old`` beside the output, PID
  no longer running) are removed by the next write of the same output; a previous output caught
  between its two renames is put back first;
- OS failures (permission denied, read-only or full disk) become one-line :class:`OutputError`;
  folders created for an output that then failed are removed again (no empty folders are left);
- within :func:`atomic_outputs` (the CLI wraps every command in it) the outputs of one command
  are **one set**: each is written to its temporary as usual, but the temporaries are renamed
  into place only when the whole command succeeded — a full disk on the second of four files
  leaves none of them;
- notes declared with :func:`record_note` (an allowed mismatch of inputs, the unit a mesh was
  read in) are added to every JSON record written (``*.json`` holding an object, except
  ``figures.json``, which holds figure data).
"""

from __future__ import annotations

import errno
import json
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
from typing import Any

from tetdose.errors import OutputError

#: File written into every output folder: tetdose may replace a folder that holds it.
MARKER = ".tetdose-output"
#: Temporaries of the pre-PID naming (``.NAME.XXXXXXXX.part``) older than this are stale [s].
LEGACY_STALE_S = 600.0

PathLike = str | os.PathLike[str]


#: JSON files that hold data, not a record: no notes are added to them.
DATA_JSON = ("figures.json",)


@dataclass(frozen=True)
class _Policy:
    inputs: tuple[Path, ...] = ()
    force: bool = False
    notes: dict[str, Any] | None = None  # record notes (mutable; None: not recording)


_POLICY: ContextVar[_Policy] = ContextVar("tetdose_output_policy",
                                          default=_Policy())  # noqa: B039 - frozen


@contextmanager
def output_policy(*, inputs: Iterable[PathLike] = (), force: bool = False) -> Iterator[None]:
    """Within the block every atomic write refuses to touch ``inputs`` (or to write inside an
    input folder); ``force`` lets it replace non-empty folders tetdose did not write (the CLI's
    ``--overwrite``); :func:`record_note` notes go into every JSON record written."""
    token = _POLICY.set(_Policy(tuple(_real(p) for p in inputs), force, {}))
    try:
        yield
    finally:
        _POLICY.reset(token)


def record_note(key: str, value: Any) -> None:  # noqa: ANN401 - any JSON value
    """Add ``key: value`` to every JSON record the current :func:`output_policy` block writes
    from now on (nothing outside such a block)."""
    notes = _POLICY.get().notes
    if notes is not None:
        notes[key] = value


def recorded_notes() -> dict[str, Any]:
    """The notes :func:`record_note` declared in the current block (a copy)."""
    return dict(_POLICY.get().notes or {})


@dataclass
class _Staged:
    """A finished temporary waiting for its rename (see :func:`atomic_outputs`)."""

    commit: Callable[[], None]
    discard: Callable[[], None]


_STAGED: ContextVar[list[_Staged] | None] = ContextVar("tetdose_staged_outputs", default=None)


@contextmanager
def atomic_outputs() -> Iterator[None]:
    """Make every output written in the block one atomic set (module docstring).

    Writes whose target lies inside another write's temporary folder are not staged (the folder
    carries them). An error (or Ctrl-C, SIGTERM) in the block removes every staged temporary and
    the folders created for them; a reader of an output written earlier in the same block must
    not expect it in place before the block ends.
    """
    staged: list[_Staged] = []
    token = _STAGED.set(staged)
    try:
        yield
    except BaseException:
        _STAGED.reset(token)
        for s in reversed(staged):
            s.discard()
        raise
    _STAGED.reset(token)
    for i, s in enumerate(staged):
        try:
            s.commit()
        except BaseException:
            for rest in reversed(staged[i + 1:]):
                rest.discard()
            raise


def _stage_or_run(path: Path, commit: Callable[[], None], discard: Callable[[], None]) -> None:
    """Run ``commit`` now, or stage it inside :func:`atomic_outputs`."""
    staged = _STAGED.get()
    if staged is None or _inside_temporary(path):
        commit()
    else:
        staged.append(_Staged(commit, discard))


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


def check_not_input(path: PathLike, *, inputs: Iterable[PathLike] = (), what: str = "output"
                    ) -> Path:
    """Refuse an output that is an input, holds one, or lies inside an input folder (the
    inputs of ``inputs`` and of the current :func:`output_policy`); return it absolute."""
    target = Path(os.path.abspath(path))
    _check_not_input(target, inputs, what, path)
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
    """Yield a temporary path beside ``path``; rename it onto ``path`` only if the block succeeds
    (inside :func:`atomic_outputs`: when that block succeeds).

    The temporary name keeps the suffix of ``path`` so that writers choosing a format by
    extension (meshio, SimpleITK) pick the right one.
    """
    path = check_output_file(path, inputs=inputs)
    created = _make_parent(path)
    _clean_stale(path)
    try:
        with _os_errors(path.parent):
            fd, tmp = tempfile.mkstemp(prefix=_temp_prefix(path), suffix=f".part{_suffix(path)}",
                                       dir=path.parent)
    except BaseException:
        _remove_empty(created)
        raise
    os.close(fd)
    tmp_path = Path(tmp)

    def discard() -> None:
        tmp_path.unlink(missing_ok=True)
        _remove_empty(created)

    def commit() -> None:
        try:
            with _os_errors(path.parent):
                _add_notes(tmp_path, path.name)
                os.chmod(tmp_path, 0o666 & ~_umask())  # mkstemp makes 0600; give the usual mode
                os.replace(tmp_path, path)
        except BaseException:
            discard()
            raise

    try:
        yield tmp_path
    except BaseException:
        discard()
        raise
    _stage_or_run(path, commit, discard)


@contextmanager
def atomic_write_dir(path: PathLike, *, overwrite: bool = True, force: bool = False,
                     inputs: Iterable[PathLike] = (), marker: bool = True,
                     owned: Callable[[Path], bool] | None = None) -> Iterator[Path]:
    """Yield a temporary folder beside ``path``; it replaces ``path`` only if the block succeeds
    (inside :func:`atomic_outputs`: when that block succeeds).

    A failure (or Ctrl-C) removes the temporary folder, so no half-written series is left behind.
    An existing folder is replaced if it is empty or tetdose wrote it (``overwrite``; any folder
    with ``force``); the new folder gets the marker file :data:`MARKER` unless it is written
    inside another atomic folder (which carries it) or ``marker`` is false (then ``owned``
    recognises a previous output by its contents, see :func:`check_output_dir`).
    """
    path = check_output_dir(path, overwrite=overwrite, force=force, inputs=inputs, owned=owned)
    created = _make_parent(path)
    _clean_stale(path)
    try:
        with _os_errors(path.parent):
            tmp = Path(tempfile.mkdtemp(prefix=_temp_prefix(path), suffix=".part",
                                        dir=path.parent))
    except BaseException:
        _remove_empty(created)
        raise

    def discard() -> None:
        shutil.rmtree(tmp, ignore_errors=True)
        _remove_empty(created)

    def commit() -> None:
        try:
            with _os_errors(path.parent):
                for record in sorted(tmp.rglob("*.json")):
                    _add_notes(record, record.name)
                if marker and not _inside_temporary(path):
                    (tmp / MARKER).write_text("written by tetdose; it may replace this folder "
                                              "as a whole\n")
                if path.exists():
                    old = Path(tempfile.mkdtemp(prefix=_temp_prefix(path), suffix=".old",
                                                dir=path.parent))
                    os.replace(path, old / "x")
                    os.replace(tmp, path)
                    shutil.rmtree(old, ignore_errors=True)
                else:
                    os.replace(tmp, path)
        except BaseException:
            discard()
            raise

    try:
        yield tmp
    except BaseException:
        discard()
        raise
    _stage_or_run(path, commit, discard)


def _suffix(path: Path) -> str:
    return "".join(path.suffixes[-2:])


def _add_notes(record: Path, name: str) -> None:
    """Merge the policy's notes into the JSON object in ``record`` (see :func:`record_note`)."""
    notes = _POLICY.get().notes
    if not notes or not name.lower().endswith(".json") or name in DATA_JSON:
        return
    try:
        doc = json.loads(record.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return
    if isinstance(doc, dict):
        doc.update(notes)
        record.write_text(json.dumps(doc, indent=2) + "\n", encoding="utf-8")


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
        if p in real.parents and p.is_dir():
            raise OutputError(f"{what} {given} lies inside the input folder {p} (tetdose never "
                              "writes into an input folder: a DICOM series there would no longer "
                              "read as one series); write outside it")


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


def _make_parent(path: Path) -> list[Path]:
    """Create the missing folders above ``path``; return them, deepest first."""
    missing = []
    parent = path.parent
    while not parent.exists() and parent != parent.parent:
        missing.append(parent)
        parent = parent.parent
    try:
        with _os_errors(path.parent):
            path.parent.mkdir(parents=True, exist_ok=True)
    except BaseException:
        _remove_empty(missing)
        raise
    return missing


def _remove_empty(folders: Sequence[Path]) -> None:
    """Remove ``folders`` (deepest first) while they are empty."""
    for folder in folders:
        try:
            folder.rmdir()
        except OSError:
            return


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
