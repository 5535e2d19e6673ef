"""The typed description of a scene: what a scene file says, parsed and validated once.

:func:`instancing.io.scene_file.parse_scene` (and the Mitsuba XML importer through it)
turns a file or dict into these records; the scene builder
(:class:`~instancing.scene.scene.Scene`) and everything downstream read only them,
never a raw dict.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Union

import numpy as np

from ..materials.material import Material
from ..materials.texture import Texture
from ..models.linear_curve import ControlPointCurves
from ..models.mesh import MeshData
from ..models.sdf_grid import SDFGridData
from .camera import Camera
from .instance_ids import InstanceIds
from .medium import Medium

Vector3 = tuple[float, float, float]


@dataclass(frozen=True)
class PointLight:
    """Mitsuba's ``point``: ``position``, ``intensity`` (W/sr per channel); ``id`` names its
    parameters in :func:`instancing.traverse` (``"<id>.position"``)."""

    position: Vector3
    intensity: Vector3
    id: str = ""


@dataclass(frozen=True)
class SpotLight(PointLight):
    """Mitsuba's ``spot``: a point light at ``position`` shining along +z of its frame
    (``light_from_world``: the inverse of its ``to_world``'s linear part, row-major), at
    full ``intensity`` within ``beam_width`` degrees of the axis, falling off linearly in
    angle to 0 at ``cutoff_angle`` degrees, times its ``texture`` (None: 1) projected onto the
    cone (u, v = 0.5 + 0.5 x / (z tan(cutoff_angle)), likewise for y, in the light's frame).
    For shadows it is a point light."""

    light_from_world: tuple[float, ...] = (1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0)
    cutoff_angle: float = 20.0
    beam_width: float = 15.0
    texture: Texture | None = None


@dataclass(frozen=True)
class ProjectorLight(PointLight):
    """Mitsuba's ``projector``: a pinhole at ``position`` projecting its ``texture`` (None:
    a constant) along +z of its frame (``light_from_world`` as a spot's) onto the scene,
    through a film of ``aspect`` (width / height: the texture's, 1 for a constant or
    checkerboard) with the horizontal field of view ``fov`` degrees. Irradiance on the
    plane z = 1 in front of it is ``pi intensity texture(u, v)`` (``intensity``: Mitsuba's
    ``scale`` times a constant irradiance); as a point light, its intensity towards a
    direction at angle theta to the axis is ``pi intensity texture(u, v) / cos^3 theta``
    within the film's frustum, 0 outside. For shadows it is a point light."""

    light_from_world: tuple[float, ...] = (1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0)
    fov: float = 40.0
    aspect: float = 1.0
    texture: Texture | None = None


@dataclass(frozen=True)
class DirectionalLight:
    """Mitsuba's ``directional``: the unit ``direction`` the light travels, ``irradiance``
    (W/m^2); ``id`` names its parameters in :func:`instancing.traverse`."""

    direction: Vector3
    irradiance: Vector3
    id: str = ""


@dataclass(frozen=True)
class ConstantLight:
    """Mitsuba's ``constant``: ``radiance`` arriving from every direction (an environment);
    ``id`` names it (its parameters' keys)."""

    radiance: Vector3
    id: str = ""


@dataclass(frozen=True)
class AreaEmitter:
    """An instance's ``area`` emitter: ``radiance`` leaving the front side, or where it has a
    ``texture`` (a bitmap or checkerboard), the texture's value at the surface coordinates
    (``radiance`` then 1)."""

    radiance: Vector3
    texture: Texture | None = None


@dataclass(frozen=True, eq=False)
class EnvironmentMap:
    """Mitsuba's ``envmap``: a latitude-longitude image of the radiance arriving from each
    direction (``texels`` (H, W, 3) linear RGB, row 0 at the +y pole of its frame), turned
    by ``to_world`` (4x4, a rotation), times ``scale``; ``filename`` the resolved file (empty
    once the texels changed: see :mod:`instancing.scene.environment`); ``id`` names it (its
    parameters' keys)."""

    filename: str
    texels: np.ndarray
    to_world: np.ndarray
    scale: float = 1.0
    id: str = ""


#: The lights that surround the scene (at most one per scene, as in Mitsuba).
ENVIRONMENTS = (ConstantLight, EnvironmentMap)

Light = Union[PointLight, DirectionalLight, ConstantLight, EnvironmentMap]


@dataclass(frozen=True)
class IntegratorChoice:
    """The integrator a scene file names (Mitsuba's ``<integrator>``, the JSON
    ``"integrator"``), which renders that name none use: ``given`` its type as written,
    ``name`` ours that renders the image it asks for ('direct', 'path' or 'volpath'; None
    where none does, ``refusal`` then says why), ``max_depth``, ``rr_depth``,
    ``hide_emitters``, and ``direct``'s ``emitter_samples`` and ``bsdf_samples`` (None: the
    defaults). Mitsuba's ``aov`` (``name`` 'aov') renders the RGB of each of its ``nested``
    integrators, then its ``aovs``: (label, Mitsuba's AOV type) pairs, and (label,
    integrator) pairs."""

    given: str
    name: str | None = None
    max_depth: int | None = None
    rr_depth: int | None = None
    hide_emitters: bool | None = None
    refusal: str = ""
    emitter_samples: int | None = None
    bsdf_samples: int | None = None
    aovs: tuple[tuple[str, str], ...] = ()
    nested: tuple[tuple[str, "IntegratorChoice"], ...] = ()


@dataclass
class ModelSpec:
    """One base model: an analytic type, a mesh with its data, an SDF grid (type
    ``sdfgrid``) with its values, or curves (type ``linearcurve`` or ``bsplinecurve``) with their
    control points (``points_to_world``: the transform that moved them, Mitsuba's plain curve's
    ``to_world``). ``flipped``: the model turned inside out (``flip_normals``): a mesh's
    winding reversed and its normals negated as read, an analytic model's normals negated
    where it is hit or sampled (its instances' :attr:`InstanceTable.inward`)."""

    name: str
    type: str
    mesh: MeshData | None = None
    filename: Path | None = None
    grid: SDFGridData | None = None
    curve: ControlPointCurves | None = None
    points_to_world: np.ndarray | None = None
    flipped: bool = False

    @property
    def kind(self) -> str:
        return "mesh" if self.mesh is not None else self.type

    @property
    def inward(self) -> bool:
        """Whether its instances' normals are negated where hit or sampled: an analytic model
        turned inside out (a mesh's winding is reversed as it is read instead)."""
        return self.flipped and self.mesh is None and self.grid is None and self.curve is None


@dataclass(frozen=True)
class InstanceMatrices:
    """The user's float64 matrices as parsed, until the scene builder has rounded them.

    Attributes:
        to_world: (N, 4, 4) float64 world_from_object matrices.
        from_world: (N, 4, 4) float64 object_from_world matrices, inverted in float64.
    """

    to_world: np.ndarray
    from_world: np.ndarray


@dataclass
class SceneDescription:
    """A validated scene: models, materials and compact per-instance data.

    Attributes:
        instance_ids: the instances' ids (:class:`~instancing.scene.instance_ids.InstanceIds`).
        instance_model: (N,) unsigned index into ``models`` per instance, in the
            smallest integer type; a read-only broadcast of one value when every
            instance uses the same model.
        instance_material_index: (N,) index into ``list(materials)``, stored the same way.
        transforms: the parsed :class:`InstanceMatrices`; the scene builder rounds them
            into its instance table and keeps a description without them (None).
        emitters: area emitters by user instance index.
        cameras: the cameras, in the file's order (none: the scene is not rendered).
        lights: point, directional and constant lights, in the file's order.
        media: the participating media by name (:mod:`instancing.scene.medium`).
        instance_media: (interior, exterior) medium names ("": none) by user instance
            index, for the instances that name one.
        integrator: the integrator the file names (None: none).
    """

    models: list[ModelSpec]
    materials: dict[str, Material]
    instance_ids: InstanceIds
    instance_model: np.ndarray
    instance_material_index: np.ndarray
    transforms: InstanceMatrices | None
    emitters: dict[int, AreaEmitter] = field(default_factory=dict)
    cameras: tuple[Camera, ...] = ()
    lights: tuple[Light, ...] = ()
    base_dir: Path = Path(".")
    media: dict[str, Medium] = field(default_factory=dict)
    instance_media: dict[int, tuple[str, str]] = field(default_factory=dict)
    integrator: IntegratorChoice | None = None

    @property
    def camera(self) -> Camera | None:
        """The first camera, or None."""
        return self.cameras[0] if self.cameras else None

    @property
    def to_world(self) -> np.ndarray:
        """(N, 4, 4) float64 world_from_object matrices as parsed (a built scene's are
        :attr:`Scene.to_world <instancing.scene.scene.Scene.to_world>`)."""
        return self._matrices().to_world

    @property
    def from_world(self) -> np.ndarray:
        """(N, 4, 4) float64 object_from_world matrices as parsed, inverted in float64."""
        return self._matrices().from_world

    def _matrices(self) -> InstanceMatrices:
        if self.transforms is None:
            raise AttributeError("a built scene's description holds no matrices; "
                                 "read Scene.to_world and Scene.from_world")
        return self.transforms

    @property
    def instance_material(self) -> list[str]:
        """Material name of each instance (a list made on demand)."""
        names = list(self.materials)
        return [names[k] for k in self.instance_material_index]
