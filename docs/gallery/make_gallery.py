"""Regenerate the gallery: the survey's figures reproduced on the shared models, and the
README's table of every method's PSNR, holes and speed against the mesh.

    python docs/gallery/make_gallery.py [--data ../shared/data] [--no-table]

Writes docs/gallery/fig*.png, then the README's quality block (the `quality` section of
benchmarks/readme_numbers.py, which measures it).
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

import numpy as np
from PIL import Image

import surfel
from surfel.camera import frame
from surfel.mls.raytrace import MlsParams
from surfel.preprocess import complete
from surfel.rendering import render

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parents[1] / "tests"))
sys.path.insert(0, str(HERE.parents[1] / "benchmarks"))
from readme_numbers import regenerate  # noqa: E402  (the README's measured blocks)

from scenes import checker_plane, grazing_camera  # noqa: E402  (the minification scene of the tests)


def save(path: Path, images: list[np.ndarray], labels: list[str] | None = None) -> None:
    """Side by side, RGB over white where transparent, labels drawn above."""
    from PIL import ImageDraw

    tiles = []
    for image in images:
        rgba = image if image.dtype == np.uint8 else np.round(np.clip(image, 0, 1) * 255).astype(np.uint8)
        if rgba.ndim == 2:
            rgba = np.repeat(rgba[..., None], 3, -1)
        tiles.append(rgba[..., :3])
    strip = Image.fromarray(np.concatenate(tiles, axis=1))
    if labels:
        canvas = Image.new("RGB", (strip.width, strip.height + 22), "white")
        canvas.paste(strip, (0, 22))
        draw = ImageDraw.Draw(canvas)
        width = tiles[0].shape[1]
        for i, label in enumerate(labels):
            draw.text((i * width + 6, 4), label, fill="black")
        strip = canvas
    strip.save(path)
    print(path)


def over_white(result) -> np.ndarray:
    return result.color * result.alpha[..., None] + (1 - result.alpha[..., None])


def figure5(bunny):
    cam = frame(bunny.center, bunny.bounding_radius, size=(384, 384))
    with tempfile.TemporaryDirectory() as folder:
        render(bunny, cam, "deferred", dump_passes=folder)
        images = [np.asarray(Image.open(Path(folder) / name).convert("RGB")) for name in
                  ("1-visibility-depth.png", "3-accumulated-color.png", "4-normalized.png")]
    save(HERE / "fig5-three-passes.png", images, ["a) visibility", "b) accumulated", "c) normalized"])


def figure6(bunny):
    # each method estimates what it needs (phong: ellipses and normal fields), as `surfel render` does
    sparse = surfel.PointCloud(bunny.positions[::4], normals=bunny.normals[::4], source="bunny / 4")
    r = bunny.bounding_radius
    cam = frame(bunny.center, r, size=(384, 384), eye=bunny.center + np.array([0.3, 0.35, 1.0]) * 0.55 * r * 2,
                target=bunny.center + np.array([0.0, 0.25 * r, 0.0]))
    images = [over_white(render(sparse, cam, m, shading="phong")) for m in ("points", "gaussian", "phong")]
    save(HERE / "fig6-points-gaussian-phong.png", images, ["unfiltered", "Gaussian", "Phong splatting"])


def figure8(bunny):
    cam = frame(bunny.center, bunny.bounding_radius, size=(320, 320))
    result = render(bunny, cam, "deferred", shading="phong")
    normals = np.where(result.alpha[..., None] > 0, 0.5 * result.normals + 0.5, 1)
    depth = render(bunny, cam, "deferred", shading="depth")
    save(HERE / "fig8-deferred-buffers.png", [normals, over_white(depth), over_white(result)],
         ["normals", "depth", "shaded"])


def figure10():
    plane = checker_plane()
    cam = grazing_camera((512, 256))
    images = [over_white(render(plane, cam, "deferred", shading="none", ewa_filter=f)) for f in (False, True)]
    save(HERE / "fig10-minification.png", images, ["no EWA filter", "EWA filter approximation"])


def figure13(bunny):
    images, labels = [], []
    for zoom in (1, 4):
        cam = frame(bunny.center, bunny.bounding_radius, size=(320, 320), zoom=zoom)
        result = render(bunny, cam, "deferred", lod_error=1.0)
        picture = over_white(result)
        if zoom > 1:  # enlarge the far view's centre for comparison
            c = picture.shape[0] // 2
            q = picture.shape[0] // (2 * zoom)
            picture = np.kron(picture[c - q:c + q, c - q:c + q], np.ones((zoom, zoom, 1)))
        images.append(picture)
        labels.append(f"{zoom}x distance: {result.stats['splats']} of {len(bunny)} splats")
    save(HERE / "fig13-sequential-point-tree.png", images, labels)


def figure16(bunny):
    cam = frame(bunny.center, bunny.bounding_radius, size=(384, 384))
    plain = render(bunny, cam, "mls", shading="phong")
    shadowed = render(bunny, cam, "mls", shading="phong", params=MlsParams(shadows=True))
    save(HERE / "fig16-mls-ray-traced.png", [over_white(plain), over_white(shadowed)],
         ["MLS surface, ray traced", "with shadows"])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", default=str(HERE.parents[2] / "shared" / "data"))
    parser.add_argument("--no-table", action="store_true", help="the figures only, not the README's quality table")
    args = parser.parse_args()
    data = Path(args.data)
    bunny = complete(surfel.load(data / "stanford-bunny.obj"))[0]
    figure5(bunny)
    figure6(bunny)
    figure8(bunny)
    figure10()
    figure13(bunny)
    figure16(bunny)
    if not args.no_table:
        regenerate(["quality"], data)


if __name__ == "__main__":
    main()
