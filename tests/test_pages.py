"""surfel.pages: the command line's processes take no transparent huge pages."""

import os
import subprocess
import sys
import time

import pytest

pytestmark = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="PR_SET_THP_DISABLE is Linux's")

# in a fresh interpreter, huge pages allowed first (the test process may have turned them off,
# by running a command in it, and its children inherit that): THP_enabled of /proc/self/status
# after the given statement
PROBE = ("import ctypes; ctypes.CDLL(None).prctl(41, 0, 0, 0, 0)\n{}\n"
         "print(open('/proc/self/status').read().split('THP_enabled:')[1].split()[0])")


def _thp_enabled(statement: str, **environment: str) -> str:
    env = {k: v for k, v in os.environ.items() if k != "NUMPY_MADVISE_HUGEPAGE"} | environment
    result = subprocess.run([sys.executable, "-c", PROBE.format(statement)], capture_output=True, text=True,
                            check=True, env=env)
    return result.stdout.strip()


def test_no_huge_pages_turns_them_off_unless_numpy_is_told():
    assert _thp_enabled("pass") == "1"
    assert _thp_enabled("from surfel.pages import no_huge_pages; no_huge_pages()") == "0"
    assert _thp_enabled("from surfel.pages import no_huge_pages; no_huge_pages()", NUMPY_MADVISE_HUGEPAGE="1") == "1"


def test_a_command_turns_them_off():
    """Any command (here `surfel methods`) first turns them off; the processes it starts inherit
    that from it."""
    command = "from surfel.cli import main; main(['methods'], standalone_mode=False)"
    assert _thp_enabled(command).splitlines()[-1] == "0"
    assert _thp_enabled("import surfel.cli").splitlines()[-1] == "1"  # importing it changes nothing


def _open_descriptors() -> set[str]:
    return set(os.listdir("/proc/self/fd"))


def test_drop_when_written_lets_the_writer_go_on_and_closes_what_it_kept(tmp_path):
    """The file is renamed and closed at once, its content intact; the background thread
    closes the descriptor it kept once the pages are dropped (none left open)."""
    from surfel.pages import drop_when_written

    data = os.urandom(1 << 22)
    before = _open_descriptors()
    for index in range(3):
        path = tmp_path / f"written-{index}.bin"
        with open(path, "wb") as file:
            file.write(data)
            file.flush()
            drop_when_written(file)
        path.rename(tmp_path / f"renamed-{index}.bin")
    deadline = time.monotonic() + 30
    while _open_descriptors() - before and time.monotonic() < deadline:
        time.sleep(0.05)
    assert not _open_descriptors() - before
    for index in range(3):
        assert (tmp_path / f"renamed-{index}.bin").read_bytes() == data
