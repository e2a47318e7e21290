"""`surfel batch`: many renders on a Dask distributed cluster, each identical to a `surfel render`.

A job is one `surfel render` invocation written as a dict of its option names (``input``,
``output``, ``method``, ``size``, ``azimuth``, ``depth``, ...; ``-`` or ``_`` alike). The dict is
turned back into the command's arguments and parsed by the `render` command itself, so a job
has exactly that command's defaults, validation and meaning, and the worker then runs the
same steps as the command (`open_input`, `make_camera`, `make_options`, `rendering.render`) and the
driver writes the files with the same `RenderResult.save`: the outputs are byte-identical to
rendering the jobs one by one. ``--turntable N`` makes the N jobs of `surfel turntable`'s orbit,
frame i at azimuth 360 i / N degrees (the cameras of `turntable.orbit_cameras`).

Execution (issue 9): an embedded `LocalCluster` of single-threaded worker processes, or a
running scheduler. OpenGL contexts belong to one thread of one process, so every worker
process renders on one dedicated thread of its own, whatever the Dask thread count; each
worker keeps the clouds it has loaded (keyed by path, size and modification time), so an input
is read and its normals/radii estimated once per worker (`rendering.complete` caches per cloud).
A job that raises is retried by Dask; an input the user must fix (a `SurfelError`) fails the job
at once, since a retry would fail the same way. Failures are listed in the summary, never
dropped. Dask is imported only here, inside the functions that need it: `import surfel` does not.
"""

from __future__ import annotations

import json
import os
import shlex
import threading
import time
from collections import OrderedDict
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from .errors import InputError, SurfelError

if TYPE_CHECKING:
    from .cloud import PointCloud
    from .result import RenderResult

INSTALL_HINT = "surfel batch needs the distributed extra: pip install 'surfel[distributed]'"
PATH_KEYS = ("input", "output", "depth", "normals", "stats", "opencv", "dump_passes")
OUTPUT_KEYS = ("output", "depth", "normals", "stats")
TURNTABLE_ELEVATION = 15.0  # `surfel turntable`'s default
CACHED_INPUTS = 4  # clouds kept per worker process


@dataclass(frozen=True)
class Job:
    """One render: `params` are the parsed `surfel render` parameters (paths absolute, so that
    workers started in another directory find them); `argv` the equivalent command line."""

    index: int
    params: dict
    argv: tuple[str, ...]


@dataclass
class JobOutcome:
    """What a worker returns: the result (only the buffers the job writes) or the error."""

    worker: str
    seconds: float
    loaded: bool = False
    result: RenderResult | None = None
    error: str | None = None


@dataclass
class Summary:
    """Where each job ran and how it went; `failed` maps job index to the error and the
    `surfel render` command that reruns that job alone."""

    cluster: str
    jobs: int
    seconds: float = 0.0
    done: int = 0
    failed: dict[int, dict] = field(default_factory=dict)
    workers: dict[str, dict] = field(default_factory=dict)

    def record(self, worker: str, outcome: JobOutcome | None, job: Job, error: str | None) -> None:
        row = self.workers.setdefault(worker, {"jobs": [], "failed": 0, "loads": 0, "seconds": 0.0, "render_ms": 0.0})
        row["jobs"].append(job.index)
        if outcome is not None:
            row["loads"] += int(outcome.loaded)
            row["seconds"] = round(row["seconds"] + outcome.seconds, 3)
            if outcome.result is not None:
                row["render_ms"] = round(row["render_ms"] + outcome.result.stats["ms"], 3)
        if error is None:
            self.done += 1
        else:
            row["failed"] += 1
            self.failed[job.index] = {"error": error, "command": shlex.join(("surfel", "render", *job.argv))}

    def as_dict(self) -> dict:
        return {"cluster": self.cluster, "jobs": self.jobs, "done": self.done, "seconds": round(self.seconds, 3),
                "failed": [{"job": i, **failure} for i, failure in sorted(self.failed.items())],
                "workers": {w: {**row, "jobs": sorted(row["jobs"])} for w, row in sorted(self.workers.items())}}

    def text(self) -> str:
        lines = [f"{self.done} of {self.jobs} jobs done in {self.seconds:.1f} s on {self.cluster}"]
        for worker, row in sorted(self.workers.items()):
            lines.append(f"  {worker}: {len(row['jobs'])} jobs ({row['failed']} failed), {row['loads']} input loads, "
                         f"{row['seconds']:.1f} s busy, {row['render_ms'] / 1000:.1f} s rendering")
        for i, failure in sorted(self.failed.items()):
            lines += [f"  job {i} failed: {failure['error']}", f"    rerun alone: {failure['command']}"]
        return "\n".join(lines)


# ---------------------------------------------------------------------------------------------
# Job specifications


def read_jobs_file(path) -> list[dict]:
    """A JSON or YAML (.yaml/.yml, needs PyYAML) list of job dicts."""
    path = Path(path)
    try:
        text = path.read_text()
    except (OSError, UnicodeDecodeError) as exc:
        raise SurfelError(f"{path}: cannot read the jobs file ({exc.strerror or exc})") from None
    if path.suffix.lower() in (".yaml", ".yml"):
        try:
            import yaml
        except ImportError:
            raise SurfelError(f"{path}: YAML jobs files need PyYAML: pip install 'surfel[distributed]'") from None
        try:
            jobs = yaml.safe_load(text)
        except yaml.YAMLError as exc:
            raise SurfelError(f"{path}: not valid YAML ({' '.join(str(exc).split())})") from None
    else:
        try:
            jobs = json.loads(text)
        except ValueError as exc:
            raise SurfelError(f"{path}: not valid JSON ({exc})") from None
    if not isinstance(jobs, list) or not jobs or not all(isinstance(job, dict) for job in jobs):
        raise SurfelError(f"{path}: a jobs file holds a non-empty list of jobs, "
                          "each a mapping of `surfel render` options")
    return jobs


def turntable_jobs(frames: int, output: str, *, input: str | None = None, demo: bool = False,
                   depth: str | None = None, normals: str | None = None, stats: str | None = None,
                   elevation: float = TURNTABLE_ELEVATION) -> list[dict]:
    """The `frames` jobs of a turntable: output names from patterns with ``{frame}`` (e.g.
    ``spot-{frame:03d}.png``), or the frame number appended to the file name."""
    jobs = []
    for i in range(frames):
        job = {"input": input, "demo": demo, "azimuth": 360.0 * i / frames, "elevation": elevation}
        for key, pattern in (("output", output), ("depth", depth), ("normals", normals), ("stats", stats)):
            if pattern is not None:
                job[key] = _frame_name(pattern, i, frames)
        jobs.append(job)
    return jobs


def _frame_name(pattern: str, i: int, frames: int) -> str:
    if "{" in pattern:
        try:
            return pattern.format(frame=i)
        except (KeyError, IndexError, ValueError) as exc:
            raise SurfelError(f"output pattern {pattern!r}: use {{frame}} or e.g. {{frame:03d}} ({exc})") from None
    path = Path(pattern)
    return str(path.with_name(f"{path.stem}-{i:0{max(3, len(str(frames - 1)))}d}{path.suffix}"))


def make_jobs(specs: list[dict], *, defaults: dict | None = None, where: str = "jobs") -> list[Job]:
    """Validate every job up front (one-line SurfelError naming `where` and the job index).

    `defaults` are options applying to every job that does not set them itself.
    """
    jobs = [_make_job(i, {**(defaults or {}), **spec}, f"{where}: job {i}") for i, spec in enumerate(specs)]
    owner: dict[str, int] = {}
    for job in jobs:
        for key in OUTPUT_KEYS:
            path = job.params[key]
            if path is not None and owner.setdefault(path, job.index) != job.index:
                raise SurfelError(f"{where}: job {job.index}: {key} {path} is also written by job {owner[path]}")
    return jobs


def _make_job(index: int, spec: dict, where: str) -> Job:
    import click

    from .cli import _floats, _size, make_options, render
    from .methods import get_method

    argv = _render_argv(spec, where)
    try:
        params = render.make_context("render", list(argv)).params
        _size(params["size"])
        make_options(params)
        for name in ("eye", "target", "up"):
            _floats(params[name], 3, f"--{name}")
    except click.ClickException as exc:
        raise SurfelError(f"{where}: {exc.format_message()}") from None
    if params["demo"] == (params["input"] is not None):
        raise SurfelError(f"{where}: give an input file or demo: true (not both)")
    try:
        method = get_method(params["method"])
    except SurfelError as exc:
        raise SurfelError(f"{where}: {exc}") from None
    if params["backend"] is not None and params["backend"] not in method.backends:
        raise SurfelError(f"{where}: method {method.name!r} has no {params['backend']!r} backend")
    for key in ("input", "opencv"):
        if params[key] is not None and not Path(params[key]).exists():
            raise SurfelError(f"{where}: {key} {params[key]}: no such file")
    params = {k: (os.path.abspath(v) if k in PATH_KEYS and v is not None else v) for k, v in params.items()}
    return Job(index, params, argv)


def _render_argv(spec: dict, where: str) -> tuple[str, ...]:
    """The `surfel render` arguments meaning what the job dict says."""
    from .cli import render

    options = {p.name: p for p in render.params if p.name != "help"}
    argv: list[str] = []
    positional: list[str] = []
    for key, value in spec.items():
        name = str(key).replace("-", "_")
        if name not in options:
            raise SurfelError(f"{where}: unknown option {key!r} (a job takes the options of `surfel render`)")
        param = options[name]
        if value is None:
            continue
        if param.param_type_name == "argument":
            positional = ["--", str(value)]
            continue
        flag = max(param.opts, key=len)
        if param.is_flag:
            if not isinstance(value, bool):
                raise SurfelError(f"{where}: {key} is true or false, got {value!r}")
            if param.secondary_opts:
                argv.append(flag if value else max(param.secondary_opts, key=len))
            elif value:
                argv.append(flag)
            continue
        if isinstance(value, (list, tuple)):
            value = ("x" if name == "size" else ",").join(str(v) for v in value)
        elif isinstance(value, (bool, dict)):
            raise SurfelError(f"{where}: {key} takes a value, got {value!r}")
        argv += [flag, str(value)]
    return tuple(argv + positional)


# ---------------------------------------------------------------------------------------------
# Worker side

_inputs: OrderedDict[tuple, PointCloud] = OrderedDict()
_gl_thread: ThreadPoolExecutor | None = None
_gl_thread_lock = threading.Lock()


def run_job(params: dict) -> JobOutcome:
    """Render one job on this worker (a Dask task); a SurfelError becomes a failed outcome."""
    try:
        from distributed import get_worker

        worker = get_worker().address
    except (ImportError, ValueError):
        worker = f"pid {os.getpid()}"
    global _gl_thread
    with _gl_thread_lock:
        if _gl_thread is None:  # OpenGL: one context, used from one thread, for the life of the process
            _gl_thread = ThreadPoolExecutor(max_workers=1, thread_name_prefix="surfel-render")
    start = time.perf_counter()
    try:
        result, loaded = _gl_thread.submit(_render, params).result()
    except SurfelError as exc:
        return JobOutcome(worker, time.perf_counter() - start, error=str(exc))
    return JobOutcome(worker, time.perf_counter() - start, loaded, result)


def _render(params: dict) -> tuple[RenderResult, bool]:
    """The body of `surfel render`, with the input cached per process."""
    from .cli import make_camera, make_options
    from .rendering import render

    cloud, loaded = _cached_input(params)
    result = render(cloud, make_camera(cloud, params), params["method"], backend=params["backend"],
                    options=make_options(params))
    # ship back only the buffers the job writes
    empty = np.empty((0, 0), np.float32)
    result = replace(result, depth=result.depth if params["depth"] else empty,
                     normals=result.normals if params["normals"] else empty)
    return result, loaded


def _cached_input(params: dict) -> tuple[PointCloud, bool]:
    """The job's cloud, loaded at most once per process while its file is unchanged."""
    from .cli import open_input

    if params["demo"]:
        key = ("demo",)
    else:
        try:
            st = os.stat(params["input"])
        except OSError as exc:  # a remote worker that does not share the driver's files
            raise InputError(params["input"], f"not readable on this worker ({exc.strerror})") from None
        key = (params["input"], st.st_size, st.st_mtime_ns)
    if key in _inputs:
        _inputs.move_to_end(key)
        return _inputs[key], False
    if params["demo"]:
        from .data import demo_cloud

        cloud = demo_cloud()
    else:
        cloud = open_input(params["input"])
    _inputs[key] = cloud
    while len(_inputs) > CACHED_INPUTS:
        _inputs.popitem(last=False)
    return cloud, True


# ---------------------------------------------------------------------------------------------
# Driver


def run_batch(jobs: list[Job], *, scheduler: str | None = None, workers: int | None = None, retries: int = 2,
              progress: bool | None = None) -> Summary:
    """Run `jobs` on a local cluster (`workers` processes) or the scheduler at `scheduler` (an
    address, or a scheduler file); write each job's files as it completes."""
    import contextlib
    import logging

    from tqdm import tqdm

    try:
        from distributed import Client, LocalCluster, as_completed
    except ImportError:
        raise SurfelError(INSTALL_HINT) from None
    start = time.perf_counter()
    with contextlib.ExitStack() as stack:
        if scheduler is None:
            n = workers or max(1, min(os.cpu_count() or 1, len(jobs)))
            cluster = stack.enter_context(LocalCluster(n_workers=n, threads_per_worker=1, processes=True,
                                                       dashboard_address=None, silence_logs=logging.CRITICAL))
            client = stack.enter_context(Client(cluster))
            name = f"local cluster of {n} worker processes"
        else:
            try:
                if Path(scheduler).is_file():
                    client = stack.enter_context(Client(scheduler_file=scheduler, timeout="20s"))
                else:
                    client = stack.enter_context(Client(scheduler, timeout="20s"))
            except (OSError, TimeoutError, ValueError) as exc:
                raise SurfelError(f"cannot reach the Dask scheduler {scheduler} ({exc})") from None
            name = f"scheduler {client.scheduler.address}"
        try:
            client.wait_for_workers(1, timeout=60)
        except TimeoutError:
            raise SurfelError(f"no Dask worker joined the {name} within 60 s") from None
        summary = Summary(name, len(jobs))
        futures = {client.submit(run_job, job.params, pure=False, retries=retries,
                                 key=f"surfel-job-{job.index}-{os.getpid()}-{time.time_ns()}"): job for job in jobs}
        bar = tqdm(as_completed(futures), total=len(jobs), desc="batch", unit="job", leave=False,
                   disable=None if progress is None else not progress)  # None: only on a terminal
        for future in bar:
            job = futures.pop(future)
            if future.status == "error":
                exc = future.exception()
                summary.record("(no worker finished it)", None, job,
                               f"{type(exc).__name__}: {exc} after {retries} retries")
                continue
            outcome = future.result()
            future.release()
            error = outcome.error
            if error is None:
                p = job.params
                try:
                    outcome.result.save(p["output"], depth=p["depth"], normals=p["normals"], stats=p["stats"])
                except OSError as exc:
                    error = f"cannot write {exc.filename}: {exc.strerror}"
            summary.record(outcome.worker, outcome, job, error)
    summary.seconds = time.perf_counter() - start
    return summary


__all__ = ["Job", "JobOutcome", "Summary", "make_jobs", "read_jobs_file", "run_batch", "run_job", "turntable_jobs"]
