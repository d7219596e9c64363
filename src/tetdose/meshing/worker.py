"""Run :func:`~tetdose.meshing.mmg.conforming_mesh` in a child process that can be stopped.

MMG is C code that installs its own signal handlers: Ctrl-C during a remesh printed MMG's own
message and exited 1, and SIGTERM could leave it deadlocked (SIGKILL needed). So the command
line meshes in a child: ``python -m tetdose.meshing.worker JOB RESULT FD``, in its own session
(the terminal's Ctrl-C reaches only the parent). The parent (:func:`mesh_in_child`):

- writes the job (label image, labels, sizes, options) to a private temporary folder;
- relays the child's progress events (JSON lines on a pipe) to ``on_progress``;
- on Ctrl-C, SIGTERM or any error, kills the child's whole process group with SIGKILL and waits
  for it (no orphan, no deadlock), then lets the interruption go on — nothing was written;
- on the child's end, returns the mesh, re-issues its warnings, or raises its error as the same
  :class:`~tetdose.errors.TetdoseError` class; a crash (MMG's segfault) becomes a one-line
  :class:`~tetdose.errors.MeshError` with MMG's last words instead of a dead process.
"""

from __future__ import annotations

import contextlib
import json
import os
import pickle
import select
import shutil
import signal
import subprocess
import sys
import tempfile
import warnings
from collections.abc import Callable, Iterable, Mapping
from pathlib import Path
from typing import Any

import tetdose.errors as errors
from tetdose.core.image import Image
from tetdose.core.mesh import TetMesh
from tetdose.errors import MeshError

#: Seconds between checks of the child while no event arrives.
POLL_S = 0.2


def mesh_in_child(labels: Image, label_ids: Iterable[int] | None,
                  size_mm: float | Mapping[int, float] | None, *, smoothing_vox: float,
                  budget: Any = None,  # noqa: ANN401 - mmg.Budget
                  on_progress: Callable[[str, dict[str, Any]], None] | None = None) -> TetMesh:
    """:func:`~tetdose.meshing.mmg.conforming_mesh` of the same arguments, in a child process
    (module docstring)."""
    work = Path(tempfile.mkdtemp(prefix="tetdose-mesh-"))
    read_fd = write_fd = -1
    proc = None
    try:
        job, result = work / "job.pickle", work / "result.pickle"
        with open(job, "wb") as f:
            pickle.dump({"labels": labels, "label_ids": None if label_ids is None
                         else [int(v) for v in label_ids], "size_mm": size_mm,
                         "smoothing_vox": smoothing_vox, "budget": budget}, f)
        read_fd, write_fd = os.pipe()
        env = dict(os.environ)
        root = str(Path(__file__).resolve().parents[2])  # the folder holding tetdose/
        env["PYTHONPATH"] = os.pathsep.join(p for p in (root, env.get("PYTHONPATH", "")) if p)
        with open(work / "output.log", "wb") as log:
            proc = subprocess.Popen(
                [sys.executable, "-m", "tetdose.meshing.worker", str(job), str(result),
                 str(write_fd)], pass_fds=(write_fd,), start_new_session=True,
                stdin=subprocess.DEVNULL, stdout=log, stderr=log, env=env)
        os.close(write_fd)
        write_fd = -1
        _relay(proc, read_fd, on_progress)
        return _outcome(proc, result, work / "output.log")
    finally:
        if proc is not None and proc.poll() is None:
            _kill(proc)
        for fd in (read_fd, write_fd):
            if fd >= 0:
                os.close(fd)
        shutil.rmtree(work, ignore_errors=True)


def _kill(proc: subprocess.Popen) -> None:
    """SIGKILL the child's process group and reap it (MMG's handlers cannot delay SIGKILL)."""
    with contextlib.suppress(ProcessLookupError, PermissionError):
        os.killpg(proc.pid, signal.SIGKILL)
    with contextlib.suppress(ProcessLookupError):
        proc.kill()
    proc.wait()


def _relay(proc: subprocess.Popen, fd: int, on_progress: Callable | None) -> None:
    """Pass the child's events on until it ends (and the pipe is drained)."""
    buffer = b""
    while True:
        ready, _, _ = select.select([fd], [], [], POLL_S)
        if ready:
            chunk = os.read(fd, 65536)
            if not chunk:  # the child closed its end: it is ending
                proc.wait()
                return
            buffer += chunk
            *lines, buffer = buffer.split(b"\n")
            for line in lines:
                event = json.loads(line)
                if on_progress is not None:
                    on_progress(event["event"], event["info"])
        elif proc.poll() is not None:
            return


def _outcome(proc: subprocess.Popen, result: Path, log: Path) -> TetMesh:
    """The mesh, or the child's error / crash as a TetdoseError."""
    if result.exists():
        with open(result, "rb") as f:
            out = pickle.load(f)  # noqa: S301 - our own child's file in our private folder
        for message in out.get("warnings", []):
            warnings.warn(message, stacklevel=3)
        if "error" in out:
            kind, message = out["error"]
            cls = getattr(errors, kind, MeshError)
            raise (cls if isinstance(cls, type) and issubclass(cls, errors.TetdoseError)
                   else MeshError)(message)
        points, tets, region = out["mesh"]
        return TetMesh(points, tets, region)
    code = proc.returncode
    said = [ln for ln in log.read_text(errors="replace").splitlines() if ln.strip()]
    how = (f"signal {-code} ({signal.Signals(-code).name})" if code is not None and code < 0
           else f"exit code {code}")
    last = f"; its last words: {' '.join(said[-1].split())[:200]}" if said else ""
    raise MeshError(f"the mesher (MMG) died ({how}){last}; try other target sizes (--size-mm), "
                    "fewer labels (--label) or --mesher gmsh")


def _child(job: Path, result: Path, fd: int) -> int:
    """The child's side: mesh the job, write the result (or the error), events on ``fd``."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)
    from tetdose.meshing.mmg import conforming_mesh

    with open(job, "rb") as f:
        spec = pickle.load(f)  # noqa: S301 - written by our parent in its private folder
    events = os.fdopen(fd, "w", buffering=1)

    def progress(event: str, info: dict[str, Any]) -> None:
        events.write(json.dumps({"event": event, "info": _jsonable(info)}) + "\n")

    out: dict[str, Any] = {}
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            mesh = conforming_mesh(spec["labels"], spec["label_ids"], spec["size_mm"],
                                   smoothing_vox=spec["smoothing_vox"], budget=spec["budget"],
                                   progress=progress)
            out["mesh"] = (mesh.points_mm, mesh.tets, mesh.region)
        except errors.TetdoseError as exc:
            out["error"] = (type(exc).__name__, str(exc))
    out["warnings"] = list(dict.fromkeys(str(w.message) for w in caught
                                         if issubclass(w.category, UserWarning)))
    tmp = result.with_suffix(".part")
    with open(tmp, "wb") as f:
        pickle.dump(out, f)
    os.replace(tmp, result)
    events.close()
    return 0


def _jsonable(info: dict[str, Any]) -> dict[str, Any]:
    out = {}
    for key, value in info.items():
        if hasattr(value, "_asdict"):
            value = dict(value._asdict())
        out[key] = value
    return out


if __name__ == "__main__":
    sys.exit(_child(Path(sys.argv[1]), Path(sys.argv[2]), int(sys.argv[3])))
