from pathlib import Path

import pytest

from browser import browser  # noqa: F401  (headless Chromium, one per session, for the page and widget tests)

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"


def gl_ok() -> bool:
    from surfel.gl.context import gl_available

    return gl_available()


requires_gl = pytest.mark.skipif(not gl_ok(), reason="no OpenGL context")


def data_file(name: str) -> Path:
    path = DATA / name
    if not path.exists():
        pytest.skip(f"{path} not available")
    return path


@pytest.fixture(scope="session")
def bunny():
    from surfel.io import load
    from surfel.preprocess import complete

    return complete(load(data_file("stanford-bunny.obj")))[0]
