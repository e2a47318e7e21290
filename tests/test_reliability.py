"""Issue 15, the input side: outputs that are not regular files, image sizes beyond what
OpenGL allows, files whose sizes lie, corrupt LOD containers, degenerate meshes and
coordinates at the edges of float range. Each refusal is one line naming the file or option,
exit status 2, nothing written."""

import os
import socket
import stat

import pytest
from click.testing import CliRunner

from conftest import requires_gl
from surfel.cli import main
from surfel.errors import SurfelError
from surfel.files import write_atomically


def invoke(*args):
    return CliRunner().invoke(main, [str(a) for a in args], catch_exceptions=False)


def assert_refused(result, *words):
    """Exit status 2 and exactly one line, `surfel: error: ...`, holding `words`."""
    lines = result.output.strip().splitlines()
    assert result.exit_code == 2, result.output
    assert len(lines) == 1 and lines[0].startswith("surfel: error: "), result.output
    for word in words:
        assert word in lines[0], (word, lines[0])


# ---- 15.1: -o never replaces what is not a regular file ------------------------------------

def test_special_files_are_never_replaced(tmp_path):
    fifo = tmp_path / "pipe.png"
    os.mkfifo(fifo)
    with pytest.raises(SurfelError, match="pipe.png: cannot write: it exists and is a FIFO"):
        write_atomically(fifo, b"data")
    assert stat.S_ISFIFO(os.lstat(fifo).st_mode)
    (tmp_path / "folder.png").mkdir()
    with pytest.raises(SurfelError, match="is a directory"):
        write_atomically(tmp_path / "folder.png", b"data")
    with socket.socket(socket.AF_UNIX) as server:
        server.bind(str(tmp_path / "socket.png"))
        with pytest.raises(SurfelError, match="socket"):
            write_atomically(tmp_path / "socket.png", b"data")
    with pytest.raises(SurfelError, match="character device"):
        write_atomically("/dev/null", b"data")
    os.symlink(fifo, tmp_path / "to-pipe.png")
    with pytest.raises(SurfelError, match="FIFO"):
        write_atomically(tmp_path / "to-pipe.png", b"data")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["folder.png", "pipe.png", "socket.png", "to-pipe.png"]


def test_a_symbolic_link_is_written_through_and_kept(tmp_path):
    (tmp_path / "real").mkdir()
    target = tmp_path / "real" / "a.png"
    target.write_bytes(b"old")
    target.chmod(0o640)
    link = tmp_path / "link.png"
    os.symlink(target, link)
    write_atomically(link, b"new")
    assert link.is_symlink() and os.readlink(link) == str(target)
    assert target.read_bytes() == b"new" and stat.S_IMODE(target.stat().st_mode) == 0o640
    dangling = tmp_path / "dangling.png"
    os.symlink(tmp_path / "real" / "b.png", dangling)
    write_atomically(dangling, b"made")
    assert dangling.is_symlink() and (tmp_path / "real" / "b.png").read_bytes() == b"made"
    assert sorted(p.name for p in (tmp_path / "real").iterdir()) == ["a.png", "b.png"]  # no temporary left


def test_the_command_line_refuses_special_outputs_before_rendering(tmp_path):
    fifo = tmp_path / "out.png"
    os.mkfifo(fifo)
    assert_refused(invoke("render", "--demo", "-o", fifo, "--size", "32x32"), "out.png", "FIFO")
    assert_refused(invoke("render", "--demo", "-o", tmp_path / "x.png", "--stats", "/dev/null", "--size", "32x32"),
                   "/dev/null", "character device")
    assert not (tmp_path / "x.png").exists() and stat.S_ISFIFO(os.lstat(fifo).st_mode)
    (tmp_path / "real.lod").mkdir()
    os.symlink(tmp_path / "real.lod", tmp_path / "link.lod")
    source = tmp_path / "in.xyz"
    source.write_text("0 0 0\n1 0 0\n0 1 0\n1 1 0\n")
    assert_refused(invoke("lod", "build", source, "-o", tmp_path / "link.lod"), "link.lod", "symbolic link")
    assert (tmp_path / "link.lod").is_symlink()


# ---- 15.2: image sizes beyond what the backend can hold -------------------------------------

@requires_gl
@pytest.mark.parametrize("args", [["--size", "1x268435456"], ["--size", "16384x64"],
                                  ["--size", "4096x4096", "--supersample", "4"],
                                  ["--size", "2048x2048", "--supersample", "8"],
                                  ["--size", "4096x64", "--method", "mesh", "--supersample", "8"]])
def test_render_targets_beyond_the_contexts_limits_are_refused(tmp_path, args):
    out = tmp_path / "x.png"
    assert_refused(invoke("render", "--demo", "-o", out, *args), "--size/--supersample")
    assert not out.exists()


@requires_gl
def test_each_side_is_checked_against_the_context():
    from surfel.gl.targets import check_target_size, max_target_side

    side = max_target_side()
    check_target_size(side, 1)
    for size in ((side + 1, 1), (1, side + 1)):
        with pytest.raises(SurfelError, match=f"limit of {side} pixels a side"):
            check_target_size(*size)


def test_cpu_renders_have_their_own_bound(tmp_path):
    out = tmp_path / "x.png"
    assert_refused(invoke("render", "--demo", "-o", out, "--method", "ewa", "--backend", "cpu",
                          "--size", "8192x8192", "--supersample", "2"), "--size/--supersample", "CPU")
    assert_refused(invoke("render", "--demo", "-o", out, "--method", "mls", "--size", "4096x4096",
                          "--supersample", "3"), "--size/--supersample", "CPU")
    assert not out.exists()
