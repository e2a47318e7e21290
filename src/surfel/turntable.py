"""Turntable animations: the camera orbits the cloud about its up axis, rendered headless."""

from __future__ import annotations

import io
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from tqdm import tqdm

from .camera import frame
from .errors import SurfelError
from .files import check_output, replaced_atomically, write_atomically
from .methods import DEFAULT_METHOD
from .options import RenderOptions
from .rendering import Renderer
from .request import (
    TURNTABLE_COMMAND,
    TURNTABLE_ELEVATION,
    TURNTABLE_FPS,
    TURNTABLE_FRAMES,
    TURNTABLE_SIZE,
    default,
    method_and_backend,
    open_input,
    options_from,
    parse_values,
)

FORMATS = (".gif", ".mp4")


def orbit_cameras(cloud, frames: int, *, size=TURNTABLE_SIZE, elevation: float = TURNTABLE_ELEVATION,
                  fov: float = 30.0):
    """`frames` auto-framed cameras at evenly spaced azimuths, starting from the front view."""
    for i in range(frames):
        yield frame(cloud.center, cloud.bounding_radius, azimuth=360.0 * i / frames, elevation=elevation,
                    geospatial=cloud.geospatial, size=size, fov=fov)


def check_animation(path) -> None:
    """A turntable's output: .gif, or .mp4 with the video extra installed, in an existing folder."""
    check_output(os.fspath(path), "a turntable", FORMATS)
    if os.fspath(path).lower().endswith(".mp4"):
        try:
            import imageio.v3  # noqa: F401
        except ImportError:
            raise SurfelError("mp4 output needs the video extra: pip install 'surfel[video]'") from None


def write_animation(images: list[np.ndarray], path, fps: float = TURNTABLE_FPS) -> None:
    """RGBA uint8 frames to a GIF (Pillow) or MP4 (imageio with its ffmpeg plugin, optional)."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix == ".gif":
        from PIL import Image

        pictures = [Image.fromarray(image[..., :3]) for image in images]
        buffer = io.BytesIO()
        pictures[0].save(buffer, format="GIF", save_all=True, append_images=pictures[1:],
                         duration=round(1000 / fps), loop=0)
        write_atomically(path, buffer.getvalue())
    elif suffix == ".mp4":
        try:
            import imageio.v3 as iio
        except ImportError:
            raise SurfelError("mp4 output needs the video extra: pip install 'surfel[video]'") from None
        with replaced_atomically(path, ".mp4") as temporary:  # imageio picks the format by the suffix
            iio.imwrite(temporary, np.stack([image[..., :3] for image in images]), fps=fps, codec="libx264")
    else:
        raise SurfelError(f"{path}: turntable output must be .gif or .mp4")


def turntable(cloud, path, *, frames: int = TURNTABLE_FRAMES, method: str = DEFAULT_METHOD, size=TURNTABLE_SIZE,
              elevation: float = TURNTABLE_ELEVATION, fps: float = TURNTABLE_FPS, progress: bool | None = None,
              backend: str | None = None, renderer: Renderer | None = None, **options) -> None:
    """Render `frames` orbit frames of `cloud` with `method` (options as `Renderer.render`
    takes them) and write them to `path`, a .gif or .mp4."""
    if frames < 1:
        raise SurfelError("a turntable needs at least one frame")
    check_animation(path)
    renderer = renderer or Renderer()
    images = []
    cameras = orbit_cameras(cloud, frames, size=size, elevation=elevation)
    for camera in tqdm(cameras, total=frames, desc="turntable", unit="frame", disable=progress is False,
                       leave=False):
        images.append(renderer.render(cloud, camera, method, backend=backend, **options).rgba8())
    write_animation(images, path, fps)


@dataclass(frozen=True)
class TurntableRequest:
    """`surfel turntable`: an orbit of auto-framed cameras rendered to a GIF or MP4."""

    input: str
    output: str
    frames: int
    fps: float
    elevation: float
    size: tuple[int, int]
    method: str
    backend: str | None
    options: RenderOptions
    sensor: tuple[float, float, float] | None = None


def parse_turntable(values: dict) -> TurntableRequest:
    """`surfel turntable`'s request, parsed by the request layer; its output is checked here,
    before anything is loaded."""
    parsed = parse_values(values, TURNTABLE_COMMAND)
    method, backend = method_and_backend(parsed)
    check_animation(parsed["output"])
    return TurntableRequest(parsed["input"], parsed["output"], default("frames", parsed), default("fps", parsed),
                            parsed.get("elevation", TURNTABLE_ELEVATION), parsed.get("size", TURNTABLE_SIZE),
                            method, backend, options_from(parsed, method), parsed.get("sensor"))


def turntable_command(values: dict) -> TurntableRequest:
    """`surfel turntable`: the request parsed, then rendered and written."""
    request = parse_turntable(values)
    with Renderer() as renderer:
        turntable(open_input(request.input, request.sensor), request.output, frames=request.frames,
                  method=request.method, size=request.size, elevation=request.elevation, fps=request.fps,
                  backend=request.backend, renderer=renderer, options=request.options)
    return request
