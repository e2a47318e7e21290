"""`surfel batch`: job validation, and Dask runs giving the files of one-by-one `surfel render` calls."""

import json
import subprocess
import sys
import time
from dataclasses import replace

import numpy as np
import pytest

from conftest import invoke, requires_gl
from surfel.errors import SurfelError

SIZE = "128x128"


def write_jobs(path, jobs):
    path.write_text(json.dumps(jobs))
    return path


def pixels(path):
    from PIL import Image

    return np.asarray(Image.open(path))


def test_import_surfel_does_not_import_dask():
    code = "import surfel, surfel.cli, surfel.batch, sys; assert not {'dask', 'distributed'} & set(sys.modules)"
    subprocess.run([sys.executable, "-c", code], check=True, timeout=120)


@pytest.mark.parametrize("job, message", [
    ({"demo": True, "output": "a.png", "colour": "red"}, "unknown option 'colour'"),
    ({"input": "missing.ply", "output": "a.png"}, "input"),
    ({"demo": True}, "--output"),
    ({"demo": True, "output": "a.png", "size": "big"}, "size"),
    ({"demo": True, "output": "a.png", "method": "nope"}, "unknown method"),
    ({"demo": True, "output": "a.png", "backface-culling": "yes"}, "true or false"),
    ({"demo": True, "output": "a.png", "background": [2, 0, 0]}, "background"),
    ({"demo": True, "output": "first.png"}, "also written by job 0"),
])
def test_an_invalid_job_stops_the_batch_before_anything_runs(tmp_path, monkeypatch, job, message):
    monkeypatch.chdir(tmp_path)  # relative paths are taken from the current directory
    jobs = write_jobs(tmp_path / "jobs.json", [{"demo": True, "output": "first.png"}, job])
    result = invoke("batch", jobs)
    assert result.exit_code == 2
    assert "jobs.json: job 1: " in result.output and message in result.output
    assert len(result.output.strip().splitlines()) == 1
    assert not (tmp_path / "first.png").exists()


def test_jobs_file_must_be_a_list_of_mappings(tmp_path):
    (tmp_path / "jobs.yaml").write_text("demo: true\n")
    result = invoke("batch", tmp_path / "jobs.yaml")
    assert result.exit_code == 2 and "non-empty list" in result.output


def test_a_job_means_what_the_same_render_flags_mean(tmp_path, monkeypatch):
    """The YAML job's request is the one `surfel render` makes of the same flags."""
    from surfel.batch import make_jobs, read_jobs_file
    from surfel.cli import render
    from surfel.request import parse_render

    monkeypatch.chdir(tmp_path)
    (tmp_path / "jobs.yaml").write_text("- {demo: true, output: a.png, size: [96, 64], radius-scale: 1.5, "
                                        "method: object-space, eye: [0, 0, 3], per-pixel-normalization: false}\n")
    job, = make_jobs(read_jobs_file(tmp_path / "jobs.yaml"))
    flags = ["--demo", "-o", "a.png", "--size", "96x64", "--radius-scale", "1.5", "--method", "object-space",
             "--eye", "0,0,3", "--per-surfel-normalization"]
    expected = parse_render(render.make_context("render", flags).params).absolute()
    assert replace(job.request, argv=()) == replace(expected, argv=())
    assert job.request.options.params.normalization == "per-surfel" and job.request.camera.size == (96, 64)
    assert job.request.outputs.png == str(tmp_path / "a.png")
    rerun = parse_render(render.make_context("render", list(job.request.argv)).params).absolute()
    assert replace(rerun, argv=()) == replace(expected, argv=())  # the command that reruns the job alone


def test_turntable_jobs_have_the_cameras_of_surfel_turntable():
    from surfel.batch import make_jobs, turntable_jobs
    from surfel.data import demo_cloud
    from surfel.turntable import orbit_cameras

    cloud = demo_cloud()
    jobs = make_jobs(turntable_jobs(6, "f-{frame:02d}.png", demo=True), defaults={"size": "64x48"})
    assert [j.request.outputs.png.rsplit("/", 1)[1] for j in jobs] == [f"f-{i:02d}.png" for i in range(6)]
    for job, camera in zip(jobs, orbit_cameras(cloud, 6, size=(64, 48)), strict=True):
        assert np.array_equal(job.request.camera.camera(cloud).world_to_eye, camera.world_to_eye)


@requires_gl
def test_turntable_on_a_local_cluster_equals_separate_renders(tmp_path):
    pytest.importorskip("distributed")
    result = invoke("batch", "--demo", "--turntable", 4, "-o", tmp_path / "batch-{frame}.png", "--size", SIZE,
                    "--shading", "lambert", "--workers", 2, "--json")
    assert result.exit_code == 0, result.output
    summary = json.loads(result.output)
    assert summary["done"] == 4 and not summary["failed"]
    assert sum(len(w["jobs"]) for w in summary["workers"].values()) == 4
    assert sum(w["loads"] for w in summary["workers"].values()) == len(summary["workers"])  # once per worker
    for i in range(4):
        one = invoke("render", "--demo", "-o", tmp_path / f"one-{i}.png", "--size", SIZE, "--shading", "lambert",
                     "--azimuth", 90 * i, "--elevation", 15)
        assert one.exit_code == 0, one.output
        batched, alone = (pixels(tmp_path / f"{name}-{i}.png").astype(int) for name in ("batch", "one"))
        # the same picture up to rounding: from an empty numba cache, whose freshly compiled
        # kernels can round an edge's coverage otherwise than the cached ones, one sample of the
        # 2x2 of one pixel came out on the other side of an outline (32 levels of alpha)
        differ = (batched != alone).any(axis=-1)
        assert differ.sum() <= 4 and np.abs(batched - alone).max() <= 64


@requires_gl
def test_a_crashing_job_is_retried_then_reported_and_the_others_are_written(tmp_path):
    pytest.importorskip("distributed")
    from surfel.batch import make_jobs, run_batch

    good, other = make_jobs([{"demo": True, "output": str(tmp_path / f"{n}.png"), "size": "32x32"} for n in "ab"])
    # a field of view that is no number raises a TypeError on the worker, not a SurfelError
    broken = replace(other.request, camera=replace(other.request.camera, fov="wide"))
    summary = run_batch([good, replace(other, request=broken)], workers=1, retries=1, progress=False)
    assert summary.done == 1 and list(summary.failed) == [1]
    error = summary.failed[1]["error"]
    assert "after 1 retries" in error and "TypeError" in error
    assert (tmp_path / "a.png").exists() and not (tmp_path / "b.png").exists()


@pytest.fixture
def loopback_cluster(tmp_path):
    """A scheduler and two single-threaded workers, each its own process, on 127.0.0.1."""
    distributed = pytest.importorskip("distributed")
    scheduler_file = tmp_path / "scheduler.json"
    quiet = {"stdout": subprocess.DEVNULL, "stderr": subprocess.DEVNULL}
    procs = [subprocess.Popen([sys.executable, "-m", "distributed.cli.dask_scheduler", "--host", "127.0.0.1",
                               "--port", "0", "--no-dashboard", "--scheduler-file", str(scheduler_file)], **quiet)]
    try:
        deadline = time.monotonic() + 60
        while not scheduler_file.exists():
            assert time.monotonic() < deadline and procs[0].poll() is None, "the scheduler did not start"
            time.sleep(0.1)
        for _ in range(2):
            procs.append(subprocess.Popen([sys.executable, "-m", "distributed.cli.dask_worker", "--scheduler-file",
                                           str(scheduler_file), "--nthreads", "1", "--nworkers", "1",
                                           "--no-dashboard"], **quiet))
        with distributed.Client(scheduler_file=str(scheduler_file), timeout="30s") as client:
            client.wait_for_workers(2, timeout=60)
        yield scheduler_file
    finally:
        for proc in reversed(procs):
            proc.terminate()
        for proc in procs:
            try:
                proc.wait(timeout=20)
            except subprocess.TimeoutExpired:
                proc.kill()


@requires_gl
def test_jobs_on_a_separate_scheduler_and_two_workers(tmp_path, loopback_cluster):
    """Identical files to one-by-one renders; a corrupt input fails its job only, and is reported."""
    (tmp_path / "corrupt.obj").write_text("v 1 2\nv 0 0 0\nf 1 2 2\n")
    views = ["front", "left", "top", "iso"]
    jobs = [{"demo": True, "output": str(tmp_path / f"batch-{v}.png"), "view": v, "size": SIZE, "method": "points",
             "depth": str(tmp_path / f"batch-{v}.npy")} for v in views]
    jobs.insert(2, {"input": str(tmp_path / "corrupt.obj"), "output": str(tmp_path / "corrupt.png")})
    result = invoke("batch", write_jobs(tmp_path / "jobs.json", jobs), "--scheduler", loopback_cluster, "--json")
    assert result.exit_code == 1, result.output
    summary = json.loads(result.output)
    assert summary["done"] == 4 and [f["job"] for f in summary["failed"]] == [2]
    assert "corrupt.obj" in summary["failed"][0]["error"]
    assert summary["failed"][0]["command"].startswith("surfel render --output ")
    assert len(summary["workers"]) == 2 and summary["cluster"].startswith("scheduler tcp://127.0.0.1:")
    assert not (tmp_path / "corrupt.png").exists()
    for v in views:
        one = invoke("render", "--demo", "-o", tmp_path / f"one-{v}.png", "--view", v, "--size", SIZE,
                     "--method", "points", "--depth", tmp_path / f"one-{v}.npy")
        assert one.exit_code == 0, one.output
        assert (tmp_path / f"batch-{v}.png").read_bytes() == (tmp_path / f"one-{v}.png").read_bytes()
        assert (tmp_path / f"batch-{v}.npy").read_bytes() == (tmp_path / f"one-{v}.npy").read_bytes()


def test_batch_without_dask_says_how_to_install_it(monkeypatch):
    from surfel import batch

    monkeypatch.setitem(sys.modules, "distributed", None)  # makes `import distributed` fail
    with pytest.raises(SurfelError, match=r"surfel\[distributed\]"):
        batch.run_batch([])


def test_the_summary_counts_in_words():
    """One job, one input load: singular; several: plural."""
    from surfel.batch import Summary

    summary = Summary("a cluster", jobs=3, done=3, workers={
        "w1": {"jobs": [0, 2], "failed": 0, "loads": 2, "seconds": 0.5, "render_ms": 100.0},
        "w2": {"jobs": [1], "failed": 0, "loads": 1, "seconds": 0.4, "render_ms": 90.0}})
    lines = summary.text().splitlines()
    assert lines[0].startswith("3 of 3 jobs done")
    assert lines[1].startswith("  w1: 2 jobs (0 failed), 2 input loads,")
    assert lines[2].startswith("  w2: 1 job (0 failed), 1 input load,")
