"""Importing Mitsuba 3 XML scenes as our scene dict.

:func:`xml_to_scene_dict` reads a Mitsuba 3 scene file (``<scene version="3.x.y">``;
``2.x.y`` files use the same syntax and are accepted too) and returns the
dict that :func:`~instancing.io.scene_file.parse_scene` accepts, so that
``load_scene("scene.xml")`` renders the same picture Mitsuba would.

The parser is ``defusedxml.ElementTree``: entity declarations (the
"billion laughs" expansion bomb) and external entities are refused.
Mitsuba's own XML semantics are reproduced and were checked against
Mitsuba 3.9.1 (``tests/test_mitsuba_xml.py``):

* ``<default name value>`` and ``$name`` in attribute values: the defaults
  apply from where they are written on, longer names are substituted first,
  an undefined ``$name`` is an error; ``parameters`` overrides defaults as the
  keyword arguments of ``mitsuba.load_file`` do.
* ``<include filename>``: resolved against the including file's folder, then
  the main scene's folder (Mitsuba's file resolver); an included ``<scene>``
  contributes its children, any other root element itself. Include cycles
  are reported with the chain of files.
* ``<transform name="to_world">``: ``translate``, ``rotate``, ``scale``,
  ``matrix`` (16 or 9 numbers) and ``lookat`` act in the order written, the
  first listed first on points: M = op_n @ ... @ op_1. Mitsuba's ``rotate``
  does not normalize its axis (``c I + (1 - c) a a^T + s [a]_x``: a non-unit
  axis also scales); we build the same matrix, so the geometry matches
  Mitsuba's. (Mitsuba then also keeps that matrix as its own inverse
  transpose, so its normals on analytic shapes under such a transform are off;
  ours follow the geometry. Unit axes, the usual case, are unaffected.)
* Shapes ``sphere`` (``center``, ``radius``: to_world @ translate(center) @
  scale(radius)), ``cube``, ``rectangle`` and ``disk`` (a rectangle's and a disk's
  ``flip_normals``: to_world @ scale(1, 1, -1), the plane mirrored onto itself), ``cylinder`` (``p0``,
  ``p1``, ``radius``: to_world @ translate(p0) @ frame(p1 - p0) @ scale(r, r,
  |p1 - p0|), the frame built by Mitsuba's ``coordinate_system``), ``obj`` and
  ``ply`` (``filename``, ``face_normals``, ``flip_normals``, ``flip_tex_coords``) and
  ``serialized`` (``filename``, ``shape_index``, ``face_normals``, ``flip_normals``; under
  a shape's own mirroring to_world, Mitsuba's computed normals turn inward and so the mesh
  is read flipped, :meth:`_Importer.placed_shading`; a sphere faces inward so, and a
  sphere, cube or cylinder by ``flip_normals``: the model turned inside out,
  :meth:`_Importer.inward_model`), and
  ``sdfgrid`` (``filename`` of a one-channel volume grid, ``normals``; no emitter) and
  ``linearcurve`` and ``bsplinecurve`` (``filename``; its ``to_world`` moves the control points,
  not the radii, so it goes into the model; no emitter).
  Meshes shade smoothly by their file's
  vertex normals or by normals computed as Mitsuba's (angle-weighted), which Mitsuba
  computes after moving a plain shape's vertices by its ``to_world``: under non-uniform
  scale or shear the model computes them so too (``computed_normals_to_world``, the
  linear part scaled to determinant +-1). Mesh files resolve like includes; the output
  holds absolute paths.
* ``shapegroup`` and ``instance``: each shape of the group becomes one of our
  instances with to_world = instance to_world @ shape to_world. (Unlike
  Mitsuba, area emitters inside shape groups are allowed, and plain spheres
  and cylinders accept any affine to_world.)
* BSDFs: ``diffuse``, ``conductor``, ``roughconductor``, ``plastic``,
  ``roughplastic``, ``pplastic`` and ``polarizer`` (as Mitsuba's unpolarized variants render
  them), ``dielectric``, ``thindielectric``, ``roughdielectric`` and
  ``twosided`` (around one or two reflecting ones), ``blendbsdf`` (two BSDFs and a
  ``weight``), ``mask`` (one BSDF and an ``opacity``), ``null``, ``principled``, ``principledthin``,
  ``normalmap`` (its ``normalmap`` texture around one plain BSDF), ``bumpmap`` (a height
  bitmap under any name, ``scale``, around one plain BSDF), with
  Mitsuba's parameters and defaults
  (colours as ``<rgb>``, ``<float>`` or ``<spectrum>``; numbers that a texture may give as
  ``<float>`` or a constant ``<spectrum>``), nested or by ``<ref id>`` (with or
  without a ``name``, which Mitsuba ignores on nested BSDFs; a BSDF nested in itself through
  references is reported as a cycle); textures
  ``bitmap``, ``checkerboard``, ``mesh_attribute`` (a PLY mesh's vertex or face
  attribute), ``volume`` (a ``gridvolume`` read from a ``.vol`` file, or a ``constvolume``)
  and ``rawconstant`` (its ``value`` everywhere, as a checkerboard of one colour) for the parameters
  that take them, nested as
  ``<texture name=...>`` or declared at the top level and referenced by ``<ref name id>``
  (bitmap files resolve like mesh files; ``accel`` accepted and ignored: it only chooses
  Mitsuba's lookup hardware; ``format`` accepted as ``variant``, the float texels ours store).
  Each becomes a named material (its id, or ``bsdf@FILE:LINE``). A shape without
  BSDF gets Mitsuba's default: our
  ``default`` material, or, when it carries an area emitter, a black diffuse
  (as Mitsuba gives emitters).
* Emitters: ``area`` inside a shape, or at the top level with an ``id`` that shapes
  refer to (``radiance``; Mitsuba attaches it to one shape, we to each that refers to
  it, and one that none refers to emits nothing in either), top-level ``point``
  (``position`` or ``to_world``; ``intensity``), ``spot`` (``to_world``, ``intensity``,
  ``cutoff_angle``, ``beam_width``, a ``texture``; ``to_world`` rigid as a sensor's),
  ``projector`` (``to_world`` as rigid, ``irradiance`` a colour or texture, ``scale``, ``fov``
  with ``fov_axis`` or ``focal_length``), ``directional``
  (``direction`` or ``to_world``; ``irradiance``), ``constant`` (``radiance``) and
  ``envmap`` (``filename`` found like mesh files, ``to_world`` a rotation as rigid as a
  sensor's, ``scale``;
  ``mis_compensation`` accepted and ignored: it only changes Mitsuba's sampling), with
  Mitsuba's default of 1 for a missing power; one environment per scene.
* ``perspective``, ``thinlens`` (``aperture_radius``, ``focus_distance``) and
  ``orthographic`` sensors, as many as the scene has (their ids name them): ``fov`` with every ``fov_axis`` Mitsuba knows
  (``x``, ``y``, ``diagonal``, ``smaller``, ``larger``, converted exactly to
  our horizontal fov with the film's aspect) or ``focal_length`` (default
  ``50mm``), ``near_clip`` (default 0.01, as Mitsuba), ``to_world`` (but for the orthographic
  one rigid within Mitsuba's tolerance, M M^T within 1e-3 of I, as rotations written with
  six digits are; then made exactly rigid), the perspective sensor's ``principal_point_offset_x``
  and ``_y``, an ``hdrfilm`` (default 768 x 576; ``crop_offset_x``, ``crop_offset_y``,
  ``crop_width`` and ``crop_height``, a window inside the film that the image shows;
  ``sample_border``; ``pixel_format``, the camera's, ``rgb`` or ``rgba``, luminance and XYZ
  formats warned about and read as RGB, with their alpha;
  nested, or declared at the top level with an ``id`` and referenced by ``<ref id>``) with a
  ``box``, ``gaussian`` (``stddev``, default 0.5: Mitsuba's default filter), ``tent``
  (``radius``, default 1), ``mitchell`` (``B`` and ``C``, default 1/3 each), ``catmullrom`` or
  ``lanczos`` (``lobes``, default 3) ``rfilter``;
  ``focus_distance`` is accepted on the pinhole (meaningless there, as in Mitsuba).
* ``<path value>`` (search folders for files, as Mitsuba's resolver; at the root of the main
  file or of an included one, relative to that file: Mitsuba 3.9.1 accepts the latter but
  was measured not to search it), ``<alias id as>``,
  ``<spectrum>`` values (constants and ``wavelength:value`` lists, converted to RGB by
  Mitsuba's own RGB variant: as an illuminant inside emitters, as a reflectance elsewhere),
  ``<point>`` and ``<vector>`` (``value``, or all of ``x``, ``y`` and ``z``, as Mitsuba).
  Elements and includes nested more than 100 deep are refused.

Render settings: the ``<integrator>`` (its type and parameters, nested integrators
named) becomes the scene's ``"integrator"``, and a sensor's ``<sampler>`` (nested or
referenced) gives the camera's ``"spp"`` (its ``sample_count``), ``"sampler"`` (its
type: independent, or stratified over each pixel's samples), ``"jitter"`` (that of a
``stratified``, ``multijitter`` or ``orthogonal`` sampler; the others take none, as in
Mitsuba) and ``"seed"`` (added to every render's seed, as Mitsuba adds it): renders that
name no integrator or spp use them
(:func:`instancing.rendering.film.render_settings`; a sensor without a sampler keeps our
default of 64 spp, not Mitsuba's 4).

Accepted and ignored: the sensor's ``far_clip`` (rays are not cut off there; it
is checked against ``near_clip`` and is a thin lens's default focus distance, as
in Mitsuba); because our renders choose them at render time, the film's output
encoding (``component_format``, ``file_format``); a sampler's type (its ``sample_count``
is rounded as Mitsuba's sampler of the type rounds it, and every type but ``independent``
is drawn by our one stratified sampler, :class:`~instancing.core.rng.PixelSampler`); and
the film's legacy ``banner``, which Mitsuba 3 reads and draws nothing for.

Everything else (other plugins such as ``bumpmap``, ``projector``,
other textures, unknown tags, attributes or parameters such as
``flip_normals`` on cylinders and cubes) is never dropped silently: all such elements
are collected and reported in one :class:`~instancing.core.errors.SceneError`, one
line per element with its file and line number.
"""

from __future__ import annotations

import functools
import math
import os
import re
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np

from ..core import transform as tf
from ..core.backend import mitsuba_module
from ..core.errors import MeshFileError, SceneError, TransformError
from ..materials.material import LOBES, MATERIAL_TYPES, parse_material
from ..materials.bump_map import PARAMETERS as BUMP_MAP_PARAMETERS
from ..materials.normal_map import PARAMETERS as NORMAL_MAP_PARAMETERS
from ..materials.parameter import CHOICE, COLOR, FLAG, IOR, NAME, NUMBER, Parameter
from ..materials.texture import TEXTURE_KEYS
from ..models.sdf_grid import NORMAL_MODES
from ..scene.camera import (CUBIC_FILTERS, GAUSSIAN_REACH, JITTERED_SAMPLERS, MAX_RFILTER_REACH, PIXEL_FORMATS,
                            RFILTER_SIZES, SAMPLERS, diagonal_fov, fov_along_x)
from .mesh_file import read_mesh

__all__ = ["xml_to_scene_dict", "coordinate_system"]

#: Mitsuba's film size when a sensor has no ``<film>`` (or the film no size).
DEFAULT_FILM_SIZE = (768, 576)
#: The pixel formats of Mitsuba's ``hdrfilm``.
MITSUBA_PIXEL_FORMATS = ("luminance", "luminance_alpha", "rgb", "rgba", "xyz", "xyza")
#: How deep elements and includes may nest (Mitsuba's own scenes nest under 10 deep).
MAX_NESTING = 100
#: Mitsuba's constant texture without colour conversion (read as a one-colour checkerboard).
RAW_CONSTANT = "rawconstant"
#: Mitsuba's tolerance for a frame without scale: each entry of M M^T within it of I's.
RIGID_TOLERANCE = 1e-3
#: Name of the black diffuse material Mitsuba gives emitting shapes without a BSDF.
EMITTER_DEFAULT_MATERIAL = "mitsuba:emitter-default-black"

_VALUE_TAGS = frozenset({"float", "integer", "boolean", "string", "point", "vector", "rgb",
                         "spectrum", "transform"})
_OBJECT_TAGS = frozenset({"shape", "bsdf", "emitter", "sensor", "film", "rfilter", "sampler",
                          "integrator", "texture", "medium", "phase", "volume", "scene"})
_TRANSFORM_OPS = frozenset({"translate", "rotate", "scale", "matrix", "lookat"})
_ANALYTIC_SHAPES = ("sphere", "cube", "rectangle", "disk", "cylinder")
_MESH_SHAPES = ("obj", "ply", "serialized")
_GRID_SHAPES = ("sdfgrid",)
#: Shapes read from a file whose geometry is not a mesh: each file's model is read by ours.
_CURVE_SHAPES = ("linearcurve", "bsplinecurve")
_FILE_SHAPES = _MESH_SHAPES + _GRID_SHAPES + _CURVE_SHAPES
_SEPARATORS = re.compile(r"[\s,;]+")
_NUMBER = re.compile(r"[+-]?(?:\d+\.?\d*|\.\d+)(?:[eE][+-]?\d+)?\Z")
#: A list of such numbers, separated as :func:`_tokens` splits them.
_NUMBER_LIST = re.compile(r"[\s,;]*[+-]?(?:\d+\.?\d*|\.\d+)(?:[eE][+-]?\d+)?"
                          r"(?:[\s,;]+[+-]?(?:\d+\.?\d*|\.\d+)(?:[eE][+-]?\d+)?)*[\s,;]*\Z")
_INTEGER = re.compile(r"[+-]?\d+\Z")
_PARAM_NAME = re.compile(r"\$([A-Za-z_][A-Za-z0-9_]*)")


# -- reading XML with line numbers ---------------------------------------------------------------


@dataclass
class _Node:
    """One XML element with where it was written (file, line)."""

    tag: str
    attrib: dict[str, str]
    file: Path
    line: int
    children: list["_Node"] = field(default_factory=list)
    text: str = ""

    @property
    def where(self) -> str:
        return f"{self.file}:{self.line}"

    def describe(self) -> str:
        """``<tag type="..." id="...">`` for messages."""
        keys = [k for k in ("type", "name", "id") if k in self.attrib]
        return "<" + " ".join([self.tag] + [f'{k}="{self.attrib[k]}"' for k in keys]) + ">"


class _NodeBuilder:
    """ElementTree parser target that builds :class:`_Node` trees with line numbers."""

    def __init__(self, path: Path):
        self.path = path
        self.parser = None  # set after the parser exists: its expat object gives line numbers
        self.stack: list[_Node] = []
        self.root: _Node | None = None

    def start(self, tag: str, attrib: dict[str, str]) -> None:
        node = _Node(tag, dict(attrib), self.path, self.parser.parser.CurrentLineNumber)
        if self.stack:
            self.stack[-1].children.append(node)
        else:
            self.root = node
        self.stack.append(node)

    def end(self, tag: str) -> None:
        self.stack.pop()

    def data(self, text: str) -> None:
        if self.stack:
            self.stack[-1].text += text

    def close(self) -> _Node | None:
        return self.root


def _read_xml(path: Path) -> _Node:
    """Parse one XML file safely (defusedxml), every element tagged with its line."""
    try:
        from defusedxml import DefusedXmlException
        from defusedxml.ElementTree import DefusedXMLParser, ParseError
    except ImportError:  # pragma: no cover - defusedxml is a dependency
        raise SceneError(f"{path}: reading Mitsuba XML needs the 'defusedxml' package "
                         "(pip install defusedxml)") from None
    try:
        data = path.read_bytes()
    except OSError as err:
        raise SceneError(f"{path}: cannot read the file ({err.strerror})") from None
    builder = _NodeBuilder(path)
    parser = DefusedXMLParser(target=builder, forbid_dtd=False, forbid_entities=True,
                              forbid_external=True)
    builder.parser = parser
    try:
        parser.feed(data)
        root = parser.close()
    except ParseError as err:
        line, column = err.position
        message = str(err).split(":")[0]
        raise SceneError(f"{path}:{line}: malformed XML at line {line}, column {column + 1}: "
                         f"{message}") from None
    except DefusedXmlException as err:
        line = parser.parser.CurrentLineNumber
        raise SceneError(f"{path}:{line}: refused to parse XML with entity declarations or "
                         f"external references (a possible entity expansion attack): {err}") from None
    if root is None:  # pragma: no cover - expat reports an empty document as malformed
        raise SceneError(f"{path}: no XML element found")
    return root


# -- defaults, $parameters and includes --------------------------------------------------------


def _version(node: _Node) -> None:
    """Check a root element's ``version="major.minor.patch"``."""
    value = node.attrib.get("version")
    if value is None:
        raise SceneError(f"{node.where}: the root element <{node.tag}> needs a version attribute "
                         '(e.g. version="3.0.0")')
    parts = value.strip().split(".")
    if len(parts) != 3 or not all(p.isdigit() for p in parts):
        raise SceneError(f"{node.where}: cannot parse the version number {value!r} "
                         "(expected major.minor.patch)")
    if int(parts[0]) not in (2, 3):
        raise SceneError(f"{node.where}: scene version {value} is not supported; expected a "
                         "Mitsuba 3 scene (version 3.x.y, or 2.x.y with the same syntax)")


class _Expander:
    """Apply ``<default>``, ``$name`` substitution and ``<include>`` in document order."""

    def __init__(self, main_dir: Path, parameters: dict[str, str]):
        self.main_dir = main_dir
        #: Folders added by ``<path>``, the latest first (Mitsuba prepends them to its
        #: file resolver): searched after the referring file's own folder.
        self.search: list[Path] = []
        self.params = dict(parameters)
        self.names = sorted(self.params, key=len, reverse=True)
        #: The parameters that some ``$name`` or ``<default>`` uses (Mitsuba refuses others).
        self.used: set[str] = set()

    def substitute(self, node: _Node) -> dict[str, str]:
        attrib = {}
        names = self.names  # longest first, so that $sx is not $s followed by 'x' (as Mitsuba)
        for key, value in node.attrib.items():
            if "$" in value:
                for name in names:
                    if "$" + name in value:
                        self.used.add(name)
                        value = value.replace("$" + name, self.params[name])
                if "$" in value:
                    missing = _PARAM_NAME.findall(value) or [value]
                    raise SceneError(f"{node.where}: {node.describe()}: undefined parameter "
                                     f"${missing[0]} in {key}={node.attrib[key]!r} (declare it with "
                                     f'<default name="{missing[0]}" value="..."/>)')
            attrib[key] = value
        return attrib

    def expand(self, node: _Node, stack: tuple[Path, ...], at_root: bool = False,
               depth: int = 1) -> list[_Node]:
        """The node with substitutions applied, or what an include stands for (``at_root``:
        a direct child of the main scene's root; ``depth``: its elements and includes above,
        bounded so that the recursive steps here and after cannot exhaust Python's stack)."""
        if depth > MAX_NESTING:
            raise SceneError(f"{node.where}: {node.describe()} is nested more than {MAX_NESTING} "
                             "elements and includes deep")
        attrib = self.substitute(node)
        if node.tag == "default":
            if set(attrib) != {"name", "value"} or not attrib["name"]:
                raise SceneError(f"{node.where}: <default> needs exactly a non-empty 'name' and "
                                 f"a 'value', got {attrib}")
            self.used.add(attrib["name"])
            if attrib["name"] not in self.params:
                self.params[attrib["name"]] = attrib["value"]
                self.names = sorted(self.params, key=len, reverse=True)
            return []
        if node.tag == "include":
            return self.include(node, attrib, stack, depth)
        if node.tag == "path":
            if not at_root:
                raise SceneError(f"{node.where}: <path> must be a direct child of a scene "
                                 "file's root")
            self.add_path(node, attrib)
            return []
        out = _Node(node.tag, attrib, node.file, node.line, text=node.text)
        for child in node.children:
            out.children.extend(self.expand(child, stack, depth=depth + 1))
        return [out]

    def include(self, node: _Node, attrib: dict[str, str], stack: tuple[Path, ...],
                depth: int) -> list[_Node]:
        if set(attrib) != {"filename"}:
            raise SceneError(f"{node.where}: <include> needs exactly a 'filename' attribute, "
                             f"got {sorted(attrib)}")
        folders = self.folders(node)
        path = _resolve(attrib["filename"], *folders)
        if path is None:
            raise SceneError(f"{node.where}: included file {attrib['filename']!r} not found "
                             f"(looked in {_folders(*folders)})")
        key = path.resolve()
        if key in stack:
            chain = " -> ".join(str(p) for p in stack[stack.index(key):] + (key,))
            raise SceneError(f"{node.where}: <include> cycle: {chain}")
        root = _read_xml(path)
        inner = stack + (key,)
        if root.tag != "scene":
            # A single included object: its root needs a version, as Mitsuba's.
            _version(root)
            del root.attrib["version"]
            return self.expand(root, inner, depth=depth + 1)
        if "version" in root.attrib:
            _version(root)
        out = []
        for child in root.children:
            # (An included scene's root may hold <path> too, as in Mitsuba.)
            out.extend(self.expand(child, inner, at_root=True, depth=depth + 1))
        return out


    def folders(self, node: _Node) -> tuple[Path, ...]:
        """Where a file named in ``node`` is looked for: its own file's folder, the ``<path>``
        folders (latest first), the main scene's folder."""
        return (node.file.parent, *self.search, self.main_dir)

    def add_path(self, node: _Node, attrib: dict[str, str]) -> None:
        """``<path value="folder"/>``: a search folder, relative to the file it is written
        in, else (as Mitsuba reads one in an included file) to the main scene's folder; a
        direct child of a scene file's root, and it must exist in one of them."""
        if set(attrib) != {"value"}:
            raise SceneError(f"{node.where}: <path> needs exactly a 'value' attribute, got "
                             f"{sorted(attrib)}")
        folder = Path(attrib["value"])
        candidates = [folder] if folder.is_absolute() else [node.file.parent / folder,
                                                             self.main_dir / folder]
        found = [c for c in candidates if c.is_dir()]
        if not found:
            raise SceneError(f"{node.where}: <path> folder {attrib['value']!r} not found (looked "
                             f"in {_folders(*(c.parent for c in candidates))})")
        self.search.insert(0, found[0])


def _folders(*folders: Path) -> str:
    """The distinct folders searched, for messages."""
    return " and ".join(dict.fromkeys(str(f) for f in folders))


def _resolve(filename: str, *folders: Path) -> Path | None:
    """The first existing file among ``folder / filename`` (an absolute name as is)."""
    name = Path(filename)
    if name.is_absolute():
        return name if name.is_file() else None
    for folder in folders:
        if (folder / name).is_file():
            return folder / name
    return None


# -- values --------------------------------------------------------------------------------------


class _Invalid(Exception):
    """An invalid or unsupported element; becomes one line of the final report.

    ``node``, when given, is where the report points (else the element being converted).
    """

    def __init__(self, message: str, node: _Node | None = None):
        super().__init__(message)
        self.node = node


def _at(node: _Node, action: Callable[[], Any]) -> Any:
    """Run ``action``, locating an unlocated problem at ``node``."""
    try:
        return action()
    except _Invalid as err:
        raise _Invalid(str(err), err.node or node) from None


def _tokens(text: str) -> list[str]:
    return [t for t in _SEPARATORS.split(text.strip()) if t]


def _number(text: str, what: str) -> float:
    text = text.strip()
    if not _NUMBER.match(text):
        raise _Invalid(f"{what}: cannot parse {text!r} as a number")
    return float(text)


def _numbers(text: str, counts: tuple[int, ...], what: str) -> list[float]:
    tokens = _tokens(text)
    if len(tokens) not in counts:
        raise _Invalid(f"{what}: expected {' or '.join(map(str, counts))} numbers, got {text!r}")
    if _NUMBER_LIST.match(text):  # (every token a number: converted at once)
        return [float(t) for t in tokens]
    return [_number(t, what) for t in tokens]


def _xyz(node: _Node, default: float | None, what: str, extra: tuple[str, ...] = ()) -> list[float]:
    """x/y/z attributes (missing ones = ``default``; all three required without one, as
    Mitsuba's ``<point>`` and ``<vector>``) or ``value`` with 1 or 3 numbers."""
    allowed = {"x", "y", "z", "value", *extra}
    unknown = sorted(set(node.attrib) - allowed)
    if unknown:
        raise _Invalid(f"{what}: unexpected attributes {unknown}")
    if "value" in node.attrib:
        if any(k in node.attrib for k in "xyz"):
            raise _Invalid(f"{what}: cannot mix 'value' with 'x'/'y'/'z'")
        values = _numbers(node.attrib["value"], (1, 3), what)
        return values * 3 if len(values) == 1 else values
    missing = [k for k in "xyz" if k not in node.attrib]
    if default is None and missing:
        raise _Invalid(f"{what}: missing attributes {missing} (give x, y and z, or 'value')")
    return [_number(node.attrib[k], what) if k in node.attrib else default for k in "xyz"]


def _check_attributes(node: _Node, required: set[str], optional: set[str] = frozenset()) -> None:
    keys = node.attrib.keys()
    if keys == required or (required <= keys and keys - required <= optional):
        return
    missing = sorted(required - set(node.attrib))
    unknown = sorted(set(node.attrib) - required - set(optional))
    if missing or unknown:
        raise _Invalid(f"{node.describe()}: " + "; ".join(
            ([f"missing attributes {missing}"] if missing else [])
            + ([f"unexpected attributes {unknown}"] if unknown else [])))


def _check_constant_spectrum(node: _Node) -> None:
    """A ``<spectrum>`` given by its ``value`` (a constant or wavelength:value pairs); a typed
    one (Mitsuba's ``d65``, ``srgb``, ``blackbody`` plugins) is named as unsupported."""
    if "type" in node.attrib:
        raise _Invalid(f"{node.describe()}: spectrum type {node.attrib['type']!r} is not supported "
                       "(only <spectrum value=\"...\"/>: one constant, or wavelength:value pairs)", node)
    _check_attributes(node, {"name", "value"})


def _value(node: _Node) -> str:
    """The ``value`` of a ``<float|integer|string|boolean|rgb name value>`` parameter."""
    _check_attributes(node, {"name", "value"})
    return node.attrib["value"]


def coordinate_system(n: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Mitsuba's ``coordinate_system``: two unit vectors completing unit ``n`` to a frame.

    The branchless construction of Duff et al., "Building an Orthonormal Basis,
    Revisited" (JCGT 2017), in float64; (s, t, n) is right-handed.
    """
    x, y, z = (float(c) for c in n)
    sign = 1.0 if z >= 0 else -1.0
    a = -1.0 / (sign + z)
    b = x * y * a
    return (np.array([x * x * a * sign + 1.0, b * sign, -x * sign]),
            np.array([b, sign + y * y * a, -y]))


def _rotate(axis: list[float], angle: float, what: str) -> tf.Transform:
    """Mitsuba 3's ``rotate``, which does *not* normalize the axis (measured with 3.9.1).

    ``c I + (1 - c) a a^T + s [a]_x``: a rotation for a unit axis (then built by
    :func:`~instancing.core.transform.rotate`), otherwise the same non-rigid matrix Mitsuba
    builds, so that a file renders as it does in Mitsuba.
    """
    a = np.asarray(axis, np.float64)
    if float(a @ a) == 1.0:
        return tf.rotate(axis, angle)
    if not a.any():
        raise _Invalid(f"{what}: zero rotation axis")
    theta = math.radians(angle)
    c, s = math.cos(theta), math.sin(theta)
    cross = np.array([[0.0, -a[2], a[1]], [a[2], 0.0, -a[0]], [-a[1], a[0], 0.0]])
    m = np.eye(4)
    m[:3, :3] = c * np.eye(3) + (1.0 - c) * np.outer(a, a) + s * cross
    return tf.from_matrix(m, what)


def _rigid(to_world: np.ndarray, what: str) -> np.ndarray:
    """A sensor's, spot light's or environment map's frame, rigid within Mitsuba's tolerance
    (its ``has_scale``: every entry of M M^T within 1e-3 of the identity's, so that rotations
    written with six digits pass), its linear part then snapped to the nearest rotation or
    reflection (the polar factor U V^T of its SVD)."""
    linear = to_world[:3, :3]
    if not np.abs(linear @ linear.T - np.eye(3)).max() <= RIGID_TOLERANCE:
        raise _Invalid(f"{what} must be rigid (no scale or shear, within Mitsuba's tolerance "
                       f"{RIGID_TOLERANCE} on M M^T = I)")
    u, _, vt = np.linalg.svd(linear)
    frame = to_world.copy()
    frame[:3, :3] = u @ vt
    return frame


def _transform(node: _Node, checked: bool = True) -> np.ndarray:
    """The 4x4 matrix of a ``<transform>``: operations act in written order (first listed
    first), composed in float64. ``checked``: the result is refused here when singular,
    ill-conditioned or not affine; shapegroup instances' transforms are checked later in one
    batch, composed with their shapes' (:meth:`_Importer.check_grouped`)."""
    _check_attributes(node, {"name"})
    result = None
    for op in node.children:
        what = f"<{op.tag}>"
        try:
            if op.tag == "translate":
                step = tf.translate(_xyz(op, 0.0, what))
            elif op.tag == "scale":
                step = tf.scale(_xyz(op, 1.0, what))
            elif op.tag == "rotate":
                if "angle" not in op.attrib:
                    raise _Invalid(f"{what}: missing attribute 'angle'")
                step = _rotate(_xyz(op, 0.0, what, extra=("angle",)),
                               _number(op.attrib["angle"], what), what)
            elif op.tag == "matrix":
                _check_attributes(op, {"value"})
                values = _numbers(op.attrib["value"], (16, 9), what)
                if len(values) == 16:
                    step = np.array(values).reshape(4, 4)
                else:
                    step = np.eye(4)
                    step[:3, :3] = np.reshape(values, (3, 3))
            elif op.tag == "lookat":
                _check_attributes(op, {"origin", "target"}, {"up"})
                origin, target = (np.array(_numbers(op.attrib[k], (3,), f"{what} {k}"))
                                  for k in ("origin", "target"))
                up = np.array(_numbers(op.attrib["up"], (3,), f"{what} up")) if "up" in op.attrib \
                    else np.zeros(3)
                if not up.any():
                    # Mitsuba picks an up vector from the viewing direction.
                    forward = target - origin
                    norm = np.linalg.norm(forward)
                    if norm == 0:
                        raise _Invalid(f"{what}: origin and target coincide")
                    up = coordinate_system(forward / norm)[0]
                step = tf.look_at(origin.tolist(), target.tolist(), up.tolist())
            else:
                raise _Invalid(f"{what}: unexpected element in a transform; expected one of "
                               f"{sorted(_TRANSFORM_OPS)}")
            step = step if isinstance(step, np.ndarray) else step.to_numpy()[0]
            result = step if result is None else step @ result
        except TransformError as err:
            raise _Invalid(f"{what}: {err}", op) from None
        except _Invalid as err:
            raise _Invalid(str(err), err.node or op) from None
    result = np.eye(4) if result is None else result
    if checked:
        try:
            tf.check_affine_matrix(result, node.describe())
        except TransformError as err:
            raise _Invalid(str(err)) from None
    return result


class _Props:
    """The parameters and nested objects of one plugin element; tracks what was used."""

    def __init__(self, importer: "_Importer", node: _Node):
        self.node = node
        self.importer = importer
        self.values: dict[str, _Node] = {}
        self.objects: list[_Node] = []
        self.used: set[str] = set()
        for child in node.children:
            if child.tag == "ref" or (child.tag in _OBJECT_TAGS and not
                                      (child.tag == "spectrum" and "type" not in child.attrib)):
                self.objects.append(child)
            elif child.tag in _VALUE_TAGS:
                name = child.attrib.get("name")
                if not name:
                    importer.report(child, f"{child.describe()} needs a 'name' attribute")
                elif name in self.values:
                    importer.report(child, f"parameter {name!r} given twice (first at line "
                                           f"{self.values[name].line})")
                else:
                    self.values[name] = child
            else:
                importer.report(child, f"unknown element {child.describe()} in {node.describe()}")
        if node.text.strip():
            importer.report(node, f"unexpected text {node.text.strip()[:40]!r} in {node.describe()}")

    def take(self, name: str, tags: tuple[str, ...]) -> _Node | None:
        """The parameter element ``name`` if it has one of ``tags`` (else report it)."""
        self.used.add(name)
        node = self.values.get(name)
        if node is not None and node.tag not in tags:
            raise _Invalid(f"{node.describe()}: parameter {name!r} of {self.node.describe()} "
                           f"must be given as {' or '.join('<' + t + '>' for t in tags)}", node)
        return node

    def ignore(self, *names: str) -> None:
        """Parameters accepted but without effect here (documented in the module docstring)."""
        self.used.update(names)

    def float(self, name: str, default: float | None) -> float | None:
        node = self.take(name, ("float", "integer"))
        if node is None:
            return default
        return _at(node, lambda: _number(_value(node), node.describe()))

    def texture_number(self, name: str) -> float | None:
        """A number parameter that a texture may give: a ``<float>``, or a ``<spectrum>`` of one
        constant value (Mitsuba's uniform spectrum, whose value its number lookups return)."""
        node = self.take(name, ("float", "integer", "spectrum"))
        if node is None:
            return None
        if node.tag == "spectrum":
            _check_constant_spectrum(node)
            text = _at(node, lambda: _value(node))
            if not _NUMBER.match(text.strip()):
                raise _Invalid(f"{node.describe()}: a spectrum for a number parameter must be one "
                               f"constant value, got {text!r}", node)
        return _at(node, lambda: _number(_value(node), node.describe()))

    def integer(self, name: str, default: int) -> int:
        node = self.take(name, ("integer",))
        if node is None:
            return default
        text = _at(node, lambda: _value(node)).strip()
        if not _INTEGER.match(text):
            raise _Invalid(f"{node.describe()}: cannot parse {text!r} as an integer", node)
        return int(text)

    def string(self, name: str, default: str | None) -> str | None:
        node = self.take(name, ("string",))
        return default if node is None else _at(node, lambda: _value(node))

    def boolean(self, name: str, default: bool) -> bool:
        node = self.take(name, ("boolean",))
        if node is None:
            return default
        value = _at(node, lambda: _value(node)).strip().lower()
        if value not in ("true", "false"):
            raise _Invalid(f"{node.describe()}: expected 'true' or 'false', got {value!r}", node)
        return value == "true"

    def point(self, name: str, default: list[float] | None) -> list[float] | None:
        node = self.take(name, ("point", "vector"))
        if node is None:
            return default
        return _at(node, lambda: _xyz(node, None, node.describe(), extra=("name",)))

    def color(self, name: str, default: float) -> list[float]:
        """An ``<rgb>`` (1 or 3 numbers) or ``<float>`` colour; a texture is reported by the caller."""
        node = self.take(name, ("rgb", "float", "integer", "spectrum"))
        if node is None:
            return [default] * 3
        if node.tag == "spectrum":
            _check_constant_spectrum(node)
            kind = ("illuminant" if self.node.tag == "emitter" else "volume" if self.node.tag == "volume"
                    else "unbounded" if name in UNBOUNDED_SPECTRA else "reflectance")
            return _at(node, lambda: spectrum_rgb(node.attrib["value"], kind, node.describe()))
        values = _at(node, lambda: _numbers(_value(node), (1, 3) if node.tag == "rgb" else (1,),
                                            node.describe()))
        return values * 3 if len(values) == 1 else values

    def transform(self, name: str, checked: bool = True) -> np.ndarray | None:
        node = self.take(name, ("transform",))
        return None if node is None else _at(node, lambda: _transform(node, checked))

    def finish(self) -> None:
        """Report every parameter nobody used (Mitsuba's "unreferenced property")."""
        for name, node in self.values.items():
            if name not in self.used:
                self.importer.report(node, f"parameter {name!r} ({node.describe()}) of "
                                           f"{self.node.describe()} is not supported")


# -- the importer --------------------------------------------------------------------------------


@dataclass
class _ShapeEntry:
    """One shape of a plain shape or a shape group, before instancing."""

    model: str
    to_world: np.ndarray
    material: str | None
    emitter: dict | None
    name: str | None
    media: dict[str, str] = field(default_factory=dict)


class _Importer:
    def __init__(self, path: Path, search: list[Path],
                 check: Callable[[str, dict, str], Any] | None = None):
        self.path = path
        self.check = check
        self.main_dir = path.parent
        self.search = search
        self.problems: list[tuple[Path, int, str]] = []
        self.ids: dict[str, _Node] = {}
        self.materials: dict[str, dict] = {}
        self.material_of_bsdf: dict[int, str | None] = {}
        self.media: dict[str, dict] = {}
        self.medium_of_node: dict[int, str | None] = {}
        self.models: dict[str, dict] = {}
        self.model_of_file: dict[tuple[str, Path], str] = {}
        self.group_entries: dict[int, list[_ShapeEntry]] = {}
        self.instances: list[dict] = []
        #: The shapegroup instances' positions in ``instances``, each with its element: their
        #: matrices are checked in one batch (:meth:`check_grouped`).
        self.grouped: list[tuple[int, _Node]] = []
        self.instance_ids: set[str] = set()
        self.lights: list[dict] = []

        self.cameras: list[dict] = []
        self.integrator_spec: dict | None = None

    def report(self, node: _Node, message: str) -> None:
        self.problems.append((node.file, node.line, message))

    def named_textures(self, node: _Node, props: "_Props", names: Sequence[str]) -> dict[str, dict]:
        """The textures nested in (or referenced by) an emitter under the parameter ``names``
        it takes, as texture dicts; every other nested object is reported."""
        taken, out = [], {}
        for child in props.objects:
            if child.attrib.get("name") not in names:
                continue
            taken.append(child)
            target = self.guarded(child, lambda child=child: self.lookup(child, "texture")
                                  if child.tag == "ref" else child)
            if target is None:
                continue
            if target.tag != "texture":
                self.report(child, f"{child.describe()} inside {node.describe()}: a texture is "
                                   "expected here")
                continue
            spec = self.guarded(target, lambda target=target: self.texture_spec(target, None))
            if spec is not None:
                out[child.attrib["name"]] = spec
        self.report_nested(node, props, taken)
        return out

    def report_nested(self, node: _Node, props: "_Props", taken: Sequence[_Node] = ()) -> None:
        """Report every nested object of a plugin but those it takes (``taken``)."""
        for child in props.objects:
            if not any(child is c for c in taken):
                self.report(child, f"{child.describe()} inside {node.describe()} is not supported")

    def guarded(self, node: _Node, action: Callable[[], Any]) -> Any:
        """Run ``action``; a value problem is reported (with the node's line) instead of raised."""
        try:
            return action()
        except _Invalid as err:
            self.report(err.node or node, str(err))
            return None

    # Ids ----------------------------------------------------------------------------------------

    def collect_ids(self, node: _Node) -> None:
        """Every object's id (in document order), and ``<alias id as>`` entries: another
        name for an object declared above (as Mitsuba's)."""
        for child in node.children:
            if child.tag == "alias":
                self.guarded(child, lambda child=child: self.alias(child))
                continue
            if child.tag in _OBJECT_TAGS and "id" in child.attrib:
                ident = child.attrib["id"]
                if ident in self.ids:
                    self.report(child, f"duplicate id {ident!r} (first used at "
                                       f"{self.ids[ident].where})")
                else:
                    self.ids[ident] = child
            if child.tag != "integrator":
                self.collect_ids(child)

    def alias(self, node: _Node) -> None:
        _check_attributes(node, {"id", "as"})
        source, target = node.attrib["id"], node.attrib["as"]
        if source not in self.ids:
            raise _Invalid(f"{node.describe()}: alias source id {source!r} is not declared above")
        if target in self.ids:
            raise _Invalid(f"{node.describe()}: alias id {target!r} is already in use (at "
                           f"{self.ids[target].where})")
        self.ids[target] = self.ids[source]

    def lookup(self, ref: _Node, *tags: str) -> _Node:
        """The element a ``<ref>`` names, which must have one of ``tags``."""
        _check_attributes(ref, {"id"}, {"name"})
        target = self.ids.get(ref.attrib["id"])
        if target is None:
            raise _Invalid(f"<ref id=\"{ref.attrib['id']}\">: no element has this id")
        if target.tag not in tags:
            raise _Invalid(f"<ref id=\"{ref.attrib['id']}\"> refers to {target.describe()} at "
                           f"{target.where}, but a " + " or ".join(f"<{t}>" for t in tags)
                           + " is expected here")
        return target

    # Top level ----------------------------------------------------------------------------------

    def run(self, root: _Node) -> dict:
        self.collect_ids(root)
        unexpected = sorted(set(root.attrib) - {"version"})
        if unexpected:
            self.report(root, f"unexpected attributes {unexpected} on <scene>")
        if root.text.strip():
            self.report(root, f"unexpected text {root.text.strip()[:40]!r} in <scene>")
        for node in root.children:
            self.guarded(node, lambda node=node: self.top_level(node))
        self.check_grouped()
        if self.problems:
            lines = [f"  {file}:{line}: {message}" for file, line, message in self.problems]
            raise SceneError(f"{self.path}: cannot import this Mitsuba scene, {len(lines)} "
                             "unsupported or invalid element(s):\n" + "\n".join(lines))
        scene: dict = {"models": self.models, "materials": self.materials,
                       "instances": self.instances, "lights": self.lights}
        if self.media:
            scene["media"] = self.media
        if self.cameras:
            scene["cameras"] = self.cameras
        if self.integrator_spec is not None:
            scene["integrator"] = self.integrator_spec
        return scene

    def top_level(self, node: _Node) -> None:
        kind = node.attrib.get("type")
        if node.tag == "shape":
            if kind == "shapegroup":
                self.shape_group(node)
            elif kind == "instance":
                self.instance(node)
            else:
                entry = self.shape(node)
                if entry is not None:
                    self.add_instance(entry, np.eye(4), node.attrib.get("id"), node)
        elif node.tag == "bsdf":
            self.material(node)
        elif ((node.tag == "emitter" and kind == "area") or node.tag == "texture"
              or (node.tag in ("film", "medium") and "id" in node.attrib)):
            # Converted where shapes (BSDFs, sensors) refer to it; unreferenced, no effect.
            return
        elif node.tag == "emitter":
            self.light(node)
        elif node.tag == "sensor":
            camera = self.sensor(node)
            if camera is not None:
                self.cameras.append(camera)
        elif node.tag == "integrator":
            self.integrator(node)
        elif node.tag == "alias":
            return  # (collect_ids resolves them)
        elif node.tag == "sampler":
            self.sampler(node)  # checked; a sensor that refers to it takes its sample count
        elif node.tag in _OBJECT_TAGS:
            self.report(node, f"{node.describe()} at the top level is not supported")
        else:
            self.report(node, f"unknown or unsupported element {node.describe()}")

    def check_object(self, node: _Node) -> None:
        _check_attributes(node, {"type"}, {"id", "name"})

    # Materials ----------------------------------------------------------------------------------

    def material(self, node: _Node) -> str | None:
        """Our material name for a ``<bsdf>`` (converted once), or None if unsupported."""
        if id(node) not in self.material_of_bsdf:
            # Converted once; a problem is reported at the <bsdf> itself, once.
            self.material_of_bsdf[id(node)] = self.guarded(node, lambda: self.convert_bsdf(node))
        return self.material_of_bsdf[id(node)]

    def convert_bsdf(self, node: _Node) -> str:
        spec = self.bsdf_spec(node)
        name = self.unique(self.materials, node.attrib.get("id") or f"bsdf@{node.file.name}:{node.line}")
        try:
            # Validated here, so that problems carry the line (files are read by the scene).
            parse_material(name, spec, _unread_file)
        except SceneError as err:
            raise _Invalid(f"{node.describe()}: {err}") from None
        self.materials[name] = spec
        return name

    def bsdf_spec(self, node: _Node, outer: tuple[_Node, ...] = ()) -> dict:
        """A ``<bsdf>`` as our material dict: the parameters its type takes, read by their
        kind (colours from ``<rgb>``, ``<float>`` or ``<spectrum>``); ``twosided`` with its
        nested BSDFs (``outer``: the BSDFs it is nested in, where a reference back to one
        is a cycle)."""
        self.check_object(node)
        kind = node.attrib["type"]
        if kind not in MATERIAL_TYPES:
            raise _Invalid(f"{node.describe()}: BSDF type {kind!r} is not supported; supported: "
                           f"{list(MATERIAL_TYPES)}")
        props = _Props(self, node)
        spec: dict[str, Any] = {"type": kind}
        # Nested BSDFs (of twosided, blendbsdf, mask, normalmap and bumpmap): <bsdf> elements and <ref>s to them.
        nested = [c for c in props.objects if self.nested_bsdf(kind, c)]
        chain = outer + (node,)
        for k, child in enumerate(nested):
            target = child if child.tag == "bsdf" else self.lookup(child, "bsdf")
            if any(target is c for c in chain):
                start = [c is target for c in chain].index(True)
                raise _Invalid(f"{child.describe()}: circular reference: "
                               + " -> ".join(c.describe() for c in chain[start:] + (target,)), child)
            spec[f"bsdf_{k}"] = self.bsdf_spec(target, chain)
        if kind == "twosided":
            self.report_nested(node, props, nested)
            props.finish()
            return spec
        parameters = (LOBES[kind].parameters if kind in LOBES else
                      NORMAL_MAP_PARAMETERS if kind == "normalmap" else BUMP_MAP_PARAMETERS)
        for child in props.objects:
            if any(child is c for c in nested):
                continue
            # A texture for a parameter: nested, or a <ref name id> to one declared elsewhere
            # (a bump map's under any name, or none).
            key = child.attrib.get("name") or ("texture" if kind == "bumpmap" else None)
            try:
                target = self.lookup(child, "texture") if child.tag == "ref" else child
                if target.tag != "texture" or key is None:
                    raise _Invalid(f"{child.describe()} inside {node.describe()} is not supported "
                                   "(a texture needs a 'name': the parameter it gives)", child)
                if key in props.values:
                    raise _Invalid(f"{child.describe()}: parameter {key!r} is also given at line "
                                   f"{props.values[key].line}", child)
                spec[key] = self.texture_spec(target, parameters.get(key))
            except _Invalid as err:
                self.report(err.node or child, str(err))
        readers = {COLOR: lambda key: props.color(key, 0.0),
                   NUMBER: lambda key: (props.texture_number(key) if parameters[key].texture
                                        else props.float(key, None)),
                   CHOICE: lambda key: props.string(key, None), NAME: lambda key: props.string(key, None),
                   FLAG: lambda key: props.boolean(key, False),
                   IOR: lambda key: (props.string(key, None) if props.values[key].tag == "string"
                                     else props.float(key, None))}
        for key, parameter in parameters.items():
            if key in props.values:
                spec[key] = readers[parameter.kind](key)
        props.finish()
        return spec

    def nested_bsdf(self, kind: str, child: _Node) -> bool:
        """Whether ``child`` of a ``kind`` BSDF is a nested BSDF: a ``<bsdf>``, an unnamed
        ``<ref>``, or a named one to a ``<bsdf>`` under a name that is no parameter of ``kind``
        (Mitsuba ignores the names of nested BSDFs, as in ``<ref name="bsdf" id="..."/>``)."""
        if child.tag != "ref" or "name" not in child.attrib:
            return child.tag in ("bsdf", "ref")
        target = self.ids.get(child.attrib.get("id", ""))
        parameters = LOBES[kind].parameters if kind in LOBES else {}
        return target is not None and target.tag == "bsdf" and child.attrib["name"] not in parameters

    def file_path(self, node: _Node, props: _Props, what: str) -> Path:
        """The resolved file of a plugin's ``filename`` (the element's folder, then the
        ``<path>`` folders, then the main file's; absolute names as they are)."""
        filename = props.string("filename", None)
        if filename is None:
            raise _Invalid(f"{node.describe()}: missing <string name=\"filename\">", node)
        path = _resolve(filename, node.file.parent, *self.search, self.main_dir)
        if path is None:
            folders = _folders(node.file.parent, *self.search, self.main_dir)
            raise _Invalid(f"{node.describe()}: {what} file {filename!r} not found (looked in "
                           f"{folders})", props.values["filename"])
        return path.resolve()

    def texture_spec(self, node: _Node, parameter: Parameter | None) -> dict:
        """A ``<texture>`` as our texture dict (a bitmap's file resolved like a mesh file's;
        colours of a texture for a number parameter as numbers)."""
        self.check_object(node)
        kind = node.attrib["type"]
        if kind not in TEXTURE_KEYS and kind != RAW_CONSTANT:
            raise _Invalid(f"{node.describe()}: texture type {kind!r} is not supported; supported: "
                           f"{[*TEXTURE_KEYS, RAW_CONSTANT]}", node)
        props = _Props(self, node)
        if kind == RAW_CONSTANT:
            return self.raw_constant(node, props, parameter)
        volumes = [child for child in props.objects if kind == "volume" and child.attrib.get("name") == "volume"]
        self.report_nested(node, props, volumes)
        spec: dict[str, Any] = {"type": kind}
        to_uv = props.transform("to_uv")
        if to_uv is not None:
            spec["to_uv"] = to_uv.tolist()
        if kind == "mesh_attribute":
            spec["name"] = props.string("name", None)
            if "scale" in props.values:
                spec["scale"] = props.float("scale", 1.0)
        elif kind == "volume":
            if not volumes:
                raise _Invalid(f"{node.describe()}: a volume texture needs its <volume name=\"volume\">", node)
            target = self.lookup(volumes[0], "volume") if volumes[0].tag == "ref" else volumes[0]
            spec["volume"] = self.volume_spec(target)
        elif kind == "checkerboard":
            for key, default in (("color0", 0.4), ("color1", 0.2)):
                color = props.color(key, default)
                number = parameter is not None and parameter.kind == NUMBER and len(set(color)) == 1
                spec[key] = color[0] if number else color
        else:
            props.ignore("accel")  # Mitsuba's choice of hardware lookups: no effect on values
            spec["filename"] = str(self.file_path(node, props, "texture"))
            for key in ("filter_type", "wrap_mode"):
                if key in props.values:
                    spec[key] = props.string(key, None)
            if "raw" in props.values:
                spec["raw"] = props.boolean("raw", False)
            # Mitsuba's storage of the texels: 'variant' (its float precision, as ours store them)
            # or 'fixed' (8-bit integers), which ours do not give.
            storage = props.values.get("format")
            if storage is not None and props.string("format", "variant") != "variant":
                raise _Invalid(f"{node.describe()}: format {_value(storage)!r} is not supported; ours "
                               "store the texels as floats (Mitsuba's 'variant')", storage)
        props.finish()
        return spec

    def raw_constant(self, node: _Node, props: "_Props", parameter: Parameter | None) -> dict:
        """A ``rawconstant`` texture (its ``value``: a ``<float>`` or a ``<vector>``, which
        Mitsuba returns without colour conversion, as ours render in RGB) as a checkerboard
        whose two colours are that value: the same on every square."""
        value = props.take("value", ("float", "integer", "vector"))
        if value is None:
            raise _Invalid(f"{node.describe()}: missing <float name=\"value\"> or <vector name=\"value\">",
                           node)
        numbers = _at(value, lambda: _numbers(_value(value), (3,) if value.tag == "vector" else (1,),
                                              value.describe()))
        props.finish()
        if parameter is not None and parameter.kind == NUMBER:
            if len(set(numbers)) > 1:
                raise _Invalid(f"{value.describe()}: a number parameter's rawconstant takes one value, "
                               f"got {_value(value)!r}", value)
            constant: Any = numbers[0]
        else:
            constant = numbers * 3 if len(numbers) == 1 else numbers
        return {"type": "checkerboard", "color0": constant, "color1": constant}

    def volume_spec(self, node: _Node) -> dict:
        """A ``<volume type="gridvolume">`` (its file resolved like a mesh file's; ``accel``
        accepted and ignored) or ``<volume type="constvolume">`` (its ``value`` a number or
        colour) as our volume dict, ``to_world`` as a matrix."""
        self.check_object(node)
        kind = node.attrib["type"]
        if kind not in ("gridvolume", "constvolume"):
            raise _Invalid(f"{node.describe()}: volume type {kind!r} is not supported; "
                           "supported: gridvolume, constvolume", node)
        props = _Props(self, node)
        self.report_nested(node, props)
        spec: dict[str, Any] = {"type": kind}
        if kind == "constvolume":
            spec["value"] = props.color("value", 1.0)
        else:
            props.ignore("accel")
            spec["filename"] = str(self.file_path(node, props, "volume grid"))
            for key in ("filter_type", "wrap_mode"):
                if key in props.values:
                    spec[key] = props.string(key, None)
            for key in ("raw", "use_grid_bbox"):
                if key in props.values:
                    spec[key] = props.boolean(key, False)
        to_world = props.transform("to_world")
        if to_world is not None:
            spec["to_world"] = to_world.tolist()
        props.finish()
        return spec

    @staticmethod
    def unique(taken: Any, name: str) -> str:
        candidate, k = name, 1
        while candidate in taken:
            k += 1
            candidate = f"{name}~{k}"
        return candidate

    # Shapes -------------------------------------------------------------------------------------

    def shape(self, node: _Node) -> _ShapeEntry | None:
        """One plain shape: its model, to_world (shape parameters folded in), BSDF, emitter."""
        self.check_object(node)
        kind = node.attrib["type"]
        if kind not in _ANALYTIC_SHAPES + _FILE_SHAPES:
            raise _Invalid(f"{node.describe()}: shape type {kind!r} is not supported; supported: "
                           f"{list(_ANALYTIC_SHAPES + _FILE_SHAPES)}, shapegroup, instance")
        props = _Props(self, node)
        ok = True

        def get(action, default=None):
            nonlocal ok
            try:
                return action()
            except _Invalid as err:
                ok = False
                self.report(err.node or node, str(err))
                return default

        to_world = get(lambda: props.transform("to_world"))
        to_world = np.eye(4) if to_world is None else to_world
        model = kind
        if kind == "sphere":
            center = get(lambda: props.point("center", [0.0, 0.0, 0.0]), [0.0] * 3)
            radius = get(lambda: props.float("radius", 1.0), 1.0)
            try:
                local = tf.translate(center) @ tf.scale(radius)
                to_world = to_world @ local.to_numpy()[0]
            except TransformError as err:
                ok = False
                self.report(node, f"{node.describe()}: center/radius: {err}")
        elif kind == "cylinder":
            p0 = np.array(get(lambda: props.point("p0", [0.0, 0.0, 0.0]), [0.0] * 3))
            p1 = np.array(get(lambda: props.point("p1", [0.0, 0.0, 1.0]), [0.0, 0.0, 1.0]))
            radius = get(lambda: props.float("radius", 1.0), 1.0)
            axis = p1 - p0
            length = float(np.linalg.norm(axis))
            if length == 0 or radius == 0:
                ok = False
                self.report(node, f"{node.describe()}: degenerate cylinder (p0 = p1 or radius 0)")
            else:
                # Mitsuba: to_world @ translate(p0) @ to_frame(frame of the axis) @ scale(r, r, length).
                n = axis / length
                s, t = coordinate_system(n)
                local = np.eye(4)
                local[:3, 0], local[:3, 1], local[:3, 2], local[:3, 3] = radius * s, radius * t, axis, p0
                to_world = to_world @ local
        # Mitsuba turns a sphere's normals inward under a mirroring to_world (a negative
        # determinant, a negative radius) and a mesh's where it computes them (see
        # placed_shading); ours follow the inverse transpose and keep their side.
        mirrored = bool(np.linalg.det(to_world[:3, :3]) < 0)
        flipped = kind in _ANALYTIC_SHAPES and get(lambda: props.boolean("flip_normals", False), False)
        if flipped and kind in ("rectangle", "disk"):
            # A flat shape's normal turned over: its plane mirrored onto itself (the
            # normal follows the inverse transpose; surface and uv stay).
            to_world = to_world @ np.diag([1.0, 1.0, -1.0, 1.0])
        elif kind in _ANALYTIC_SHAPES and flipped != (kind == "sphere" and mirrored):
            # Turned inside out: a sphere by flip_normals or a mirror (not both), a cube or
            # cylinder by flip_normals.
            model = self.inward_model(kind)
        if kind in _FILE_SHAPES:
            shading = {}
            if kind in _MESH_SHAPES:
                # Mitsuba flips v by default in OBJ files, not in PLY files; its serialized
                # plugin has no such flag, but a shape_index.
                flags = [("face_normals", False), ("flip_normals", False)]
                if kind != "serialized":
                    flags.append(("flip_tex_coords", kind == "obj"))
                shading = {flag: get(lambda flag=flag: props.boolean(flag, default), default)
                           for flag, default in flags}
                if kind == "serialized":
                    shading["shape_index"] = get(lambda: props.integer("shape_index", 0), 0)
            elif kind in _GRID_SHAPES:
                shading = {"normals": get(lambda: props.string("normals", "smooth"), "smooth")}
                if shading["normals"] not in NORMAL_MODES:
                    ok = False
                    self.report(props.values["normals"], f"{node.describe()}: normals "
                                f"{shading['normals']!r} is not one of {list(NORMAL_MODES)}")
            filename = get(lambda: props.string("filename", None))
            if filename is None:
                if ok:
                    self.report(node, f"{node.describe()}: missing <string name=\"filename\">")
                ok = False
            else:
                path = _resolve(filename, node.file.parent, *self.search, self.main_dir)
                if path is None:
                    ok = False
                    folders = _folders(node.file.parent, *self.search, self.main_dir)
                    self.report(props.values["filename"], f"{node.describe()}: "
                                f"{'mesh' if kind in _MESH_SHAPES else kind} file {filename!r} "
                                f"not found (looked in {folders})")
                elif kind in _MESH_SHAPES and path.suffix.lower() != "." + kind:
                    ok = False
                    self.report(node, f"{node.describe()}: file {filename!r} does not have the "
                                      f"extension .{kind}")
                elif kind in _CURVE_SHAPES:
                    # Its to_world moves the control points but not their radii: the model
                    # holds the moved points, its instance nothing more.
                    model = self.mesh_model(kind, path, points_to_world=tuple(map(tuple, to_world)))
                    to_world = np.eye(4)
                else:
                    if kind in _MESH_SHAPES and (mirrored or not tf.is_similarity(to_world)):
                        shading = get(lambda: self.placed_shading(node, path, shading, to_world), shading)
                    model = self.mesh_model(kind, path, **shading)
        material, emitter, media = None, None, {}
        for child in props.objects:
            if child.attrib.get("name") in ("interior", "exterior") and child.tag in ("ref", "medium"):
                side = child.attrib["name"]
                if side in media:
                    ok = False
                    self.report(child, f"{node.describe()} has more than one {side} medium")
                    continue
                media[side] = self.guarded(child, lambda child=child: self.medium(child))
                ok = ok and media[side] is not None
                continue
            if child.tag == "ref" and self.ids.get(child.attrib.get("id", "")) is not None \
                    and self.ids[child.attrib["id"]].tag == "emitter":
                # An area emitter declared at the top level, referenced by id.
                child = self.ids[child.attrib["id"]]
            if child.tag == "bsdf" or child.tag == "ref":
                if material is not None:
                    ok = False
                    self.report(child, f"{node.describe()} has more than one BSDF")
                    continue
                try:
                    material = self.material(child if child.tag == "bsdf" else self.lookup(child, "bsdf"))
                except _Invalid as err:
                    self.report(err.node or child, str(err))
                if material is None:
                    ok = False
            elif child.tag == "emitter":
                if emitter is not None:
                    ok = False
                    self.report(child, f"{node.describe()} has more than one emitter")
                    continue
                emitter = self.guarded(child, lambda child=child: self.area_emitter(child))
                ok = ok and emitter is not None
            else:
                ok = False
                self.report(child, f"{child.describe()} inside {node.describe()} is not supported")
        props.finish()
        if not ok:
            return None
        if emitter is not None and material is None:
            # Mitsuba gives emitting shapes without a BSDF a black diffuse one.
            material = EMITTER_DEFAULT_MATERIAL
            self.materials[material] = {"type": "diffuse", "reflectance": [0.0, 0.0, 0.0]}
        return _ShapeEntry(model, to_world, material, emitter, node.attrib.get("id"), media)

    def placed_shading(self, node: _Node, path: Path, shading: dict, to_world: np.ndarray) -> dict:
        """The flags of a mesh under a to_world that mirrors it or is no similarity, where
        Mitsuba computes its normals (without normals in the file, or with ``face_normals``;
        the file's own normals follow the inverse transpose in both). Mitsuba computes them
        after moving the vertices by to_world: a mirror reverses the triangles' winding, and
        with it their normals, where our instances keep a normal's side (so the mesh is read
        turned inside out); and smooth normals computed from stretched or sheared triangles
        are not the inverse transpose of the unstretched ones (so the model computes them
        under the linear part, ``computed_normals_to_world``, scaled to determinant +-1:
        shapes that differ by a uniform scale share a model)."""
        if not shading["face_normals"]:
            try:
                if read_mesh(path, shading.get("shape_index", 0)).normals is not None:
                    return shading
            except MeshFileError as err:
                raise _Invalid(f"{node.describe()}: {err}", node) from None
        linear = to_world[:3, :3]
        shading = {**shading, "flip_normals": shading["flip_normals"] != bool(np.linalg.det(linear) < 0)}
        if not shading["face_normals"] and not tf.is_similarity(to_world):
            frame = np.eye(4)
            frame[:3, :3] = linear / np.cbrt(abs(np.linalg.det(linear)))
            shading["computed_normals_to_world"] = tuple(map(tuple, frame))
        return shading

    def inward_model(self, kind: str) -> str:
        """The analytic model ``kind`` turned inside out (``flip_normals``), declared once."""
        key = (kind, "inward")
        if key not in self.model_of_file:
            name = self.unique(self.models, f"{kind}.inward")
            self.models[name] = {"type": kind, "flip_normals": True}
            self.model_of_file[key] = name
        return self.model_of_file[key]

    def mesh_model(self, kind: str, path: Path, **flags: bool | int | str | tuple) -> str:
        """The model of a mesh, grid or curve file read with these flags (and a serialized
        file's shape index, a grid's normals, a curve's ``points_to_world`` as a tuple of
        rows): one per distinct file and flags."""
        key = (kind, path.resolve(), *sorted(flags.items()))
        if key not in self.model_of_file:
            name = self.unique(self.models, f"{path.stem}.{kind}")
            self.models[name] = {"type": kind, "filename": str(key[1]),
                                 **{k: [list(row) for row in v] if isinstance(v, tuple) else v
                                    for k, v in flags.items()}}
            self.model_of_file[key] = name
        return self.model_of_file[key]

    def area_emitter(self, node: _Node) -> dict:
        self.check_object(node)
        if node.attrib["type"] != "area":
            raise _Invalid(f"{node.describe()}: emitter type {node.attrib['type']!r} inside a shape "
                           "is not supported (only 'area')")
        props = _Props(self, node)
        textures = self.named_textures(node, props, ("radiance",))
        radiance = textures.get("radiance") or props.color("radiance", 1.0)
        props.finish()
        return {"type": "area", "radiance": radiance}

    def shape_group(self, node: _Node) -> list[_ShapeEntry]:
        """The shapes of a ``shapegroup`` (converted once; instanced by ``instance`` shapes)."""
        if id(node) in self.group_entries:
            return self.group_entries[id(node)]
        self.group_entries[id(node)] = entries = []
        self.check_object(node)
        props = _Props(self, node)
        for child in props.objects:
            if child.tag != "shape":
                self.report(child, f"{child.describe()} inside a shapegroup is not supported")
            elif child.attrib.get("type") in ("shapegroup", "instance"):
                self.report(child, f"{child.describe()}: shape groups cannot contain shape groups "
                                   "or instances")
            else:
                entry = self.guarded(child, lambda child=child: self.shape(child))
                if entry is not None:
                    entries.append(entry)
        props.finish()
        return entries

    def instance(self, node: _Node) -> None:
        self.check_object(node)
        props = _Props(self, node)
        # (Checked with every instance's, in one batch, when the scene is parsed.)
        to_world = props.transform("to_world", checked=False)
        groups = []
        for child in props.objects:
            if child.tag == "ref":
                groups.append(self.guarded(child, lambda child=child: self.lookup(child, "shape")))
            elif child.tag == "shape" and child.attrib.get("type") == "shapegroup":
                groups.append(child)
            else:
                self.report(child, f"{child.describe()} inside an instance is not supported")
        props.finish()
        groups = [g for g in groups if g is not None]
        if len(groups) != 1 or groups[0].attrib.get("type") != "shapegroup":
            raise _Invalid(f"{node.describe()}: an instance needs exactly one shapegroup "
                           "(<ref id=\"...\"/> to a <shape type=\"shapegroup\">)")
        entries = self.shape_group(groups[0])
        base = node.attrib.get("id") or f"instance@{node.file.name}:{node.line}"
        for k, entry in enumerate(entries):
            self.grouped.append((len(self.instances), node))
            self.add_instance(entry, np.eye(4) if to_world is None else to_world,
                              f"{base}/{entry.name or k}", node)

    def check_grouped(self) -> None:
        """The shapegroup instances' matrices (left unchecked where they are read, as there
        may be many) checked in one batch as a scene's instances are; the first that fails is
        reported at its instance's line."""
        if not self.grouped:
            return
        matrices = np.array([self.instances[k]["to_world"] for k, _ in self.grouped], np.float64)
        try:
            tf.checked_affine_inverse(matrices)
            return
        except TransformError:
            pass
        for matrix, (_, node) in zip(matrices, self.grouped):
            try:
                tf.checked_affine_inverse(matrix, "its to_world")
            except TransformError as err:
                self.report(node, f"{node.describe()}: {err}")
                return

    def add_instance(self, entry: _ShapeEntry, to_world: np.ndarray, name: str | None,
                     node: _Node) -> None:
        name = self.unique(self.instance_ids, name or f"{entry.model}@{node.file.name}:{node.line}")
        self.instance_ids.add(name)
        instance = {"id": name, "model": entry.model, "to_world": to_world @ entry.to_world}
        if entry.material is not None:
            instance["material"] = entry.material
        if entry.emitter is not None:
            instance["emitter"] = dict(entry.emitter)
        instance.update(entry.media)
        self.instances.append(instance)

    # Lights -------------------------------------------------------------------------------------

    def light(self, node: _Node) -> None:
        self.check_object(node)
        kind = node.attrib["type"]
        if kind not in ("point", "spot", "projector", "directional", "constant", "envmap"):
            raise _Invalid(f"{node.describe()}: emitter type {kind!r} is not supported at the top "
                           "level; supported: point, spot, projector, directional, constant, "
                           "envmap (and area inside shapes)")
        props = _Props(self, node)
        textures = self.named_textures(node, props, {"spot": ("texture",),
                                                     "projector": ("irradiance",)}.get(kind, ()))
        if kind in ("constant", "envmap") and any(light["type"] in ("constant", "envmap")
                                                  for light in self.lights):
            raise _Invalid(f"{node.describe()}: only one environment emitter (constant or "
                           "envmap) per scene, as in Mitsuba")
        if kind == "constant":
            light = {"type": "constant", "radiance": props.color("radiance", 1.0)}
        elif kind == "envmap":
            # mis_compensation only changes how Mitsuba samples the map (not the image).
            props.ignore("mis_compensation")
            light = {"type": "envmap", "filename": str(self.file_path(node, props, "environment map")),
                     "scale": props.float("scale", 1.0)}
            to_world = props.transform("to_world")
            if to_world is not None:
                light["to_world"] = _rigid(to_world, f"{node.describe()}: the environment's "
                                                     "to_world").tolist()
        elif kind == "spot":
            to_world = props.transform("to_world")
            to_world = np.eye(4) if to_world is None else _rigid(to_world, f"{node.describe()}: "
                                                                           "the spot's to_world")
            light = {"type": "spot", "intensity": props.color("intensity", 1.0),
                     "to_world": to_world.tolist()}
            cutoff = props.float("cutoff_angle", 20.0)
            light.update(cutoff_angle=cutoff, beam_width=props.float("beam_width", 0.75 * cutoff),
                         **textures)
        elif kind == "projector":
            to_world = props.transform("to_world")
            to_world = np.eye(4) if to_world is None else _rigid(to_world, f"{node.describe()}: "
                                                                           "the projector's to_world")
            fov, axis = field_of_view(props.float("fov", None), props.string("fov_axis", None),
                                      props.string("focal_length", None), node.describe())
            light = {"type": "projector", "to_world": to_world.tolist(), "scale": props.float("scale", 1.0),
                     "fov": fov, "fov_axis": axis,
                     "irradiance": textures.get("irradiance") or props.color("irradiance", 1.0)}
        else:
            key, vector_key = ("position", "intensity") if kind == "point" else ("direction", "irradiance")
            vector = props.point(key, None)
            to_world = props.transform("to_world")
            if vector is not None and to_world is not None:
                raise _Invalid(f"{node.describe()}: give either {key!r} or 'to_world', not both")
            if vector is None:
                m = np.eye(4) if to_world is None else to_world
                # Mitsuba: the light sits at to_world's origin / travels along its +z axis.
                vector = (m[:3, 3] if kind == "point" else m[:3, 2]).tolist()
            if kind == "directional" and not any(vector):
                raise _Invalid(f"{node.describe()}: zero direction")
            light = {"type": kind, key: [float(c) for c in vector],
                     vector_key: props.color(vector_key, 1.0)}
        props.finish()
        if "id" in node.attrib and kind not in ("constant", "envmap"):
            light["id"] = node.attrib["id"]
        self.checked("light", light, node)
        self.lights.append(light)

    def checked(self, kind: str, record: dict, node: _Node) -> None:
        """Check a converted ``light`` or ``medium`` record's values (:attr:`check`), its
        problems named by its element."""
        if self.check is not None:
            try:
                self.check(kind, record, node.describe())
            except SceneError as err:
                raise _Invalid(str(err), node) from None

    # Camera -------------------------------------------------------------------------------------

    def sensor(self, node: _Node) -> dict | None:
        self.check_object(node)
        kind = node.attrib["type"]
        if kind not in ("perspective", "thinlens", "orthographic"):
            raise _Invalid(f"{node.describe()}: sensor type {kind!r} is not supported (only "
                           "'perspective', 'thinlens' and 'orthographic')")
        props = _Props(self, node)
        width, height, rfilter = DEFAULT_FILM_SIZE[0], DEFAULT_FILM_SIZE[1], "gaussian"
        films, medium, sampler = [], None, None
        for child in props.objects:
            if child.tag in ("ref", "medium") and child.attrib.get("name") == "medium":
                medium = self.guarded(child, lambda child=child: self.medium(child))
                if medium is None:
                    return None
            elif child.tag == "film":
                films.append(child)
            elif child.tag == "sampler":
                sampler = self.guarded(child, lambda child=child: self.sampler(child))
            elif child.tag == "ref":
                # A film or a sampler declared at the top level.
                target = self.guarded(child, lambda child=child: self.lookup(child, "film", "sampler"))
                if target is not None and target.tag == "film":
                    films.append(target)
                elif target is not None:
                    sampler = self.guarded(target, lambda target=target: self.sampler(target))
            else:
                self.report(child, f"{child.describe()} inside {node.describe()} is not supported")
        for extra in films[1:]:
            self.report(extra, f"{node.describe()} has more than one film")
        if films:
            film = self.guarded(films[0], lambda: self.film(films[0]))
            if film is None:
                return None
            width, height, rfilter, crop, sample_border, pixel_format = film
        else:
            crop, sample_border, pixel_format = None, False, "rgb"
        camera = {"type": kind}
        if pixel_format != "rgb":
            camera["pixel_format"] = pixel_format
        if crop is not None:
            camera["crop"] = crop
        if sample_border:
            camera["sample_border"] = True
        if kind != "orthographic":
            fov = props.float("fov", None)
            focal_length = props.string("focal_length", None)
            fov_axis = props.string("fov_axis", None)
            camera["fov"] = horizontal_fov(fov, fov_axis, focal_length, width / height,
                                           node.describe())
        camera["near_clip"] = props.float("near_clip", 1e-2)
        far_clip = props.float("far_clip", 1e4)
        if not 0 < camera["near_clip"] < far_clip:
            raise _Invalid(f"{node.describe()}: near_clip must lie in (0, far_clip), got "
                           f"{camera['near_clip']} and far_clip {far_clip}")
        if kind == "thinlens":
            camera["aperture_radius"] = props.float("aperture_radius", None)
            if camera["aperture_radius"] is None:
                raise _Invalid(f"{node.describe()}: a thinlens sensor needs 'aperture_radius'")
            camera["focus_distance"] = props.float("focus_distance", far_clip)
        else:
            props.ignore("focus_distance")
            props.float("focus_distance", None)
        if kind == "perspective":
            point = [props.float(f"principal_point_offset_{axis}", 0.0) for axis in "xy"]
            if point != [0.0, 0.0]:
                camera["principal_point"] = point
        to_world = props.transform("to_world")
        props.finish()
        to_world = np.eye(4) if to_world is None else to_world
        if kind != "orthographic":
            to_world = _rigid(to_world, f"{node.describe()}: the sensor's to_world")
        if "id" in node.attrib:
            camera["id"] = node.attrib["id"]
        if medium is not None:
            camera["medium"] = medium
        if sampler is not None:
            camera["spp"], camera["sampler"], camera["seed"], jitter = sampler
            if not jitter:
                camera["jitter"] = False
        return {**camera, "to_world": to_world.tolist(), "width": width, "height": height,
                "rfilter": rfilter}

    # Media ---------------------------------------------------------------------------------------

    def medium(self, node: _Node) -> str:
        """Our medium name for a ``<medium>`` or a ``<ref>`` to one (converted once)."""
        if node.tag == "ref":
            _check_attributes(node, {"id"}, {"name"})
            node = self.lookup(node, "medium")
        if id(node) not in self.medium_of_node:
            name = self.unique(self.media, node.attrib.get("id") or f"medium@{node.file.name}:{node.line}")
            self.medium_of_node[id(node)] = None
            spec = self.medium_spec(node)
            self.checked("medium", spec, node)
            self.media[name] = spec
            self.medium_of_node[id(node)] = name
        name = self.medium_of_node[id(node)]
        if name is None:
            raise _Invalid(f"{node.describe()} cannot be converted (reported at its element)", node)
        return name

    def medium_spec(self, node: _Node) -> dict:
        """A ``homogeneous`` medium (a constant extinction) or a ``heterogeneous`` one (a
        gridvolume or constvolume extinction), its albedo a constant or a volume, and its
        phase function."""
        self.check_object(node)
        kind = node.attrib["type"]
        if kind not in ("homogeneous", "heterogeneous"):
            raise _Invalid(f"{node.describe()}: medium type {kind!r} is not supported "
                           "(only 'homogeneous' and 'heterogeneous')")
        props = _Props(self, node)
        phase, volumes = {"type": "isotropic"}, {}
        for child in props.objects:
            if child.tag == "phase":
                self.check_object(child)
                phase_props = _Props(self, child)
                phase = {"type": child.attrib["type"]}
                if phase["type"] == "hg":
                    phase["g"] = phase_props.float("g", 0.8)
                elif phase["type"] != "isotropic":
                    raise _Invalid(f"{child.describe()}: phase function type {phase['type']!r} is "
                                   "not supported (only 'isotropic' and 'hg')", child)
                for extra in phase_props.objects:
                    self.report(extra, f"{extra.describe()} inside {child.describe()} is not supported")
                phase_props.finish()
            elif child.tag == "volume" and (child.attrib.get("name") == "albedo" or (
                    kind == "heterogeneous" and child.attrib.get("name") == "sigma_t")):
                volumes[child.attrib["name"]] = {"type": "volume", "volume": self.volume_spec(child)}
            else:
                self.report(child, f"{child.describe()} inside {node.describe()} is not supported "
                                   "(a homogeneous medium's sigma_t is a constant, a heterogeneous "
                                   "one's a volume; the albedo a constant or a volume)")
        if kind == "heterogeneous" and "sigma_t" not in volumes:
            raise _Invalid(f"{node.describe()}: a heterogeneous medium needs its sigma_t as a "
                           "<volume type=\"gridvolume\" name=\"sigma_t\"> (or a constvolume)", node)
        spec = {"type": kind,
                "sigma_t": volumes["sigma_t"] if "sigma_t" in volumes else props.color("sigma_t", 1.0),
                "albedo": volumes["albedo"] if "albedo" in volumes else props.color("albedo", 0.75),
                "scale": props.float("scale", 1.0),
                "phase": phase, "sample_emitters": props.boolean("sample_emitters", True),
                "has_spectral_extinction": props.boolean("has_spectral_extinction", True)}
        props.finish()
        return spec

    def film(self, node: _Node) -> tuple[int, int, str] | None:
        self.check_object(node)
        if node.attrib["type"] != "hdrfilm":
            raise _Invalid(f"{node.describe()}: film type {node.attrib['type']!r} is not supported "
                           "(only 'hdrfilm')")
        props = _Props(self, node)
        rfilter = "gaussian"  # Mitsuba's default reconstruction filter
        filters = [c for c in props.objects if c.tag == "rfilter"]
        for child in props.objects:
            if child.tag != "rfilter":
                self.report(child, f"{child.describe()} inside {node.describe()} is not supported")
        for extra in filters[1:]:
            self.report(extra, f"{node.describe()} has more than one rfilter")
        if filters:
            rfilter = self.rfilter(filters[0])
        width = props.integer("width", DEFAULT_FILM_SIZE[0])
        height = props.integer("height", DEFAULT_FILM_SIZE[1])
        crop = {key: props.integer(f"crop_{name}", None) for key, name in
                (("x", "offset_x"), ("y", "offset_y"), ("width", "width"), ("height", "height"))}
        sample_border = props.boolean("sample_border", False)
        props.ignore("component_format", "file_format", "banner")
        for fmt in ("component_format", "file_format"):
            props.string(fmt, None)
        pixel_format = self.pixel_format(props)
        # Mitsuba 3 reads a legacy ``banner`` and draws none: a boolean, without effect.
        props.boolean("banner", False)
        props.finish()
        if not (1 <= width <= 1 << 15 and 1 <= height <= 1 << 15):
            raise _Invalid(f"{node.describe()}: width and height must lie in [1, 32768], got "
                           f"{width} x {height}")
        crop = {key: value for key, value in crop.items() if value is not None}
        # Mitsuba's crop window: the offset from the film's corner (default 0), the size (default
        # the film's); the window must lie inside the film.
        x, y = crop.get("x", 0), crop.get("y", 0)
        w, h = crop.get("width", width), crop.get("height", height)
        if not (0 <= x and 0 <= y and 1 <= w and 1 <= h and x + w <= width and y + h <= height):
            raise _Invalid(f"{node.describe()}: the crop window (offset {x}, {y}, size {w} x {h}) "
                           f"must lie inside the {width} x {height} film")
        return (width, height, rfilter, {"x": x, "y": y, "width": w, "height": h} if crop else None,
                sample_border, pixel_format)

    def pixel_format(self, props: _Props) -> str:
        """A film's ``pixel_format`` as a camera's (Mitsuba's names, in any case): ``rgb`` or
        ``rgba``; luminance and XYZ films are warned about and give RGB, with their alpha."""
        value = props.string("pixel_format", "rgb").strip().lower()
        node = props.values.get("pixel_format")
        if value not in MITSUBA_PIXEL_FORMATS:
            raise _Invalid(f"{node.describe()}: pixel_format {value!r} is not one of Mitsuba's "
                           f"{list(MITSUBA_PIXEL_FORMATS)}", node)
        if value in PIXEL_FORMATS:
            return value
        alpha = value.endswith("_alpha") or value == "xyza"
        warnings.warn(f"{node.where}: the film's pixel_format {value!r} gives "
                      f"{'RGBA' if alpha else 'RGB'} here (Mitsuba's would differ in channels)",
                      UserWarning, stacklevel=2)
        return "rgba" if alpha else "rgb"

    def rfilter(self, node: _Node) -> str | dict:
        """The scene file's form of a reconstruction filter: its name, or with a size
        (``stddev``, ``radius``) or a mitchell filter's ``B`` and ``C`` a dict (checked by the
        scene file's parser)."""
        self.check_object(node)
        kind = node.attrib["type"]
        if kind not in RFILTER_SIZES:
            raise _Invalid(f"{node.describe()}: reconstruction filter {kind!r} is not supported "
                           f"(only {', '.join(map(repr, RFILTER_SIZES))})")
        props = _Props(self, node)
        self.report_nested(node, props)
        size = RFILTER_SIZES[kind]
        if kind == "lanczos":  # (an integer in Mitsuba)
            value = float(props.integer(size[0], int(size[1])))
        else:
            value = props.float(size[0], size[1]) if size is not None else None
        if value is not None and not 0 < value * (GAUSSIAN_REACH if kind == "gaussian" else 1) \
                <= MAX_RFILTER_REACH:
            self.report(props.values[size[0]], f"{node.describe()}: {size[0]} {value} is not "
                                                f"supported (positive, reaching at most "
                                                f"{MAX_RFILTER_REACH} pixels)")
        if kind == "mitchell":
            bc = tuple(props.float(key, default) for key, default in zip("BC", CUBIC_FILTERS[kind]))
            props.finish()
            return kind if bc == CUBIC_FILTERS[kind] else {"type": kind, "B": bc[0], "C": bc[1]}
        props.finish()
        return kind if value is None or value == size[1] else {"type": kind, size[0]: value}

    def sampler(self, node: _Node) -> tuple[int, str, int, bool]:
        """A sampler's ``sample_count`` as Mitsuba's sampler of its type rounds it
        (:func:`mitsuba_sample_count`; the spp of renders that name none), its type (the
        camera's ``sampler``: independent, or stratified over a pixel's samples), its
        ``seed`` (the camera's, added to each render's) and its ``jitter`` (the camera's;
        taken by the samplers that take it in Mitsuba, reported on the others, as Mitsuba's
        unused parameters)."""
        self.check_object(node)
        if node.attrib["type"] not in SAMPLERS:
            raise _Invalid(f"{node.describe()}: unknown sampler type {node.attrib['type']!r}")
        props = _Props(self, node)
        self.report_nested(node, props)
        count = props.integer("sample_count", 4)
        seed = props.integer("seed", 0)
        jitter = props.boolean("jitter", True) if node.attrib["type"] in JITTERED_SAMPLERS else True
        props.finish()
        if count < 1:
            raise _Invalid(f"{node.describe()}: sample_count must be positive, got {count}")
        if not 0 <= seed < 2 ** 32:
            raise _Invalid(f"{node.describe()}: seed must be an integer in [0, 2^32), got {seed}")
        return mitsuba_sample_count(node.attrib["type"], count), node.attrib["type"], seed, jitter

    def integrator(self, node: _Node) -> None:
        """The file's integrator as ``{"type": ..., parameter: value}``: renders that name
        none use it where one of ours renders it as asked
        (:func:`instancing.io.scene_file.parse_integrator`); the integrators nested in it
        (Mitsuba's ``aov`` and ``moment`` around others) under ``"integrators"``, each with
        the name Mitsuba gives it as ``"id"``; other nested objects are named under ``"nested"``."""
        self.check_object(node)
        if self.integrator_spec is not None:
            self.report(node, f"a second {node.describe()} (a scene has one integrator)")
            return
        self.integrator_spec = self.integrator_values(node)

    def integrator_values(self, node: _Node) -> dict:
        """One ``<integrator>`` element's type, parameters and nested integrators."""
        props = _Props(self, node)
        readers = {"integer": lambda name: props.integer(name, 0),
                   "float": lambda name: props.float(name, 0.0),
                   "boolean": lambda name: props.boolean(name, False),
                   "string": lambda name: props.string(name, "")}
        spec: dict = {"type": node.attrib["type"]}
        for name, child in props.values.items():
            if child.tag in readers:
                spec[name] = readers[child.tag](name)
            else:
                props.ignore(name)
                spec[name] = child.describe()
        nested = [child for child in props.objects if child.tag == "integrator"]
        if nested:
            # Labelled as Mitsuba names nested objects: by their name, else _arg_0, _arg_1, ...
            # in the order of the unnamed ones.
            unnamed = iter(range(len(nested)))
            spec["integrators"] = [
                {**self.integrator_values(child),
                 "id": child.attrib.get("name") or f"_arg_{next(unnamed)}"}
                for child in nested]
        others = [child for child in props.objects if child.tag != "integrator"]
        if others:
            spec["nested"] = ", ".join(child.describe() for child in others)
        return spec


#: Parameters whose spectra are not reflectances: a conductor's complex index of
#: refraction (Mitsuba's RGB variant converts them without clamping to [0, 1]).
UNBOUNDED_SPECTRA = ("eta", "k", "sigma_t")
#: Per kind of spectrum: a plugin that reads it as Mitsuba reads such a parameter, and the
#: traverse key of its value.
_SPECTRUM_READERS = {
    "illuminant": ('<emitter version="3.0.0" type="point"><spectrum name="intensity" value="{}"/>'
                   '</emitter>', "intensity.value"),
    "reflectance": ('<bsdf version="3.0.0" type="diffuse"><spectrum name="reflectance" '
                    'value="{}"/></bsdf>', "reflectance.value"),
    "unbounded": ('<bsdf version="3.0.0" type="conductor"><spectrum name="eta" value="{}"/>'
                  '</bsdf>', "eta.value"),
    "volume": ('<volume version="3.0.0" type="constvolume"><spectrum name="value" value="{}"/>'
               '</volume>', "value.value"),
}


@functools.lru_cache(maxsize=256)
def spectrum_rgb(value: str, kind: str, what: str = "<spectrum>") -> list[float]:
    """The RGB colour Mitsuba's RGB variant makes of a ``<spectrum value=...>``: a constant,
    or ``wavelength:value`` pairs, converted by Mitsuba itself as the ``kind`` of quantity
    it is: ``"illuminant"`` (e.g. a constant 1 becomes (1.20, 0.95, 0.91)),
    ``"reflectance"`` (clamped to the gamut), ``"unbounded"`` (a conductor's eta, k) or
    ``"volume"`` (a constvolume's value: the reflectance's conversion, unclamped)."""
    mi = mitsuba_module()
    plugin, key = _SPECTRUM_READERS[kind]
    try:
        params = mi.traverse(mi.load_string(plugin.format(value.replace('"', ""))))
    except Exception as err:  # Mitsuba's parser raises RuntimeError with its own message
        raise _Invalid(f"{what}: Mitsuba cannot read the spectrum {value!r} "
                       f"({str(err).splitlines()[-1]})") from None
    rgb = np.ravel(np.asarray(params[key], np.float64))
    return [float(c) for c in (np.repeat(rgb, 3) if rgb.size == 1 else rgb)]


def mitsuba_sample_count(kind: str, count: int) -> int:
    """The samples per pixel that Mitsuba's sampler ``kind`` takes for ``sample_count``:
    ``stratified`` a square, ``ldsampler`` the square of a power of two (at least 4),
    ``orthogonal`` the square of a prime, ``multijitter`` a near-square grid; the
    ``independent`` sampler the count itself."""
    if kind == "stratified":
        return (math.isqrt(count - 1) + 1) ** 2
    if kind == "ldsampler":
        side = 2
        while side * side < count:
            side = 1 << side.bit_length()  # (the next power of two above it)
        return side * side
    if kind == "orthogonal":
        side = 2
        while side * side < count or any(side % k == 0 for k in range(2, side // 2 + 1)):
            side += 1
        return side * side
    if kind == "multijitter":
        rows = math.isqrt(count)
        return rows * -(-count // rows)
    return count


def _unread_file(filename: str, raw: bool, volume: bool = False) -> tuple[Any, str]:
    """A texture file's stand-in while a material is validated (the scene reads the file):
    one texel or cell of 0."""
    if volume:
        return (np.zeros((1, 1, 1, 1), np.float32), (np.zeros(3), np.ones(3))), filename
    return np.zeros((1, 1, 3), np.float32), filename


def horizontal_fov(fov: float | None, fov_axis: str | None, focal_length: str | None,
                   aspect: float, what: str = "sensor") -> float:
    """Mitsuba's ``parse_fov``: the horizontal field of view in degrees.

    Args:
        fov: the ``fov`` parameter (degrees) or None.
        fov_axis: 'x', 'y', 'diagonal', 'smaller' or 'larger' (default 'x'), only with ``fov``.
        focal_length: 35 mm equivalent focal length such as '50mm' (Mitsuba's default when
            neither is given); the field of view then spans the film diagonal.
        aspect: film width / height.
    """
    fov, fov_axis = field_of_view(fov, fov_axis, focal_length, what)
    try:
        return fov_along_x(fov, fov_axis, aspect)
    except ValueError as err:
        raise _Invalid(f"{what}: {err}") from None


def field_of_view(fov: float | None, fov_axis: str | None, focal_length: str | None,
                  what: str) -> tuple[float, str]:
    """A sensor's or projector's ``fov`` and ``fov_axis``, or its ``focal_length`` (35 mm
    equivalent, Mitsuba's default 50mm when neither is given) as the field of view along the
    film diagonal."""
    if fov is not None and focal_length is not None:
        raise _Invalid(f"{what}: give either 'fov' or 'focal_length', not both")
    if fov is not None:
        return fov, fov_axis or "x"
    if fov_axis is not None:
        raise _Invalid(f"{what}: 'fov_axis' needs 'fov'")
    text = focal_length or "50mm"
    text = text[:-2] if text.endswith("mm") else text
    value = _number(text, f"{what}: focal_length")
    if value <= 0:
        raise _Invalid(f"{what}: focal_length must be positive, got {focal_length!r}")
    return diagonal_fov(value), "diagonal"


def xml_to_scene_dict(path: str | os.PathLike, parameters: dict[str, Any] | None = None,
                      check: Callable[[str, dict, str], Any] | None = None) -> tuple[dict, Path]:
    """Read a Mitsuba 3 XML scene as our scene dict (see the module docstring for what is supported).

    Args:
        path: the ``.xml`` scene file.
        parameters: values for ``$name`` parameters, overriding the file's ``<default>`` s
            (as ``mitsuba.load_file(path, name=value)``).
        check: validates one ``"light"`` or ``"medium"`` record (the first argument; its
            problems named by the third), raising :class:`SceneError`: each ``<emitter>``'s
            and ``<medium>``'s problem is then reported with its file and line among the
            others.

    Returns:
        (scene dict for :func:`~instancing.io.scene_file.parse_scene`, the scene file's folder).
        Mesh file names in the dict are absolute.

    Raises:
        SceneError: the file is missing or malformed XML (file and line), contains entity
            declarations, an include is missing or cyclic, a ``$name`` is undefined; or, in one
            error listing all of them with file and line, every element or parameter that is
            unsupported or invalid.
    """
    path = Path(path)
    if not path.is_file():
        raise SceneError(f"scene file not found: {path}")
    root = _read_xml(path)
    if root.tag != "scene":
        raise SceneError(f"{root.where}: the root element must be <scene>, got <{root.tag}>")
    _version(root)
    expander = _Expander(path.parent, {str(k): str(v) for k, v in (parameters or {}).items()})
    top = _Node("scene", {k: v for k, v in root.attrib.items() if k != "version"}, root.file,
                root.line, text=root.text)
    stack = (path.resolve(),)
    for child in root.children:
        top.children.extend(expander.expand(child, stack, at_root=True))
    unused = sorted(set(map(str, parameters or {})) - expander.used)
    if unused:
        raise SceneError(f"{path}: parameters {unused} are not used by the file (no $name and no "
                         "<default name=...> names them; Mitsuba refuses unused parameters too)")
    return _Importer(path, expander.search, check).run(top), path.parent
