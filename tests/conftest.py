"""Shared fixtures. Every model a test renders is carried by the repository or made by
tests/models.py; no test depends on files outside the checkout."""

import pytest

from browser import browser  # noqa: F401  (headless Chromium, one per session, for the page and widget tests)


def gl_ok() -> bool:
    from surfel.gl.context import gl_available

    return gl_available()


requires_gl = pytest.mark.skipif(not gl_ok(), reason="no OpenGL context")


def invoke(*args):
    """`surfel ARGS` in this process (click's runner), exceptions propagated."""
    from click.testing import CliRunner

    from surfel.cli import main

    return CliRunner().invoke(main, [str(a) for a in args], catch_exceptions=False)


def assert_refused(result, *words):
    """Exit status 2 and exactly one line, `surfel: error: ...`, holding `words`."""
    lines = result.output.strip().splitlines()
    assert result.exit_code == 2, result.output
    assert len(lines) == 1 and lines[0].startswith("surfel: error: "), result.output
    for word in words:
        assert word in lines[0], (word, lines[0])


@pytest.fixture(scope="session")
def dense_spot():
    """Spot refined to 46,850 vertices (models.dense_spot), completed (radii, tangent axes):
    a dense organic mesh whose vertices are the splats."""
    from models import dense_spot
    from surfel.preprocess import complete

    return complete(dense_spot())[0]


@pytest.fixture(scope="session")
def turned_part():
    """The CAD part with sharp creases (models.turned_part), as a mesh."""
    from models import turned_part

    return turned_part()
