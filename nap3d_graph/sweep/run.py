"""Running a sweep: fields first, then every cell, on a local process pool or on Ray.

Layout of a sweep folder::

    DIR/sweep.yaml                    the specification, as given
    DIR/sweep.lock                    while a sweep writes here (its host and pid)
    DIR/fields/<field id>.pt          each field, with .report.json and .log.txt
    DIR/fields/<field id>.done.json   written last: the field is finished (or failed: error)
    DIR/cells/<cell id>/run/...       the cell's run folder (config.yaml, estimate.txt, ...)
    DIR/cells/<cell id>/log.txt       everything the cell printed
    DIR/cells/<cell id>/result.json   written last, atomically: the cell is finished
    DIR/cells/<cell id>/error.json    the cell failed twice (its error, never dropped)

Resuming is running the same command again: a field with its ``.done.json`` and a cell with
its ``result.json`` or ``error.json`` are finished and skipped (``retry_failed`` runs failed
cells again); anything else is started afresh. A lock keeps a second sweep out of a folder
while the first is alive; a lock left by a dead sweep on this host is taken over.

Each task runs the command line in-process (``nap3d_graph.cli.main``) on one core: torch and
OpenCV are held to one thread, and a Ray task asks Ray for one CPU, so two cells never share
a core. Data reach Ray workers by path: on a cluster, recordings and the sweep folder must be
on storage every node mounts at the same path.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import shutil
import socket
import time
import traceback
from pathlib import Path

from nap3d_graph.pools import THREAD_ENV
from nap3d_graph.progress import progress_bar
from nap3d_graph.textfiles import write_json_atomic

__all__ = ["run_sweep", "SweepLocked", "cell_status"]

log = logging.getLogger(__name__)


class SweepLocked(RuntimeError):
    """Another live sweep writes into the folder."""


# --- what runs in a worker ----------------------------------------------------------------


def _one_core() -> None:
    os.environ.update(THREAD_ENV)
    try:
        import torch

        torch.set_num_threads(1)
    except ImportError:
        pass
    import cv2

    cv2.setNumThreads(1)


def _cli(command, argv: list[str], log_path: Path) -> int:
    """``command(argv)`` (the command line's entry point: ``nap3d-graph ARGV``) in this
    process, its output appended to ``log_path``."""
    _one_core()
    with open(log_path, "a") as handle, contextlib.redirect_stdout(handle), contextlib.redirect_stderr(handle):
        logging.root.handlers.clear()  # the CLI configures logging to this cell's log, not the last one's
        handle.write("$ nap3d-graph " + " ".join(argv) + "\n")
        handle.flush()
        try:
            return command(argv)
        except SystemExit as exc:
            return int(exc.code or 0)
        except BaseException:
            handle.write(traceback.format_exc())
            return 1
        finally:
            logging.root.handlers.clear()


def _tail(path: Path, lines: int = 5) -> str:
    try:
        text = path.read_text(errors="replace").strip().splitlines()
    except OSError:
        return ""
    return " | ".join(t.strip() for t in text[-lines:] if t.strip())


def build_field(command, argv: list[str], pt: str) -> dict:
    """Worker task: train one field (twice at most); writes its ``.done.json``."""
    pt = Path(pt)
    log_path, done = pt.with_suffix(".log.txt"), pt.with_suffix(".done.json")
    t0 = time.perf_counter()
    for attempt in (1, 2):
        code = _cli(command, argv + ["--force"], log_path)
        if code == 0 and pt.is_file():
            result = {"status": "ok", "seconds": time.perf_counter() - t0, "attempts": attempt}
            write_json_atomic(done, result)
            return result
    result = {"status": "failed", "error": _tail(log_path) or f"exit {code}", "attempts": 2}
    write_json_atomic(done, result)
    return result


def run_cell(command, argv: list[str], cell_dir: str) -> dict:
    """Worker task: one run (twice at most); writes ``result.json`` or ``error.json``."""
    cell_dir = Path(cell_dir)
    log_path = cell_dir / "log.txt"
    t0 = time.perf_counter()
    code = 1
    for attempt in (1, 2):
        shutil.rmtree(cell_dir / "run", ignore_errors=True)  # what an interrupted attempt left
        code = _cli(command, argv, log_path)
        metrics_path = cell_dir / "run" / "latest" / "metrics.json"
        if code == 0 and metrics_path.is_file():
            result = {"status": "ok", "seconds": time.perf_counter() - t0, "attempts": attempt,
                      **_cell_metrics(json.loads(metrics_path.read_text()))}
            write_json_atomic(cell_dir / "result.json", result)
            return result
    result = {"status": "failed", "error": _tail(log_path) or f"exit {code}", "attempts": 2,
              "seconds": time.perf_counter() - t0}
    write_json_atomic(cell_dir / "error.json", result)
    return result


def _cell_metrics(metrics: dict) -> dict:
    """The figures a sweep tabulates from a run's metrics.json."""
    out = {"frames": metrics.get("frames"), "keyframes": metrics.get("keyframes"),
           "accepted": metrics.get("corrections_accepted")}
    for name, key in (("odometry", "ate_odometry_m"), ("estimate", "ate_estimate_m"), ("estimate_online", "ate_causal_m")):
        if name in metrics:
            out[key] = metrics[name]["ate_m"]["rmse"]
            if name == "estimate":
                out["ate_estimate_max_m"] = metrics[name]["ate_m"].get("max")
    return out


# --- pools ----------------------------------------------------------------------------------


# --- the sweep ------------------------------------------------------------------------------


@contextlib.contextmanager
def sweep_lock(folder: Path):
    """Hold ``folder/sweep.lock`` while the sweep writes (SweepLocked when a live one has it)."""
    lock = folder / "sweep.lock"
    me = {"host": socket.gethostname(), "pid": os.getpid()}
    try:
        fd = os.open(lock, os.O_CREAT | os.O_EXCL | os.O_WRONLY)
    except FileExistsError:
        try:
            holder = json.loads(lock.read_text())
        except (OSError, ValueError):
            holder = {}
        if holder.get("host") != me["host"] or _alive(int(holder.get("pid", -1))):
            raise SweepLocked(f"{folder}: another sweep writes here ({holder.get('host', '?')} pid "
                              f"{holder.get('pid', '?')}); wait for it, or remove {lock} if it is gone") from None
        log.warning("%s: taking over the lock of a sweep that is gone (pid %s)", folder, holder.get("pid"))
        lock.unlink(missing_ok=True)
        fd = os.open(lock, os.O_CREAT | os.O_EXCL | os.O_WRONLY)
    with os.fdopen(fd, "w") as handle:
        handle.write(json.dumps(me))
    try:
        yield
    finally:
        lock.unlink(missing_ok=True)


def _alive(pid: int) -> bool:
    if pid <= 0:
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def _read_json(path: Path) -> dict | None:
    """A task's status file, or None when it is absent (unfinished) or unreadable."""
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError):
        return None


def cell_status(folder: Path, cell) -> dict | None:
    """A cell's result.json or error.json, or None when it is not finished."""
    cell_dir = folder / "cells" / cell.id
    return _read_json(cell_dir / "result.json") or _read_json(cell_dir / "error.json")


def _field_path(folder: Path, task) -> Path:
    return folder / "fields" / f"{task.id}.pt"


def _field_done(folder: Path, task) -> dict | None:
    return _read_json(_field_path(folder, task).with_suffix(".done.json"))


def run_sweep(spec, folder, pool, command, progress: bool = True, retry_failed: bool = False) -> dict:
    """Run every unfinished field and cell of ``spec`` into ``folder`` on ``pool``; returns
    ``{"ran": n, "skipped": n, "failed": n, "fields_trained": n}``. ``command``: the command
    line's entry point, ``command(argv) -> exit code`` (``nap3d_graph.cli.main``; a module-level
    function, so a process or Ray worker can be handed it), which each field and cell runs."""
    folder = Path(folder)
    (folder / "fields").mkdir(parents=True, exist_ok=True)
    (folder / "cells").mkdir(parents=True, exist_ok=True)
    with sweep_lock(folder):
        if retry_failed:
            for cell in spec.cells():
                (folder / "cells" / cell.id / "error.json").unlink(missing_ok=True)
        fields = {t.id: t for t in spec.fields() if not t.untrained}
        todo_fields = [t for t in fields.values() if (_field_done(folder, t) or {}).get("status") != "ok"
                       or not _field_path(folder, t).is_file()]
        cells = spec.cells()
        todo = [c for c in cells if cell_status(folder, c) is None]
        counts = {"cells": len(cells), "skipped": len(cells) - len(todo), "ran": 0, "failed": 0,
                  "fields_trained": 0, "pool": pool.name, "workers": pool.workers}
        bar = progress_bar(total=len(todo_fields) + len(todo), desc="sweep", unit="task", disable=not progress,
                   postfix={"running": 0, "failed": 0})
        try:
            # Fields first: every run of a field waits for it, and a field is built once.
            pending = {pool.submit(build_field, command, t.argv(_field_path(folder, t)), str(_field_path(folder, t))): t
                       for t in todo_fields}
            _drain(pool, pending, bar, counts, field=True)
            pending = {}
            for cell in todo:
                cell_dir = folder / "cells" / cell.id
                cell_dir.mkdir(parents=True, exist_ok=True)
                (cell_dir / "log.txt").unlink(missing_ok=True)
                task = cell.field
                field_path = None if task.untrained else _field_path(folder, task)
                built = {} if field_path is None else (_field_done(folder, task) or {})
                if field_path is not None and built.get("status") != "ok":
                    error = built.get("error", "not built")
                    write_json_atomic(cell_dir / "error.json", {"status": "failed", "error": f"field {task.id} failed: {error}",
                                                          "attempts": 0})
                    counts["failed"] += 1
                    bar.update(1)
                    continue
                argv = cell.argv(field_path, cell_dir / "run")
                pending[pool.submit(run_cell, command, argv, str(cell_dir))] = cell
            _drain(pool, pending, bar, counts, field=False)
        finally:
            bar.close()
    return counts


def _drain(pool, pending: dict, bar, counts: dict, field: bool) -> None:
    """Wait for every submitted task, updating the bar (done, running, failed)."""
    waiting = list(pending)
    while waiting:
        bar.set_postfix(running=min(len(waiting), pool.workers), failed=counts["failed"])
        done, waiting = pool.wait_any(waiting)
        for future in done:
            try:
                result = pool.result(future)
            except Exception as exc:  # a lost worker: the cell has no file, a resume runs it again
                log.warning("task for %s did not return (%s): run the sweep again to redo it",
                            pending[future].id, str(exc).splitlines()[0] if str(exc) else type(exc).__name__)
                result = {"status": "failed"}
            failed = result.get("status") != "ok"
            if field:
                counts["fields_trained"] += not failed
                counts["fields_failed"] = counts.get("fields_failed", 0) + failed
            else:
                counts["ran"] += 1
                counts["failed"] += failed
            bar.update(1)
    bar.set_postfix(running=0, failed=counts["failed"])
