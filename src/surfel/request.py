"""Render requests: what the command line, batch jobs, the viewer and turntables ask of the
renderer, parsed and checked in one place.

A `RenderRequest` is an input (a file, or the bundled demo), a camera specification
(`CameraSpec`), the method and its backend, the `RenderOptions` with the method's parameters,
and the files to write (`Outputs`). Every option is one row of `OPTIONS`: its name (the flag
is --name with dashes; a batch job's key is the name, with dashes or underscores), how its
text is parsed, its default, its help, and what it sets: the input, the camera, a common
option, a method parameter, an output, or the method itself. `cli.py` declares its click
options from these rows; `batch.py` parses each job with `parse_render`, the parser of
`surfel render`'s own flags, so that a job means exactly what those flags mean.

Checked here, before anything is loaded, rendered or written, each refused in one line that
names the flag: text that is not a value of the option's kind; values that cannot be honoured
(`RenderOptions` and the parameter dataclasses check theirs on construction; the camera's
are checked here: a field of view outside (0, 180), an orthographic height or a zoom that is
not positive, an OpenCV K that is not an invertible 3x3 pinhole matrix or an R that is not a
rotation); an option the chosen method does not use, when the user set it; camera options
that contradict each other; and every output location (`files.check_output`).
"""

from __future__ import annotations

import os
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field, fields, replace
from pathlib import Path

import numpy as np

from .camera import VIEWS, Camera, OpenCvCamera, frame
from .colors import NAMED
from .errors import SurfelError
from .files import check_folder, check_output
from .methods import DEFAULT_METHOD, METHODS, get_method
from .methods.params import SplatParams
from .options import RenderOptions, SettingError
from .parsers import (
    choice,
    direction,
    field_of_view,
    integer,
    integer_in,
    integers,
    number,
    numbers,
    ortho_height,
    positive_number,
    size,
    text,
    words,
)
from .shading import DEFAULT_HELP as DEFAULT_SHADING_HELP
from .shading import MODELS

# The defaults of `surfel turntable` (and `surfel batch --turntable`), where they differ from render's.
TURNTABLE_FRAMES = 36
TURNTABLE_FPS = 12.0
TURNTABLE_ELEVATION = 15.0
TURNTABLE_SIZE = (512, 512)
VIEW_SIZE = (800, 800)  # `surfel view`'s window
IMAGE_FORMATS = (".png", "")  # colour images are PNG; a name without extension gets PNG too


# ---------------------------------------------------------------------------------------------
# The option table


@dataclass(frozen=True)
class Option:
    """One option: `parse` turns its text into its value (None: an on/off flag, given as a bool).

    sets: "input", "camera", "options" (a RenderOptions field), "params" (a parameter of the
    method), "output", "method" (the method and backend), "turntable", "scan" or "sample". `field`: the
    RenderOptions field or parameter it sets, when not `name`; `value` maps a flag's bool to it.
    `default`: text parsed like a given value, for the options whose default is not that of
    the dataclass they set (CameraSpec, RenderOptions, the method's parameters); else None.
    """

    name: str
    parse: Callable[[str], object] | None
    help: str
    sets: str
    default: str | None = None
    field: str | None = None
    flag: str | None = None  # a flag's click declaration when not --name ("--a/--no-a")
    short: str | None = None
    metavar: str | None = None
    value: Callable[[bool], object] | None = None
    shown: str | None = None  # the default --help shows where the data decides it

    @property
    def label(self) -> str:
        """How messages name it: its flag."""
        return "--" + self.name.replace("_", "-")

    def label_for(self, value) -> str:
        """The flag as given: an on/off flag's second name when off."""
        sides = (self.flag or self.label).split("/")
        return sides[1] if value is False and len(sides) > 1 else sides[0]

    @property
    def target(self) -> str:
        return self.field or self.name

    def shown_default(self) -> str | None:
        """The default --help shows: the table's, or that of the dataclass field it sets (the
        splat methods' common parameters for a parameter; other parameters say theirs in help)."""
        if self.shown is not None or self.default is not None or self.parse is None:
            return self.shown or self.default
        owner = {"camera": CameraSpec, "options": RenderOptions, "params": SplatParams}.get(self.sets)
        value = {f.name: f.default for f in fields(owner)}.get(self.target) if owner is not None else None
        if isinstance(value, tuple):
            return ("x" if self.name == "size" else ",").join(f"{v:g}" for v in value)
        return None if value is None else f"{value:g}" if isinstance(value, float) else str(value)


def _normalization(per_pixel: bool) -> str:
    return "per-pixel" if per_pixel else "per-surfel"


OPTIONS: dict[str, Option] = {o.name: o for o in [
    # what to render and where to write it
    Option("input", text, "The file to render.", "input", metavar="FILE"),
    Option("demo", None, "Render the bundled demo model (Spot, CC0) instead of INPUT.", "input"),
    Option("output", text, "PNG to write.", "output", short="-o", metavar="FILE"),
    Option("depth", text, "Write eye depth (H x W float32 .npy).", "output", metavar="FILE"),
    Option("normals", text, "Write eye normals (H x W x 3 float32 .npy).", "output", metavar="FILE"),
    Option("stats", text, "Write render statistics (.json).", "output", metavar="FILE"),
    Option("method", text, "Rendering method (see `surfel methods`).", "method", default=DEFAULT_METHOD, short="-m",
           metavar="NAME"),
    Option("backend", choice("auto", "gl", "cpu"),
           "Default auto: cpu where OpenGL is a software rasterizer (llvmpipe) and the method's CPU path is "
           "faster there, else gl, else cpu.", "method", metavar="[auto|gl|cpu]"),
    # the camera (docs/conventions.md)
    Option("size", size, "Image size in pixels.", "camera", metavar="WxH"),
    Option("view", choice(*VIEWS), "Auto-framing direction (default front).", "camera",
           metavar=f"[{'|'.join(VIEWS)}]"),
    Option("azimuth", number, "Degrees from the front view towards the right, about the up axis.", "camera",
           metavar="DEG"),
    Option("elevation", number, "Degrees above the horizon.", "camera", metavar="DEG"),
    Option("eye", numbers(3), "Camera position in file coordinates.", "camera", metavar="X,Y,Z"),
    Option("target", numbers(3), "Look-at point (default: bounding-box centre).", "camera", metavar="X,Y,Z"),
    Option("up", direction, "Up vector (default 0,0,1 for LAS/LAZ, 0,1,0 otherwise).", "camera", metavar="X,Y,Z"),
    Option("fov", field_of_view, "Vertical field of view in degrees.", "camera", metavar="DEG"),
    Option("ortho", ortho_height, "Orthographic camera showing HEIGHT world units vertically; auto: the height "
           "that frames the data as auto-framing does.", "camera", metavar="HEIGHT|auto"),
    Option("opencv", text, 'Pinhole camera from a JSON file {"K": 3x3, "R": 3x3, "t": 3} (OpenCV world-to-camera).',
           "camera", metavar="FILE"),
    Option("zoom", positive_number, "Move the auto-framed camera this many times farther.", "camera",
           metavar="FACTOR"),
    # every method
    Option("shading", choice(*MODELS), "Shading model (edl: eye-dome lighting).", "options",
           metavar=f"[{'|'.join(MODELS)}]", shown=DEFAULT_SHADING_HELP),
    Option("color", text, f"What the colour shows: {', '.join(NAMED)} or any attribute's name (see `surfel "
           "info`).", "options", metavar="MODE",
           shown="rgb where the cloud has colours, else elevation for geospatial clouds, else white"),
    Option("colormap", text, "Colour map of continuous attributes (matplotlib's names).", "options",
           metavar="NAME"),
    Option("color_range", numbers(2), "Values the colour map spans [default: the 2nd to 98th percentile].",
           "options", metavar="LO,HI"),
    Option("classes", integers, "Draw only the points of these classification codes (e.g. 2,9).", "options",
           metavar="CODES"),
    Option("returns", words, "Draw only these returns: numbers, first, last (e.g. first or 1,2).", "options",
           metavar="LIST"),
    Option("edl_strength", number, "Eye-dome lighting strength.", "options", metavar="S"),
    Option("edl_radius", positive_number, "Eye-dome lighting radius in pixels (shades at 1, 2 and 4 times it).",
           "options", metavar="PX"),
    Option("background", numbers(3), "Background colour in [0, 1].", "options", metavar="R,G,B"),
    Option("supersample", integer, "Samples per pixel side, 1 to 8 (default: the method's).", "options",
           metavar="N"),
    Option("lod_error", positive_number, "Level of detail: allowed projected error in pixels (splat methods).",
           "options", metavar="PX"),
    Option("point_budget", integer, "Most points drawn from a .lod hierarchy or COPC file (its LOD error is "
           "raised to fit).", "options", metavar="N"),
    Option("smooth", None, "Denoise the positions first: move them onto the points' MLS surface, as `surfel "
           "prepare --smooth` does (raw scans) [default: off].", "options"),
    Option("dump_passes", text, "Write the intermediate passes to this folder as images (gaussian, deferred, "
           "phong, object-space, ewa on gl).", "options", metavar="FOLDER"),
    # method parameters (methods/params.py and each method's dataclass)
    Option("radius_scale", number, "Multiply every splat radius (splat methods).", "params", metavar="FACTOR"),
    Option("depth_offset", number, "Visibility offset z_t as a fraction of the splat radius (blended splat "
           "methods).", "params", metavar="FRACTION"),
    Option("backface_culling", None, "Drop splats facing away (blended splat methods) [default: off].", "params",
           flag="--backface-culling/--no-backface-culling"),
    Option("ewa_filter", None, "Screen-space EWA filter approximation (gaussian, deferred, phong) [default: on for "
           "deferred, off for gaussian and phong].", "params", flag="--ewa-filter/--no-ewa-filter"),
    Option("lowpass_radius", number, "Screen-space low-pass radius in pixels (blended splat methods).", "params",
           metavar="PX"),
    Option("phong_normals", None, "deferred: light each pixel with its splats' linear normal fields (Phong "
           "splatting's), or with each splat's one normal as Botsch et al. 2005 do [default: normal fields].",
           "params", flag="--phong-normals/--splat-normals"),
    Option("per_pixel_normalization", None, "object-space: divide by the accumulated weight per pixel (Botsch & "
           "Kobbelt 2003), or Ren et al.'s precomputed per-surfel weights [default: per-pixel].", "params",
           field="normalization", flag="--per-pixel-normalization/--per-surfel-normalization",
           value=_normalization),
    Option("shadows", None, "Ray-traced shadows (mls).", "params", flag="--shadows"),
    Option("reflect", None, "One mirror bounce (mls).", "params", flag="--reflect"),
    Option("adaptive", None, "Adaptive supersampling: trace each pixel's corner, interpolate the samples of pixels "
           "whose corners see one smooth surface (mls) [default: on].", "params", flag="--adaptive/--no-adaptive"),
    # the input's acquisition
    Option("sensor", numbers(3), "Position of the scanner that measured the input, in file coordinates: "
           "estimated normals face it and splat sizes follow the range from it (terrestrial scans).", "input",
           metavar="X,Y,Z"),
    # turntables
    Option("frames", integer_in(1, 3600), "Frames in the orbit.", "turntable", default=str(TURNTABLE_FRAMES),
           metavar="N"),
    Option("fps", positive_number, "Frames per second of the animation.", "turntable", default=f"{TURNTABLE_FPS:g}",
           metavar="RATE"),
    # the virtual range scanner (`surfel scan`; scan.ScanSettings checks the ranges)
    Option("views", integer, "Views around the model.", "scan", metavar="N", shown="6"),
    Option("resolution", integer, "Samples per side of each view's depth image.", "scan", metavar="PX", shown="256"),
    Option("noise", number, "Range noise (standard deviation) along each ray, a fraction of the model's size.",
           "scan", metavar="FRACTION", shown="0.001"),
    Option("misalignment", number, "Registration error of each view (rotation and translation), a fraction of the "
           "model's size.", "scan", metavar="FRACTION", shown="0.0005"),
    Option("grazing", number, "Incidence angle past which no sample returns; fewer return from half of it.",
           "scan", metavar="DEG", shown="80"),
    Option("seed", integer, "Random seed of the noise, the lost samples and the misregistration.", "scan",
           metavar="N", shown="0"),
    # points spread over a mesh's faces (`surfel sample`; mesh_samples.SampleSettings checks the ranges)
    Option("points", integer, "Points to spread evenly over the mesh's faces (about as many remain).", "sample",
           metavar="N", shown="200000"),
    Option("crease_angle", number, "Faces meeting at a sharper angle than this keep their own normals (an edge); "
           "flatter ones are shaded smoothly.", "sample", metavar="DEG", shown="30"),
]}

CAMERA = tuple(name for name, o in OPTIONS.items() if o.sets == "camera")
RENDER = tuple(name for name, o in OPTIONS.items() if o.sets in ("options", "params"))
OUTPUTS = ("output", "depth", "normals", "stats")
# what `surfel render` takes, and hence a batch job; what `surfel turntable` takes
RENDER_COMMAND = ("input", "demo", "sensor", *OUTPUTS, "method", "backend", *CAMERA, *RENDER)
# what `surfel export-html` takes: render's options that the page honours
PAGE_COMMAND = ("input", "demo", "output", "method", *CAMERA, "shading", "color", "colormap", "color_range",
                "classes", "returns", "edl_strength", "edl_radius", "background", "supersample", "lod_error",
                "point_budget", "radius_scale", "depth_offset", "backface_culling", "ewa_filter", "lowpass_radius",
                "phong_normals")
PAGE_MAX_SUPERSAMPLE = 4
SCAN = tuple(name for name, o in OPTIONS.items() if o.sets == "scan")
SAMPLE = tuple(name for name, o in OPTIONS.items() if o.sets == "sample")
TURNTABLE_COMMAND = ("input", "sensor", "output", "frames", "fps", "elevation", "size", "method", "backend", *RENDER)


def option_text(option: Option, value, where: str) -> str | bool:
    """A batch job's value as the text the flag would be given (lists joined by commas, a
    size by x), or the bool of a flag; anything else is refused."""
    if option.parse is None:
        if not isinstance(value, bool):
            raise SurfelError(f"{where}{option.name} is true or false, got {value!r}")
        return value
    if isinstance(value, (list, tuple)):
        return ("x" if option.name == "size" else ",").join(str(v) for v in value)
    if isinstance(value, (bool, dict)) or value is None:
        raise SurfelError(f"{where}{option.name} takes a value, got {value!r}")
    return str(value)


def parse_values(values: Mapping[str, object], names, where: str = "") -> dict:
    """The given (not None) values of the options `names`, parsed; defaults are not filled in.
    Text from the command line, or a job's values (see `option_text`); keys with dashes or
    underscores. An unknown key or a value its option refuses is a one-line SurfelError."""
    parsed = {}
    for key, raw in values.items():
        name = str(key).replace("-", "_")
        if name not in names:
            raise SurfelError(f"{where}unknown option {key!r} (it takes the options of `surfel render`)")
        if raw is None:
            continue
        option = OPTIONS[name]
        given = option_text(option, raw, where)
        if option.parse is None:
            parsed[name] = given
            continue
        try:
            parsed[name] = option.parse(given)
        except ValueError as exc:
            raise SurfelError(f"{where}{option.label}: {exc}") from None
    return parsed


def default(name: str, parsed: dict):
    """The parsed value of `name`, else its parsed default (None if it has none)."""
    if name in parsed:
        return parsed[name]
    option = OPTIONS[name]
    return None if option.default is None else option.parse(option.default)


def argv_of(values: Mapping[str, object]) -> tuple[str, ...]:
    """The command-line arguments meaning these (job) values: flags, then the input."""
    argv, positional = [], []
    for key, value in values.items():
        name = str(key).replace("-", "_")
        option = OPTIONS[name]
        if value is None:
            continue
        if name == "input":
            positional = ["--", str(value)]
        elif option.parse is None:
            declaration = (option.flag or option.label).split("/")
            if value or len(declaration) > 1:
                argv.append(declaration[0] if value else declaration[1])
        else:
            argv += [option.label, option_text(option, value, "")]
    return tuple(argv + positional)


# ---------------------------------------------------------------------------------------------
# Options and parameters of a method


def render_options(method: str, values: Mapping[str, object], *, strict: bool = True,
                   labels: Mapping[str, str] | None = None, where: str = "") -> RenderOptions:
    """RenderOptions (with the method's parameters) from values keyed by RenderOptions field
    or parameter name. strict: a value the method does not use is refused (the command line,
    where the user set it); else it is left out (the viewer applies its keys wherever they
    mean something). `labels` name the fields in messages (the flags)."""
    m = get_method(method)
    labels = labels or {}
    kept = {}
    for name, value in values.items():
        if value is None:
            continue
        if not m.uses(name):
            if strict:
                users = ", ".join(other.name for other in METHODS.values() if other.uses(name))
                raise SurfelError(f"{where}{labels.get(name, name)}: method {method!r} does not use it "
                                  f"(it applies to {users or 'no method'})")
            continue
        kept[name] = value
    common = {k: v for k, v in kept.items() if k in RenderOptions.names()}
    try:
        params = m.make_params({k: v for k, v in kept.items() if k not in common})
        return RenderOptions(**common, params=params)
    except SettingError as exc:
        raise SurfelError(f"{where}{labels.get(exc.name, exc.name)}: {exc.problem}") from None


# ---------------------------------------------------------------------------------------------
# Outputs


@dataclass(frozen=True)
class Outputs:
    """The files a render writes: a PNG, eye depth and normals (.npy), statistics (.json)."""

    png: str | None = None
    depth: str | None = None
    normals: str | None = None
    stats: str | None = None

    def named(self) -> dict[str, str]:
        return {label: path for label, path in (("--output", self.png), ("--depth", self.depth),
                                                ("--normals", self.normals), ("--stats", self.stats)) if path}

    def check_names(self, where: str = "") -> None:
        """What the names alone tell: the PNG's extension, one file named twice."""
        if self.png is not None and Path(self.png).suffix.lower() not in IMAGE_FORMATS:
            raise SurfelError(f"{where}{self.png}: --output writes a PNG: name it .png")
        seen: dict[str, str] = {}
        for label, path in self.named().items():
            key = os.path.realpath(path)
            if key in seen:
                raise SurfelError(f"{where}{path}: {label} names the same file as {seen[key]}")
            seen[key] = label

    def check(self) -> None:
        """Every location, so that a render writes all it was asked for or nothing."""
        for label, path in self.named().items():
            check_output(path, label)

    def absolute(self) -> Outputs:
        return Outputs(*(p and os.path.abspath(p) for p in (self.png, self.depth, self.normals, self.stats)))


# ---------------------------------------------------------------------------------------------
# Camera


@dataclass(frozen=True)
class CameraSpec:
    """The camera flags of docs/conventions.md, checked; `camera(cloud)` makes the camera."""

    size: tuple[int, int] = (1024, 1024)
    view: str | None = None
    azimuth: float | None = None
    elevation: float | None = None
    eye: tuple[float, float, float] | None = None
    target: tuple[float, float, float] | None = None
    up: tuple[float, float, float] | None = None
    fov: float = 30.0
    ortho: float | str | None = None  # a height, or "auto"
    opencv: OpenCvCamera | None = field(default=None, compare=False)
    zoom: float = 1.0

    @classmethod
    def from_parsed(cls, parsed: dict, where: str = "") -> CameraSpec:
        given = {name for name in CAMERA if name in parsed}
        conflicts = [("opencv", ("view", "azimuth", "elevation", "eye", "target", "up", "fov", "ortho", "zoom"),
                      "sets the whole camera"),
                     ("eye", ("view", "azimuth", "elevation", "zoom"), "places the camera"),
                     ("view", ("azimuth", "elevation"), "chooses the direction")]
        for name, others, what in conflicts:
            clash = [OPTIONS[o].label for o in others if o in given]
            if name in given and clash:
                raise SurfelError(f"{where}{OPTIONS[name].label} {what}; drop {', '.join(clash)}")
        values = {name: parsed[name] for name in CAMERA if name in parsed}
        if "opencv" in values:
            try:
                values["opencv"] = OpenCvCamera.read(values["opencv"])
            except SurfelError as exc:
                raise SurfelError(f"{where}{exc}") from None
        return cls(**values)

    def check_eye(self, target: np.ndarray) -> None:
        """Refuse an --eye that looks nowhere: on its target, or along the --up given."""
        sight = target - np.asarray(self.eye, np.float64)
        reach = float(np.linalg.norm(sight))
        if not reach > 1e-12 * max(float(np.abs(target).max()), 1.0):
            raise SurfelError(f"--eye: the camera stands on its target {target.tolist()}; move it or the --target")
        if self.up is not None:
            up = np.asarray(self.up, np.float64)
            if np.linalg.norm(np.cross(sight / reach, up / np.linalg.norm(up))) < 1e-9:
                raise SurfelError("--up: parallel to the line of sight from --eye to the target; choose another up")

    def camera(self, cloud) -> Camera:
        """The camera for `cloud` (a PointCloud or a LodSource: its bounds frame the view)."""
        if self.opencv is not None:
            c = self.opencv
            return Camera.from_opencv(c.K, c.R, c.t, self.size).fit_clip_planes(cloud.center, cloud.bounding_radius)
        if self.eye is not None:
            self.check_eye(np.asarray(cloud.center if self.target is None else self.target, np.float64))
        return frame(cloud.center, cloud.bounding_radius, view=self.view, azimuth=self.azimuth,
                     elevation=self.elevation, up=self.up, geospatial=cloud.geospatial, fov=self.fov,
                     size=self.size, eye=self.eye, target=self.target, ortho_height=self.ortho, zoom=self.zoom,
                     bounds=cloud.bounds)


# ---------------------------------------------------------------------------------------------
# Requests


@dataclass(frozen=True)
class RenderRequest:
    """One render: `surfel render`'s command line, a batch job, or the frames of a turntable."""

    input: str | None
    demo: bool
    method: str
    backend: str | None
    camera: CameraSpec
    options: RenderOptions
    outputs: Outputs
    argv: tuple[str, ...] = ()  # the `surfel render` arguments that make this request
    sensor: tuple[float, float, float] | None = None  # --sensor

    def open_input(self):
        """The demo cloud, a lazy LOD source (a .lod directory, a COPC file) or the loaded cloud."""
        if self.demo:
            from .data import demo_cloud
            from .lod.source import with_sensor

            return with_sensor(demo_cloud(), self.sensor)
        return open_input(self.input, self.sensor)

    def render(self, renderer, cloud=None):
        """Render (the input, or `cloud` when the caller has it loaded) with `renderer`."""
        from .cloud import PointCloud

        cloud = self.open_input() if cloud is None else cloud
        if self.options.point_budget is not None and isinstance(cloud, PointCloud):
            raise SurfelError(f"{self.input or 'demo'}: --point-budget applies to .lod hierarchies and COPC files")
        return renderer.render(cloud, self.camera.camera(cloud), self.method, backend=self.backend,
                               options=self.options)

    def check_outputs(self) -> None:
        self.outputs.check()
        if self.options.dump_passes is not None:
            check_folder(self.options.dump_passes, "--dump-passes")

    def write(self, result) -> None:
        o = self.outputs
        result.save(o.png, depth=o.depth, normals=o.normals, stats=o.stats)

    def absolute(self) -> RenderRequest:
        """Paths made absolute (for workers started in another directory)."""
        options = self.options
        if options.dump_passes is not None:
            options = replace(options, dump_passes=os.path.abspath(options.dump_passes))
        return replace(self, input=None if self.input is None else os.path.abspath(self.input),
                       outputs=self.outputs.absolute(), options=options)


def open_input(path, sensor: tuple[float, float, float] | None = None):
    """A lazy LOD source (a .lod directory, a COPC file) if PATH is one, else the loaded cloud;
    with `sensor`, the position of the scanner that measured it (`lod.source.with_sensor`)."""
    from .io import load
    from .lod.source import open_source, with_sensor

    source = open_source(path)
    if source is None:
        refuse_folder(path)
    return with_sensor(source or load(path), sensor)


def refuse_folder(path) -> None:
    """A folder that is no .lod hierarchy: its tiles are one cloud only to `lod build`."""
    if os.path.isdir(path):
        raise SurfelError(f"{path}: a folder, not a point file or .lod hierarchy (`surfel lod build {path} "
                          "-o NAME.lod` builds one hierarchy of the tiles in a folder)")


def method_and_backend(parsed: dict, where: str = "") -> tuple[str, str | None]:
    method = default("method", parsed)
    try:
        m = get_method(method)
    except SurfelError as exc:
        raise SurfelError(f"{where}{exc}") from None
    backend = None if parsed.get("backend") == "auto" else parsed.get("backend")
    if backend is not None and backend not in m.backends:
        raise SurfelError(f"{where}--backend: method {method!r} has no {backend!r} backend; "
                          f"it has {', '.join(m.backends)}")
    return method, backend


def options_from(parsed: dict, method: str, where: str = "") -> RenderOptions:
    """The RenderOptions of the parsed values, each checked against the method."""
    values, labels = {}, {}
    for name in RENDER:
        option = OPTIONS[name]
        labels[option.target] = option.label_for(parsed.get(name))
        if name in parsed:
            value = parsed[name]
            values[option.target] = option.value(value) if option.value else value
    return render_options(method, values, labels=labels, where=where)


def parse_render(values: Mapping[str, object], *, where: str = "", require_output: bool = True) -> RenderRequest:
    """The request that `surfel render` with these option values makes (None: not given)."""
    parsed = parse_values(values, RENDER_COMMAND, where)
    if parsed.get("demo", False) == ("input" in parsed):
        raise SurfelError(f"{where}give an input file or --demo (not both)")
    if require_output and "output" not in parsed:
        raise SurfelError(f"{where}missing --output (the PNG to write)")
    method, backend = method_and_backend(parsed, where)
    options = options_from(parsed, method, where)
    if options.dump_passes is not None and backend is not None and backend not in get_method(method).dump_passes:
        raise SurfelError(f"{where}--dump-passes: method {method!r} writes no passes on its {backend} backend")
    outputs = Outputs(*(parsed.get(name) for name in OUTPUTS))
    outputs.check_names(where)
    given = {k: v for k, v in values.items() if v is not None}
    return RenderRequest(parsed.get("input"), parsed.get("demo", False), method, backend,
                         CameraSpec.from_parsed(parsed, where), options, outputs, argv_of(given),
                         parsed.get("sensor"))


__all__ = ["OPTIONS", "SAMPLE", "SCAN", "Option", "CameraSpec", "Outputs", "RenderRequest", "default",
           "method_and_backend", "open_input", "options_from", "parse_render", "parse_values", "render_options"]
