"""`surfel batch`: many renders on a Dask distributed cluster, each identical to a `surfel render`.

A job is one `surfel render` invocation written as a dict of its option names (``input``,
``output``, ``method``, ``size``, ``azimuth``, ``depth``, ...; ``-`` or ``_`` alike). It is
parsed by `request.parse_render`, the parser of the `render` command's own flags, so a job has
exactly that command's defaults, validation and meaning; the worker then runs the same steps
as the command (`RenderRequest.render`) and the driver writes the files with the same
`RenderRequest.write`: the outputs are byte-identical to rendering the jobs one by one.
``--turntable N`` makes the N jobs of `surfel turntable`'s orbit, frame i at azimuth
360 i / N degrees (the cameras of `turntable.orbit_cameras`), named by a {frame} pattern, a
number before the extension, or FOLDER/000.png ... for a folder.

Execution (issue 9): an embedded `LocalCluster` of single-threaded worker processes, or a
running scheduler. OpenGL contexts belong to one thread of one process, so every worker
process renders on one dedicated thread of its own, whatever the Dask thread count, with its
own Renderer (`Worker`); it keeps the clouds it has loaded (keyed by path, size and
modification time), so an input is read and its normals/radii estimated once per worker.
A job whose output locations cannot be written is reported failed before it runs, and the
others go on. A job that raises is retried by Dask; an input the user must fix (a
`SurfelError`) fails the job at once, since a retry would fail the same way. Failures are
listed in the summary, never dropped. Dask is imported only here, inside the functions that
need it: `import surfel` does not.
"""

from __future__ import annotations

import json
import os
import shlex
import string
import threading
import time
from collections import OrderedDict
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from .errors import InputError, SurfelError
from .rendering import Renderer
from .request import TURNTABLE_ELEVATION, RenderRequest, parse_render

if TYPE_CHECKING:
    from .cloud import PointCloud
    from .result import RenderResult

INSTALL_HINT = "surfel batch needs the distributed extra: pip install 'surfel[distributed]'"
CACHED_INPUTS = 4  # clouds kept per worker process
EXTENSIONS = {"output": ".png", "depth": ".npy", "normals": ".npy", "stats": ".json"}


@dataclass(frozen=True)
class Job:
    """One render: the parsed request (paths absolute, so that workers started in another
    directory find them); `request.argv` is the equivalent command line."""

    index: int
    request: RenderRequest


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
            self.failed[job.index] = {"error": error, "command": shlex.join(("surfel", "render", *job.request.argv))}

    def as_dict(self) -> dict:
        return {"cluster": self.cluster, "jobs": self.jobs, "done": self.done, "seconds": round(self.seconds, 3),
                "failed": [{"job": i, **failure} for i, failure in sorted(self.failed.items())],
                "workers": {w: {**row, "jobs": sorted(row["jobs"])} for w, row in sorted(self.workers.items())}}

    def text(self) -> str:
        lines = [f"{self.done} of {_count(self.jobs, 'job')} done in {self.seconds:.1f} s on {self.cluster}"]
        for worker, row in sorted(self.workers.items()):
            lines.append(f"  {worker}: {_count(len(row['jobs']), 'job')} ({row['failed']} failed), "
                         f"{_count(row['loads'], 'input load')}, {row['seconds']:.1f} s busy, "
                         f"{row['render_ms'] / 1000:.1f} s rendering")
        for i, failure in sorted(self.failed.items()):
            lines += [f"  job {i} failed: {failure['error']}", f"    rerun alone: {failure['command']}"]
        return "\n".join(lines)


def _count(n: int, noun: str) -> str:
    return f"{n} {noun}" if n == 1 else f"{n} {noun}s"


# ---------------------------------------------------------------------------------------------
# Job specifications


def read_jobs_file(path) -> list[dict]:
    """A JSON or YAML (.yaml/.yml, needs PyYAML) list of job dicts."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as exc:
        raise SurfelError(f"{path}: cannot read the jobs file ({exc.strerror or exc})") from None
    except UnicodeDecodeError as exc:
        raise SurfelError(f"{path}: the jobs file is not UTF-8 text (byte {exc.start})") from None
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
    """The `frames` jobs of a turntable, their files named by `frame_names`."""
    names = {key: frame_names(pattern, frames, key) for key, pattern in
             (("output", output), ("depth", depth), ("normals", normals), ("stats", stats)) if pattern is not None}
    return [{"input": input, "demo": demo, "azimuth": 360.0 * i / frames, "elevation": elevation,
             **{key: files[i] for key, files in names.items()}} for i in range(frames)]


def frame_names(pattern: str, frames: int, key: str = "output") -> list[str]:
    """The file of each frame: a pattern with {frame} (e.g. spot-{frame:03d}.png); an existing
    folder, or a name ending in a separator, gets FOLDER/000.png ...; a name with an extension
    gets the frame number before it (spot.png: spot-000.png ...)."""
    label, extension = f"--{key}", EXTENSIONS[key]
    digits = max(3, len(str(frames - 1)))
    if "{" in pattern or "}" in pattern:
        check_frame_pattern(pattern, label)
        return [pattern.format(frame=i) for i in range(frames)]
    if os.path.isdir(pattern) or pattern.endswith(("/", os.sep)):
        return [os.path.join(pattern, f"{i:0{digits}d}{extension}") for i in range(frames)]
    path = Path(pattern)
    if not path.suffix:
        raise SurfelError(f"{label} {pattern}: no such folder; give an existing folder, or a name with "
                          f"{{frame}} or an extension (e.g. {pattern}-{{frame:03d}}{extension})")
    return [str(path.with_name(f"{path.stem}-{i:0{digits}d}{path.suffix}")) for i in range(frames)]


def check_frame_pattern(pattern: str, label: str) -> None:
    """A pattern's only field is {frame}, with an integer format (no attributes, no indexing)."""
    usage = f"{label} {pattern!r}: use {{frame}} or e.g. {{frame:03d}}"
    try:
        fields = [(name, spec) for _, name, spec, _ in string.Formatter().parse(pattern) if name is not None]
    except ValueError as exc:
        raise SurfelError(f"{usage} ({exc})") from None
    if not fields:
        raise SurfelError(usage)
    for name, spec in fields:
        if name != "frame":
            raise SurfelError(f"{usage}, not {{{name}}}")
        try:
            format(0, spec)
        except ValueError as exc:
            raise SurfelError(f"{usage} ({exc})") from None


def make_jobs(specs: list[dict], *, defaults: dict | None = None, where: str = "jobs") -> list[Job]:
    """Parse and check every job up front (one-line SurfelError naming `where` and the job index).

    `defaults` are options applying to every job that does not set them itself.
    """
    def keyed(mapping):
        return {str(key).replace("-", "_"): value for key, value in mapping.items()}

    base = {key: value for key, value in keyed(defaults or {}).items() if value is not None}
    jobs = [Job(i, _parse_job({**base, **keyed(spec)}, f"{where}: job {i}: ")) for i, spec in enumerate(specs)]
    owner: dict[str, int] = {}
    for job in jobs:
        for path in job.request.outputs.named().values():
            if owner.setdefault(path, job.index) != job.index:
                raise SurfelError(f"{where}: job {job.index}: {path} is also written by job {owner[path]}")
    return jobs


def _parse_job(spec: dict, where: str) -> RenderRequest:
    request = parse_render(spec, where=where)
    if request.input is not None and not Path(request.input).exists():
        raise SurfelError(f"{where}input {request.input}: no such file")
    return request.absolute()


def batch_command(jobs, *, defaults: dict, turntable: int | None, demo: bool, outputs: dict,
                  scheduler: str | None, workers: int | None, retries: int) -> Summary:
    """`surfel batch`: the jobs of a file, or of a turntable, run; the summary."""
    given = {key: value for key, value in defaults.items() if value is not None}
    if turntable is None:
        if demo or any(outputs.values()):
            raise SurfelError("--demo, -o, --depth, --normals and --stats go with --turntable; "
                              "jobs name their outputs")
        if jobs is None:
            raise SurfelError("give a JOBS file, or an input with --turntable N")
        specs, where = read_jobs_file(jobs), jobs
    else:
        if demo == (jobs is not None):
            raise SurfelError("with --turntable give an input file or --demo (not both)")
        if outputs["output"] is None:
            raise SurfelError("--turntable needs -o/--output")
        fixed = sorted({"view", "azimuth", "eye", "opencv"} & set(given))
        if fixed:
            raise SurfelError(f"--turntable sets the camera; drop --{', --'.join(fixed)}")
        specs = turntable_jobs(turntable, outputs["output"], input=jobs, demo=demo, depth=outputs["depth"],
                               normals=outputs["normals"], stats=outputs["stats"],
                               elevation=given.pop("elevation", TURNTABLE_ELEVATION))
        where = "turntable"
    return run_batch(make_jobs(specs, defaults=given, where=where), scheduler=scheduler, workers=workers,
                     retries=retries)


# ---------------------------------------------------------------------------------------------
# Worker side


class Worker:
    """What a worker process keeps from job to job: the one thread that renders (an OpenGL
    context belongs to one thread), its Renderer, and the inputs it has loaded."""

    def __init__(self):
        self.thread = ThreadPoolExecutor(max_workers=1, thread_name_prefix="surfel-render")
        # the workers fill the cores: a helper compiling ahead would only compete with them
        self.renderer = Renderer(compile_ahead=False)
        self.inputs: OrderedDict[tuple, PointCloud] = OrderedDict()

    def render(self, request: RenderRequest) -> tuple[RenderResult, bool]:
        """The body of `surfel render`, with the input cached (runs on the render thread)."""
        cloud, loaded = self.input(request)
        result = request.render(self.renderer, cloud)
        # ship back only the buffers the job writes
        empty = np.empty((0, 0), np.float32)
        outputs = request.outputs
        result = replace(result, depth=result.depth if outputs.depth else empty,
                         normals=result.normals if outputs.normals else empty)
        return result, loaded

    def input(self, request: RenderRequest) -> tuple[PointCloud, bool]:
        """The job's cloud, loaded at most once per process while its file is unchanged."""
        if request.demo:
            key = ("demo",)
        else:
            try:
                st = os.stat(request.input)
            except OSError as exc:  # a remote worker that does not share the driver's files
                raise InputError(request.input, f"not readable on this worker ({exc.strerror})") from None
            key = (request.input, st.st_size, st.st_mtime_ns, request.sensor)
        if key in self.inputs:
            self.inputs.move_to_end(key)
            return self.inputs[key], False
        cloud = self.inputs[key] = request.open_input()
        while len(self.inputs) > CACHED_INPUTS:
            self.inputs.popitem(last=False)
        return cloud, True


_worker: Worker | None = None  # this process's, made by its first job
_worker_lock = threading.Lock()


def run_job(request: RenderRequest) -> JobOutcome:
    """Render one job on this worker (a Dask task); a SurfelError becomes a failed outcome."""
    global _worker
    try:
        from distributed import get_worker

        address = get_worker().address
    except (ImportError, ValueError):
        address = f"pid {os.getpid()}"
    with _worker_lock:
        if _worker is None:
            _worker = Worker()
    start = time.perf_counter()
    try:
        result, loaded = _worker.thread.submit(_worker.render, request).result()
    except SurfelError as exc:
        return JobOutcome(address, time.perf_counter() - start, error=str(exc))
    return JobOutcome(address, time.perf_counter() - start, loaded, result)


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
        runnable = []
        for job in jobs:  # a job that could not write its files is not run; the others are
            try:
                job.request.check_outputs()
                runnable.append(job)
            except SurfelError as exc:
                summary.record("(not run)", None, job, str(exc))
        futures = {client.submit(run_job, job.request, pure=False, retries=retries,
                                 key=f"surfel-job-{job.index}-{os.getpid()}-{time.time_ns()}"): job
                   for job in runnable}
        bar = tqdm(as_completed(futures), total=len(futures), desc="batch", unit="job", leave=False,
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
                try:
                    job.request.write(outcome.result)
                except SurfelError as exc:
                    error = str(exc)
            summary.record(outcome.worker, outcome, job, error)
    summary.seconds = time.perf_counter() - start
    return summary


__all__ = ["Job", "JobOutcome", "Summary", "Worker", "batch_command", "frame_names", "make_jobs", "read_jobs_file",
           "run_batch", "run_job", "turntable_jobs"]
