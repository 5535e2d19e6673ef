"""The scene's materials as one flat table, and the BSDF operations on it.

Every material is a row: its kernel (BSDF type and the variant its discrete parameters
choose, e.g. the GGX distribution), the row its back side shows (Mitsuba's ``twosided``;
none for one-sided BSDFs) and its parameters, one array per parameter name over all rows
(a colour an Array3f, a number a Float). A lane gathers its material's row, so that any
number of materials of one type cost the same as one: no per-material code is traced, and
only the kernels the scene uses are. (Mitsuba's plugins, dispatched per material through
``BSDFPtr``, were measured: 1 048 576 roughplastic evaluations over 1 / 10 / 100 / 1 000
materials took 4 / 6 / 15 / 66 ms of kernel time plus 0 / 1 / 6 / 63 ms of tracing each call.)

A parameter given by a texture (:mod:`instancing.materials.texture`) stores, per row, the
texture's index in the scene's :class:`~instancing.materials.texture.TextureSet` next to
its constant column; lanes of such rows look their value up at the hit's ``uv`` (a number
parameter reads a colour texture's luminance). Only the parameters that some material
textures trace a lookup.

Directions are in the shading frame (+z the shading normal), ``wi`` towards the viewer and
``wo`` towards the light, as in Mitsuba; ``evaluate`` returns ``f cos(theta_o)``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..core.backend import (Array2f, Array3f, Bool, Float, UInt32, device_array, device_arrays,
                            device_vectors, dr)
from .material import LOBES, Material
from .parameter import COLOR, NUMBER
from .texture import Texture, TextureSet, luminance

#: Back row of a one-sided material: black seen from behind.
NO_BACK = 0xFFFFFFFF
#: Texture index of a parameter that a row gives as a constant.
NO_TEXTURE = 0xFFFFFFFF


@dataclass(frozen=True)
class BSDFSample:
    """A sampled direction: ``wo`` (shading frame), ``weight`` = f cos / pdf, its density
    ``pdf`` (solid angle; 1 for delta lobes), whether the lobe was a delta lobe, and
    whether the sample is valid (else weight 0)."""

    wo: Array3f
    weight: Array3f
    pdf: Float
    delta: Bool
    valid: Bool


class BSDFTable:
    """The materials of a scene (in its order) as device arrays; see the module docstring."""

    def __init__(self, materials: list[Material]):
        rows = list(materials)
        back = []
        for material in materials:
            if material.back is None:
                back.append(NO_BACK)
            elif material.back is material:
                back.append(len(back))
            else:
                back.append(len(rows))
                rows.append(material.back)
        back += [NO_BACK] * (len(rows) - len(back))
        self.rows = rows
        self.material_count = len(materials)
        keys = [(row.type, row.lobe.variant(row.values)) for row in rows]
        self.kernels = list(dict.fromkeys(keys))
        self.kernel_of_row = device_array(UInt32, np.array([self.kernels.index(k) for k in keys],
                                                           np.uint32))
        self.back_of_row = device_array(UInt32, np.array(back, np.uint32))
        self.two_sided = any(b != NO_BACK for b in back)
        # Rows whose BSDF scatters on both sides itself (dielectrics: no frame flip).
        both = [getattr(row.lobe, "both_sides", False) for row in rows]
        self.both_sides = any(both)
        self.both_sides_of_row = device_array(UInt32, np.array(both, np.uint32)) if self.both_sides else None
        #: Whether some material reflects by a delta lobe only (a mirror).
        self.has_mirror = any(row.lobe.delta_only for row in rows)
        #: Whether some kernel chooses between lobes (a third random number per sample).
        self.chooses_lobe = any(getattr(row.lobe, "chooses_lobe", False) for row in rows)
        # One array per numeric parameter name, over all rows (0 where a row lacks it); the
        # values a type derives from its parameters (an IOR ratio, a tabulated function:
        # one flat array of a row's samples after another's) likewise.
        columns: dict[str, list] = {}
        derived: dict[int, dict] = {}
        textures: list[Texture] = []
        texture_of: dict[str, list[int]] = {}
        for lobe in {row.lobe for row in rows if hasattr(row.lobe, "derived")}:
            mine = [r for r, row in enumerate(rows) if row.lobe is lobe]
            derived.update(zip(mine, lobe.derived([rows[r].values for r in mine])))
        for r, row in enumerate(rows):
            values = {key: row.values[key] for key, parameter in row.lobe.parameters.items()
                      if parameter.kind in (COLOR, NUMBER)}
            for key, value in values.items():
                if isinstance(value, Texture):
                    # The texture's index beside a constant 0 of the parameter's kind.
                    texture_of.setdefault(key, [NO_TEXTURE] * len(rows))[r] = len(textures)
                    textures.append(value)
                    kind = row.lobe.parameters[key].kind
                    values[key] = (0.0,) * 3 if kind == COLOR else 0.0
            values.update(derived.get(r, {}))
            for key, value in values.items():
                columns.setdefault(key, [None] * len(rows))[r] = value
        # Every table has the diffuse reflectance (the scene's differentiable colours).
        columns.setdefault("reflectance", [(0.0,) * 3] * len(rows))
        self.values: dict[str, Float | Array3f] = {}
        #: Columns that hold several samples per row (read by the kernels with the row).
        self.tables: set[str] = set()
        for key, column in columns.items():
            sample = next(v for v in column if v is not None)
            zero = np.zeros_like(np.asarray(sample, np.float64))
            stacked = np.array([zero if v is None else np.asarray(v, np.float64) for v in column],
                               np.float32)
            if isinstance(sample, tuple):  # a colour
                self.values[key] = device_vectors(stacked)
                continue
            if isinstance(sample, np.ndarray):  # a tabulated function
                self.tables.add(key)
            self.values[key] = device_arrays(Float, stacked.ravel())[0]
        #: The scene's textures, and per textured parameter each row's texture (or NO_TEXTURE).
        self.textures = TextureSet(textures) if textures else None
        self.texture_of = {key: device_array(UInt32, np.array(index, np.uint32))
                           for key, index in texture_of.items()}

    @property
    def reflectance(self) -> Array3f:
        """The diffuse reflectance of the materials (their rows; 0 for other types)."""
        stored = self.values["reflectance"]
        if len(self.rows) == self.material_count:
            return stored
        return dr.gather(Array3f, stored, dr.arange(UInt32, self.material_count))

    def albedo(self, material: UInt32, uv: Array2f | None = None) -> Array3f:
        """Each lane's material's albedo (Mitsuba's AOV): the lobe's own colour parameter
        (0 for dielectrics)."""
        value = Array3f(0.0)
        for lobe, variant, mine, p in self._each_kernel(material, uv):
            if lobe.albedo is not None:
                value = dr.select(mine, p[lobe.albedo], value)
        return value

    def roughness(self, material: UInt32, uv: Array2f | None = None) -> Float:
        """Each lane's material's microfacet roughness ``alpha`` (textured ones looked up at
        ``uv``; 0 for smooth and diffuse materials)."""
        value = Float(0.0)
        for lobe, variant, mine, p in self._each_kernel(material, uv):
            if "alpha" in lobe.parameters:
                value = dr.select(mine, p["alpha"], value)
        return value

    def reflects(self, material: UInt32, wi: Array3f) -> Bool:
        """Whether the side of each lane's material that wi (shading frame) looks at
        scatters light: the front, the back of a two-sided material, either side of a
        dielectric."""
        return self._side(material, wi)[2]

    def mirror(self, material: UInt32) -> Bool:
        """Whether each lane's material reflects by a delta lobe only (a mirror: no density
        of directions to evaluate)."""
        if not self.has_mirror:
            return Bool(False)
        kernel = dr.gather(UInt32, self.kernel_of_row, material)
        result = Bool(False)
        for k, (name, variant) in enumerate(self.kernels):
            if LOBES[name].delta_only:
                result |= kernel == k
        return result

    def set_value(self, key: str, front: Float | Array3f) -> None:
        """Replace parameter ``key`` of the materials (one lane per material, in order),
        e.g. by grad-enabled values; the back rows of two-sided materials keep theirs."""
        stored = self.values[key]
        if len(self.rows) == self.material_count:
            self.values[key] = front
            return
        rows = dr.arange(UInt32, len(self.rows))
        first = dr.gather(type(front), front, dr.minimum(rows, self.material_count - 1))
        self.values[key] = dr.select(rows < self.material_count, first, dr.detach(stored))

    # -- kernels ------------------------------------------------------------------------------

    def _side(self, material: UInt32, wi: Array3f) -> tuple[UInt32, Bool, Bool]:
        """(row, flipped, lit): the row of the side wi looks at (a two-sided material's back
        row where wi is below the surface, its frame flipped), whether the frame is
        flipped, and whether that side scatters (a dielectric sees wi below the surface
        itself: no flip)."""
        both = Bool(False)
        if self.both_sides:
            both = dr.gather(UInt32, self.both_sides_of_row, material) != 0
        if not self.two_sided:
            return material, Bool(False), (wi.z > 0) | both
        below = (wi.z < 0) & ~both
        back = dr.gather(UInt32, self.back_of_row, material)
        return dr.select(below, back, material), below, ~below | (back != NO_BACK)

    def _parameters(self, lobe, row: UInt32, uv: Array2f | None) -> dict:
        """The lanes' values of what ``lobe`` reads: its parameters and derived values
        gathered by row, textured ones looked up at ``uv``; tabulated ones whole (with
        ``row`` to index them)."""
        keys = [*lobe.parameters, *getattr(lobe, "derived_keys", ())]
        p = {key: (self.values[key] if key in self.tables
                   else dr.gather(type(self.values[key]), self.values[key], row))
             for key in keys if key in self.values}
        for key in self.texture_of.keys() & lobe.parameters.keys():
            if uv is None:
                raise ValueError("a textured material is looked up without surface coordinates")
            texture = dr.gather(UInt32, self.texture_of[key], row)
            textured = texture != NO_TEXTURE
            number = lobe.parameters[key].kind == NUMBER
            value = self.textures.eval(texture, uv, textured, number)
            if number:
                value = luminance(value)
            p[key] = dr.select(textured, value, p[key])
        p["row"] = row
        return p

    def _each_kernel(self, row: UInt32, uv: Array2f | None):
        """(lobe, variant, lanes of that kernel, its parameters) per kernel present."""
        single = len(self.kernels) == 1
        kernel = None if single else dr.gather(UInt32, self.kernel_of_row, row)
        for k, (name, variant) in enumerate(self.kernels):
            lobe = next(r.lobe for r in self.rows if r.type == name)
            yield (lobe, variant, Bool(True) if single else kernel == k,
                   self._parameters(lobe, row, uv))

    def evaluate(self, material: UInt32, wi: Array3f, wo: Array3f,
                 uv: Array2f | None = None) -> Array3f:
        """f cos(theta_o) of each lane's material for directions wi, wo (shading frame), at
        surface coordinates ``uv`` (needed where a material is textured)."""
        return self._per_kernel("eval", Array3f, material, wi, wo, uv)

    def pdf(self, material: UInt32, wi: Array3f, wo: Array3f, uv: Array2f | None = None) -> Float:
        """The solid-angle density with which :meth:`sample` picks wo (0 for delta lobes)."""
        return self._per_kernel("pdf", Float, material, wi, wo, uv)

    def _per_kernel(self, method: str, result: type, material: UInt32, wi: Array3f, wo: Array3f,
                    uv: Array2f | None):
        """Each lane's kernel's ``method`` (eval or pdf) on the side wi sees, 0 where that
        side does not reflect."""
        row, flip, lit = self._side(material, wi)
        wi, wo = _flipped(wi, flip), _flipped(wo, flip)
        value = result(0.0)
        for lobe, variant, mine, p in self._each_kernel(row, uv):
            value = dr.select(mine, getattr(lobe, method)(p, wi, wo, variant), value)
        return dr.select(lit, value, 0.0)

    def sample(self, material: UInt32, wi: Array3f, sampler, uv: Array2f | None = None) -> BSDFSample:
        """A direction wo drawn from each lane's material (two random numbers, three where
        some material chooses between lobes)."""
        u0 = sampler.next_float32() if self.chooses_lobe else Float(0.0)
        u = (u0, sampler.next_float32(), sampler.next_float32())
        row, flip, lit = self._side(material, wi)
        wi = _flipped(wi, flip)
        wo, weight, pdf, delta, valid = Array3f(0.0), Array3f(0.0), Float(0.0), Bool(False), Bool(False)
        for lobe, variant, mine, p in self._each_kernel(row, uv):
            wo_k, weight_k, pdf_k, valid_k, delta_k = lobe.sample(p, wi, u, variant)
            wo = dr.select(mine, wo_k, wo)
            weight = dr.select(mine, weight_k, weight)
            pdf = dr.select(mine, pdf_k, pdf)
            valid = dr.select(mine, valid_k, valid)
            delta = dr.select(mine, delta_k, delta)
        valid &= lit
        return BSDFSample(_flipped(wo, flip), dr.select(valid, weight, 0.0), pdf, delta, valid)


def _flipped(w: Array3f, flip: Bool) -> Array3f:
    """w mirrored through the tangent plane where ``flip``."""
    return Array3f(w.x, w.y, dr.select(flip, -w.z, w.z))
