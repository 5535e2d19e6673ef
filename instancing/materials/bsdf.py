"""The scene's materials as one flat table, and the BSDF operations on it.

Every material is a row: its kernel (BSDF type and the variant its discrete parameters
choose, e.g. the GGX distribution), the row its back side shows (Mitsuba's ``twosided``;
none for one-sided BSDFs) and its parameters, one array per parameter name over all rows
(a colour an Array3f, a number a Float). A lane gathers its material's row, so that any
number of materials of one type cost the same as one: no per-material code is traced, and
only the kernels the scene uses are; where nothing carries derivatives, each runs in a branch
that a SIMD packet skips when none of its lanes uses it. (Mitsuba's plugins, dispatched per material through
``BSDFPtr``, were measured: 1 048 576 roughplastic evaluations over 1 / 10 / 100 / 1 000
materials took 4 / 6 / 15 / 66 ms of kernel time plus 0 / 1 / 6 / 63 ms of tracing each call.)

A parameter given by a texture (:mod:`instancing.materials.texture`) stores, per row, the
texture's index in the scene's :class:`~instancing.materials.texture.TextureSet` next to
its constant column; lanes of such rows look their value up at the hit's ``uv`` (a number
parameter reads a colour texture's luminance), or, where a material reads mesh attributes
or volumes, at the hit's :class:`~instancing.materials.texture.LookupPoint` (the ``uv``
arguments below). Only the parameters that some material textures trace a lookup.

Directions are in the shading frame (+z the shading normal), ``wi`` towards the viewer and
``wo`` towards the light, as in Mitsuba; ``evaluate`` returns ``f cos(theta_o)``.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Callable

import numpy as np

from ..core.backend import (Array3f, Bool, Float, UInt32, device_array, device_arrays,
                            device_vectors, dr)
from .bump_map import BUMP_MAP, BumpMap, SurfaceFrame, bumped_frame
from .delta_lobe import chosen
from .material import LOBES, Material
from .normal_map import NORMAL_MAP, NormalMap, into, out_of, shadowing, tilted_frame
from .parameter import COLOR, NUMBER
from .texture import Coordinates, Texture, TextureSet, luminance

#: Back row of a one-sided material: black seen from behind.
NO_BACK = 0xFFFFFFFF
#: Texture index of a parameter that a row gives as a constant.
NO_TEXTURE = 0xFFFFFFFF
#: Kernel of a blend row (its lanes are routed to its parts' rows).
NO_KERNEL = 0xFFFFFFFF
#: The names a map around a whole material files its texture under.
OUTER = {NORMAL_MAP: "outer_normalmap", BUMP_MAP: "outer_bumpmap"}


@dataclass(frozen=True)
class BSDFSample:
    """A sampled direction: ``wo`` (shading frame), ``weight`` = f cos / pdf, its density
    ``pdf`` (solid angle; 1 for delta lobes), whether the lobe was a delta lobe, whether
    the sample is valid (else weight 0), the random numbers ``u`` it was drawn from, and
    whether it passed straight through by a pass-through lobe (``null``, a polarizer, a
    mask's transparent part, a thin dielectric's transmission: Mitsuba's ``Null`` lobes), and
    the relative index of refraction it crossed (Mitsuba's ``eta``: the interface's, or its
    inverse from inside, where the sample refracted; 1 otherwise)."""

    wo: Array3f
    weight: Array3f
    pdf: Float
    delta: Bool
    valid: Bool
    u: tuple[Float, Float, Float]
    null: Bool
    eta: Float


class BSDFTable:
    """The materials of a scene (in its order) as device arrays; see the module docstring.

    ``attributes`` gives the scene's meshes' attribute values where a material reads one,
    ``origin`` the rendering space's (see :class:`~instancing.materials.texture.TextureSet`)."""

    def __init__(self, materials: list[Material], attributes: Callable[[str], np.ndarray] | None = None,
                 origin: np.ndarray | None = None):
        # The materials are the first rows; each row's back side (of a twosided with two
        # BSDFs) and parts (of a blend or mask) follow as rows of their own, theirs in turn.
        rows = list(materials)
        back, parts = [], []
        for material in rows:  # (rows grows as it is walked)
            if material.back is None:
                back.append(NO_BACK)
            elif material.back is material:
                back.append(len(back))
            else:
                back.append(len(rows))
                rows.append(material.back)
            if material.parts is None:
                parts.append((NO_BACK, NO_BACK))
            else:
                parts.append((len(rows), len(rows) + 1))
                rows.extend(material.parts)
        self.rows = rows
        #: Per row, the rows of its two parts (NO_BACK, NO_BACK where it is no mix).
        self.part_rows = parts
        self.material_count = len(materials)
        #: Whether some material is a blend or mask (its lanes evaluate its two parts and mix
        #: them, each part on its own sides).
        self.blends = any(p[0] != NO_BACK for p in parts)
        if self.blends:
            self.parts_of_row = [device_array(UInt32, np.array(column, np.uint32))
                                 for column in zip(*parts)]
            # The mixing kinds present (blendbsdf, mask); per row which one, where both are.
            self.mixes = list(dict.fromkeys(row.lobe for row in rows if row.parts is not None))
            if len(self.mixes) > 1:
                self.mix_of_row = device_array(UInt32, np.array(
                    [self.mixes.index(row.lobe) if row.parts else 0 for row in rows], np.uint32))
        # Kernels of the plain BSDFs (a blend row has none: NO_KERNEL).
        keys = [(row.type, row.lobe.variant(row.values)) for row in rows]
        self.kernels = list(dict.fromkeys(k for row, k in zip(rows, keys) if row.parts is None))
        self.kernel_of_row = device_array(UInt32, np.array(
            [NO_KERNEL if row.parts is not None else self.kernels.index(k)
             for row, k in zip(rows, keys)], np.uint32))
        self.back = back
        self.back_of_row = device_array(UInt32, np.array(back, np.uint32))
        self.two_sided = any(b != NO_BACK for b in back)
        # Rows whose BSDF scatters on both sides itself (dielectrics: no frame flip; a mix
        # whose parts see some light from below: they resolve their own sides; a one-sided
        # BSDF under a normal map, whose tilted frame decides which side wi sees).
        def own_sides(m: Material) -> bool:
            return m.both_sides or ((m.normal_map or m.bump_map or m.outer) is not None and m.back is None)

        both = [own_sides(row) if row.parts is None else
                any(own_sides(part) or part.back is not None for part in row.parts) for row in rows]
        self.both_sides = any(both)
        self.both_sides_of_row = device_array(UInt32, np.array(both, np.uint32)) if self.both_sides else None
        #: Whether some material reflects by a delta lobe only (a mirror).
        self.has_mirror = any(row.lobe.delta_only for row in rows)
        #: Whether some material may sample a delta lobe.
        self.has_delta = any(getattr(row.lobe, "samples_delta", False) for row in rows)
        #: Whether some material's value depends on the incoming direction beyond its side
        #: (every material but a diffuse one).
        self.reads_incoming = any(row.type != "diffuse" for row in rows)
        #: Whether some material lets light straight through (a pass-through lobe).
        self.passes_light = any(_passes(row.lobe) for row in rows)
        # Rows under a normal or bump map (their own or one around the whole material): they
        # let no light straight through, as Mitsuba's map plugins do not pass the query on.
        mapped = [(row.normal_map or row.bump_map or row.outer) is not None for row in rows]
        self.mapped_of_row = (device_array(UInt32, np.array(mapped, np.uint32))
                              if self.passes_light and any(mapped) else None)
        #: Whether some material's roughness is anisotropic (its BSDF reads the shading
        #: frame's tangent, which hits then compute from the surface's dp/du).
        self.anisotropic = any(getattr(row.lobe, "anisotropic", lambda values: False)(row.values)
                               for row in rows)
        #: Whether some kernel chooses between lobes (a third random number per sample).
        self.chooses_lobe = any(getattr(row.lobe, "chooses_lobe", False) for row in rows)
        # One column per numeric parameter name, over all rows (0 where a row lacks it); the
        # values a type derives from its parameters (an IOR ratio, a tabulated function:
        # one flat array of a row's samples after another's) likewise. Kept on the host
        # too, so that a row's constants can change (instancing.traverse).
        textures: list[Texture] = []
        #: (row, parameter) -> index of the texture giving it.
        self.texture_index: dict[tuple[int, str], int] = {}
        columns: dict[str, list] = {}
        for r, values in enumerate(self._row_values(range(len(rows)))):
            parameter_of = {_column(rows[r].lobe, key): key for key in rows[r].lobe.parameters}
            for column, value in values.items():
                if isinstance(value, Texture):
                    # The texture's index (one per texture object, however many rows
                    # read it) beside a constant 0 of the parameter's kind.
                    key = parameter_of[column]
                    if not any(value is t for t in textures):
                        textures.append(value)
                    self.texture_index[(r, key)] = next(k for k, t in enumerate(textures)
                                                        if t is value)
                    values[column] = (0.0,) * 3 if rows[r].lobe.parameters[key].kind == COLOR else 0.0
                columns.setdefault(column, [None] * len(rows))[r] = values[column]
        # Every table has the diffuse reflectance (the scene's differentiable colours).
        columns.setdefault("reflectance", [(0.0,) * 3] * len(rows))
        #: Host copies of the columns: (rows,) numbers, (rows, 3) colours, (rows, samples) tables.
        self.host: dict[str, np.ndarray] = {}
        self.values: dict[str, Float | Array3f] = {}
        #: Columns that hold several samples per row (read by the kernels with the row).
        self.tables: set[str] = set()
        for key, column in columns.items():
            sample = next(v for v in column if v is not None)
            zero = np.zeros_like(np.asarray(sample, np.float64))
            self.host[key] = np.array([zero if v is None else np.asarray(v, np.float64)
                                       for v in column], np.float32)
            if isinstance(sample, np.ndarray):  # a tabulated function
                self.tables.add(key)
            self._upload(key)
        #: (row, parameter) pairs whose tables' derivatives are tabulated (tabulate_derivatives).
        self.tabulated_derivatives: set[tuple[int, str]] = set()
        #: Whether some frame is tilted by a normal map (:mod:`instancing.materials.normal_map`)
        #: or a bump map (:mod:`instancing.materials.bump_map`, which reads the surface's
        #: derivatives at the hits). A map of a plain BSDF is filed as its row's parameter
        #: ``normalmap`` or ``bumpmap``; a map around a whole material (a twosided BSDF or a
        #: mix, ``Material.outer``) under OUTER's names, and tilts the frame before anything
        #: else. Per kind (row maps: False, outer ones: True) and row: the map's options (bit 0:
        #: flip_invalid_normals, bit 1: use_shadowing_function, bit 2: a map) and a bump map's
        #: scale.
        self.normal_mapped = any(isinstance(m.normal_map or m.outer, NormalMap) for m in rows)
        self.bump_mapped = any(isinstance(m.bump_map or m.outer, BumpMap) for m in rows)
        self._tilt_arrays: dict[bool, tuple[UInt32, Float]] = {}
        for outer in (False, True):
            options, scales = [0] * len(rows), [0.0] * len(rows)
            for r, row in enumerate(rows):
                tilt = row.outer if outer else (row.normal_map or row.bump_map)
                if tilt is None or (outer and r >= self.material_count):
                    continue
                key = NORMAL_MAP if isinstance(tilt, NormalMap) else BUMP_MAP
                if not any(tilt.texture is t for t in textures):
                    textures.append(tilt.texture)
                self.texture_index[(r, OUTER[key] if outer else key)] = next(
                    k for k, t in enumerate(textures) if t is tilt.texture)
                options[r] = 4 | int(tilt.flip_invalid_normals) | int(tilt.use_shadowing_function) << 1
                scales[r] = getattr(tilt, "scale", 0.0)
            if any(options):
                self._tilt_arrays[outer] = (device_array(UInt32, np.array(options, np.uint32)),
                                            device_array(Float, np.array(scales, np.float32)))
        #: The scene's textures, and per textured parameter each row's texture (or NO_TEXTURE).
        self.textures = TextureSet(textures, attributes, origin) if textures else None
        # Each texture as the materials first held it -> its index: a map's record keeps that
        # object when the texture changes (see current_texture).
        self._first_texture = {id(t): (k, t) for k, t in enumerate(textures)}
        texture_of: dict[str, list[int]] = {}
        for (r, key), t in self.texture_index.items():
            texture_of.setdefault(key, [NO_TEXTURE] * len(rows))[r] = t
        self.texture_of = {key: device_array(UInt32, np.array(index, np.uint32))
                           for key, index in texture_of.items()}

    def _row_values(self, rows) -> list[dict]:
        """Per row (indices): its numeric parameters (by column, :func:`_column`) and the
        values its type derives."""
        rows = list(rows)
        derived: dict[int, dict] = {}
        for lobe in {self.rows[r].lobe for r in rows if hasattr(self.rows[r].lobe, "derived")}:
            mine = [r for r in rows if self.rows[r].lobe is lobe]
            derived.update(zip(mine, lobe.derived([self.rows[r].values for r in mine])))
        result = []
        for r in rows:
            row = self.rows[r]
            values = {_column(row.lobe, key): row.values[key] for key, parameter in row.lobe.parameters.items()
                      if parameter.kind in (COLOR, NUMBER) and key in row.values}
            values.update(derived.get(r, {}))
            result.append(values)
        return result

    def _upload(self, key: str) -> None:
        """The device column ``key`` from its host copy."""
        host = self.host[key]
        if host.ndim == 2 and key not in self.tables:  # colours
            self.values[key] = device_vectors(host)
        else:
            self.values[key] = device_arrays(Float, host.ravel())[0]

    def shared_back(self, material: int) -> int | None:
        """The row of row ``material``'s back side where that is the front's own BSDF
        (a ``twosided`` with one BSDF: its parameters are the front's), else None."""
        back = self.back[material]
        if back in (NO_BACK, material) or self.rows[back].values is not self.rows[material].values:
            return None
        return back

    def rows_of(self, row: int) -> list[int]:
        """Every row holding row ``row``'s parameters: the row, its shared back side, and
        the rows of the same BSDF elsewhere (a blend's part under a twosided blend appears
        under its back row too)."""
        shared = self.shared_back(row)
        same = {id(self.rows[row])} | ({id(self.rows[shared])} if shared is not None else set())
        return [r for r, m in enumerate(self.rows) if id(m) in same]

    def set_constants(self, material: int, changes: dict, part: int | None = None) -> Material:
        """Give material ``material`` (or its ``part``-th part: a blend's or mask's BSDF) new
        constant parameter values (validated by the caller; a two-sided BSDF with one BSDF
        on both sides): its columns and the values its type derives from them are
        rewritten. Returns the new material."""
        row = material if part is None else self.part_rows[material][part]
        rows = self.rows_of(row)
        old = self.rows[row]
        values = {**old.values, **changes}
        if hasattr(old.lobe, "changed"):
            values = old.lobe.changed(values, set(changes))
        back, shared = old.back, self.shared_back(row)
        if shared is not None:
            back = dataclasses.replace(self.rows[shared], values=values)
        new = {id(old): dataclasses.replace(old, values=values, back=back)}
        if shared is not None:
            new[id(self.rows[shared])] = back
        if part is not None:
            # The mix holding it (and its own back side, a twosided mix) hold the new part.
            top = self.rows[material]
            parts = tuple(new[id(old)] if p is old else p for p in top.parts)
            top_back = top.back
            if top_back is not None and top_back is not top and top_back.parts is top.parts:
                top_back = new[id(top_back)] = dataclasses.replace(top_back, parts=parts)
            new[id(top)] = dataclasses.replace(top, parts=parts, back=top_back)
        for r, m in enumerate(self.rows):
            if id(m) in new:
                self.rows[r] = new[id(m)]
        self._rewrite(rows)
        return self.rows[material]

    def current_texture(self, texture: Texture) -> Texture:
        """The texture as the table holds it now, for a texture that a material's record
        gave (a normal or bump map's record keeps the texture it was loaded with when its
        texels are set); other textures as they are."""
        k, first = self._first_texture.get(id(texture), (None, None))
        return self.textures.textures[k] if first is texture else texture

    def set_texels(self, texture: int, texels: np.ndarray) -> None:
        """Replace the texels of bitmap ``texture`` (same size); the values derived from
        them (a plastic's sampling weight reads its texture's mean) follow."""
        self.textures.set_texels(texture, texels)
        self._replace_texture(texture, texels=self.textures.texels_of(texture), filename="")

    def set_texture_color(self, texture: int, field: str, rgb: tuple[float, float, float]) -> None:
        """Replace checkerboard ``texture``'s ``field`` ("color0" or "color1"); the values
        derived from it follow."""
        self.textures.set_color(texture, field, rgb)
        self._replace_texture(texture, **{field: tuple(float(c) for c in rgb)})

    def _replace_texture(self, texture: int, **changes) -> None:
        """Texture ``texture``'s record with ``changes``, in the set and in the values of
        the rows reading it, whose derived values are recomputed."""
        old = self.textures.textures[texture]
        new = self.textures.textures[texture] = dataclasses.replace(old, **changes)
        rows = []
        for (row, key), t in self.texture_index.items():
            if t == texture and key not in (NORMAL_MAP, BUMP_MAP, *OUTER.values()):  # (no BSDF values)
                self.rows[row].values[key] = new  # (the dict a two-sided back shares too)
                rows.append(row)
        self._rewrite(rows)

    def _rewrite(self, rows: list[int]) -> None:
        """Recompute the constant columns (and derived values, and the derivatives of tables
        that are tabulated) of ``rows`` from their materials and upload the columns that
        changed."""
        changed = set()
        for row, row_values in zip(rows, self._row_values(rows)):
            for key, value in row_values.items():
                if isinstance(value, Texture):
                    continue
                value = np.asarray(value, np.float32)
                if not np.array_equal(self.host[key][row], value):
                    self.host[key][row] = value
                    changed.add(key)
        for key in changed:
            self._upload(key)
        for parameter in {p for r, p in self.tabulated_derivatives if r in rows}:
            self._tabulate(parameter, [r for r in rows if (r, parameter) in self.tabulated_derivatives])

    def tabulate_derivatives(self, rows: list[int], parameter: str) -> None:
        """Tabulate the derivatives with respect to ``parameter`` of the tables ``rows``
        precompute from it (rows whose type tabulates from it; once: they follow later
        changes), so that its derivatives reach those tables' values."""
        rows = [r for r in rows if parameter in getattr(self.rows[r].lobe, "tabulated_from", ())
                and (r, parameter) not in self.tabulated_derivatives]
        if rows:
            self.tabulated_derivatives.update((r, parameter) for r in rows)
            self._tabulate(parameter, rows)

    def _tabulate(self, parameter: str, rows: list[int]) -> None:
        """Compute and upload the derivative tables of ``rows`` with respect to ``parameter``
        (columns made on first use, zero in other rows)."""
        for lobe in {self.rows[r].lobe for r in rows}:
            mine = [r for r in rows if self.rows[r].lobe is lobe]
            for r, derived in zip(mine, lobe.derivatives([self.rows[r].values for r in mine], parameter)):
                for key, value in derived.items():
                    value = np.asarray(value, np.float32)
                    if key not in self.host:
                        self.host[key] = np.zeros((len(self.rows), *value.shape), np.float32)
                        if value.ndim:
                            self.tables.add(key)
                    self.host[key][r] = value
        for key in [k for k in self.host if k.endswith(f"_d_{parameter}")]:
            self._upload(key)

    def texture(self, material: int, key: str) -> int | None:
        """The index (in :attr:`textures`) of the texture giving parameter ``key`` of
        material ``material``, or None where a constant gives it."""
        return self.texture_index.get((material, key))

    def state(self) -> dict:
        """The arrays that may carry derivatives: the columns read per lookup (not the
        tabulated ones) and, with bitmaps, the texels, with checkerboards their colours, with
        mesh attributes their corner values."""
        state = {key: value for key, value in self.values.items() if key not in self.tables}
        if self.textures is not None and self.textures.has_bitmaps:
            state["texels"] = self.textures.texels
        if self.textures is not None and self.textures.has_checkerboards:
            state["texture.color0"], state["texture.color1"] = self.textures.color0, self.textures.color1
        if self.textures is not None and self.textures.has_attributes:
            state["attributes"] = self.textures.attributes
        return state

    def restore(self, state: dict) -> None:
        """Make ``state`` (as :meth:`state` returns it; e.g. grad-enabled) the table's arrays."""
        for key, value in state.items():
            if key in ("texels", "attributes"):
                setattr(self.textures, key, value)
            elif key.startswith("texture."):  # a checkerboard colour
                setattr(self.textures, key.split(".")[1], value)
            else:
                self.values[key] = value

    @property
    def differentiable(self) -> bool:
        """Whether some array of :meth:`state` carries derivatives."""
        return bool(dr.grad_enabled(*self.state().values()))

    @property
    def reflectance(self) -> Array3f:
        """The diffuse reflectance of the materials (their rows; 0 for other types)."""
        stored = self.values["reflectance"]
        if len(self.rows) == self.material_count:
            return stored
        return dr.gather(Array3f, stored, dr.arange(UInt32, self.material_count))

    def albedo(self, material: UInt32, uv: Coordinates | None = None) -> Array3f:
        """Each lane's material's albedo (Mitsuba's AOV): the lobe's own colour parameter
        (0 for dielectrics)."""
        def albedo(row: UInt32) -> Array3f:
            return self._per_lane_kernel(row, uv, (), (Array3f(0.0),), lambda lobe, variant, p: (
                Array3f(0.0) if lobe.albedo is None else p[lobe.albedo],))[0]

        return self._blended(material, uv, albedo)

    def roughness(self, material: UInt32, uv: Coordinates | None = None) -> Float:
        """Each lane's material's microfacet roughness ``alpha`` (textured ones looked up at
        ``uv``; a principled material's from its ``roughness``; an anisotropic one's the
        geometric mean of ``alpha_u`` and ``alpha_v``; 0 for smooth and diffuse materials)."""
        def alpha(lobe, variant, p) -> tuple[Float]:
            if hasattr(lobe, "microfacet_alpha"):
                return (lobe.microfacet_alpha(p, variant),)
            return (p["alpha"] if "alpha" in lobe.parameters else Float(0.0),)

        return self._per_lane_kernel(material, uv, (), (Float(0.0),), alpha)[0]

    def reflects(self, material: UInt32, wi: Array3f) -> Bool:
        """Whether the side of each lane's material that wi (shading frame) looks at
        scatters light: the front, the back of a two-sided material, either side of a
        dielectric."""
        return self._side(material, wi)[2]

    def mirror(self, material: UInt32, wi: Array3f) -> Bool:
        """Whether the side of each lane's material that wi (shading frame) looks at scatters
        by delta lobes only (a mirror, glass, a pass-through: no density of directions to
        evaluate, and no light for a light sample to find)."""
        if not self.has_mirror:
            return Bool(False)
        row, _, lit = self._side(material, wi)
        kernel = dr.gather(UInt32, self.kernel_of_row, row, lit)
        result = Bool(False)
        for k, (name, variant) in enumerate(self.kernels):
            if LOBES[name].delta_only:
                result |= kernel == k
        return result & lit

    def null_transmission(self, material: UInt32, wi: Array3f, uv: Coordinates | None = None) -> Array3f:
        """The share of the light arriving along -wi (shading frame) that each lane's
        material lets straight through (Mitsuba's ``eval_null_transmission``): its
        pass-through lobe's (:mod:`instancing.materials.mask`, a thin dielectric's
        ``(1 - R') specular_transmittance``), a mix's weighted sum of its parts', 0 for
        every other BSDF and under a normal or bump map."""
        if not self.passes_light:
            return dr.zeros(Array3f, dr.width(wi))
        row, flip, lit = self._side(material, wi)
        wi = _flipped(wi, flip)

        def part_value(part: UInt32) -> Array3f:
            part_wi, part_lit = wi, Bool(True)
            if self.blends:
                part, part_flip, part_lit = self._side(part, wi)
                part_wi = _flipped(wi, part_flip)
            value = self._per_lane_kernel(part, uv, (part_wi,), (Array3f(0.0),), lambda lobe, variant, p, wi: (
                lobe.null_transmission(p, wi, variant) if _passes(lobe) else Array3f(0.0),))[0]
            return dr.select(part_lit & self._unmapped(part, part_lit), value, 0.0)

        value = self._blended(row, uv, part_value)
        return dr.select(lit & self._unmapped(material) & self._unmapped(row, lit), value, 0.0)

    def _unmapped(self, row: UInt32, active: Bool | bool = True) -> Bool:
        """Whether each lane's row is under no normal or bump map (lanes not ``active``, whose
        row may be a missing back side, read none)."""
        if self.mapped_of_row is None:
            return Bool(True)
        return dr.gather(UInt32, self.mapped_of_row, row, active) == 0

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
        row where wi is below the surface, its frame flipped; a one-sided material's own row,
        unlit, so that lanes never read past the table), whether the frame is flipped, and
        whether that side scatters (a dielectric sees wi below the surface itself: no flip)."""
        both = Bool(False)
        if self.both_sides:
            both = dr.gather(UInt32, self.both_sides_of_row, material) != 0
        if not self.two_sided:
            return material, Bool(False), (wi.z > 0) | both
        below = (wi.z < 0) & ~both
        back = dr.gather(UInt32, self.back_of_row, material)
        has_back = back != NO_BACK
        return dr.select(below & has_back, back, material), below, ~below | has_back

    def _parameters(self, lobe, row: UInt32, uv: Coordinates | None) -> dict:
        """The lanes' values of what ``lobe`` reads: its parameters and derived values
        gathered by row, textured ones looked up at ``uv``; tabulated ones whole (with
        ``row`` to index them)."""
        columns = {key: _column(lobe, key) for key in lobe.parameters}
        columns.update((key, key) for key in getattr(lobe, "derived_keys", ()))
        p = {key: (self.values[column] if column in self.tables
                   else dr.gather(type(self.values[column]), self.values[column], row))
             for key, column in columns.items() if column in self.values}
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

    def _per_lane_kernel(self, row: UInt32, uv: Coordinates | None, inputs: tuple, initial: tuple,
                         compute: Callable) -> tuple:
        """``compute(lobe, variant, parameters, *inputs)`` (a tuple) of each lane's row's
        kernel, ``initial`` where none applies. Where nothing carries derivatives, each
        kernel runs in a branch of its own, which a SIMD packet skips when none of its lanes
        uses that kernel; otherwise every lane runs every kernel (a symbolic branch would
        carry the AD graph through a conditional) and selects its own."""
        if len(self.kernels) == 1:
            lobe, variant = self._lobe(0)
            return compute(lobe, variant, self._parameters(lobe, row, uv), *inputs)
        # Every lane of the query (a branch runs as wide as its condition; one material for
        # all lanes is one row).
        lanes = dr.width((row, uv, inputs))
        kernel = dr.gather(UInt32, self.kernel_of_row, row) + dr.zeros(UInt32, lanes)
        branched = not (self.differentiable or dr.grad_enabled(inputs, uv))
        value = initial
        for k in range(len(self.kernels)):
            lobe, variant = self._lobe(k)

            def computed(row, inputs, value, lobe=lobe, variant=variant):
                return compute(lobe, variant, self._parameters(lobe, row, uv), *inputs)

            if branched:
                value = dr.if_stmt((row, inputs, value), kernel == k, computed,
                                   lambda row, inputs, value: value, mode="symbolic")
            else:
                value = tuple(dr.select(kernel == k, new, old)
                              for new, old in zip(computed(row, inputs, value), value))
        return value

    def _lobe(self, k: int) -> tuple:
        """(the BSDF type's lobe, the variant) of kernel ``k``."""
        name, variant = self.kernels[k]
        return next(r.lobe for r in self.rows if r.type == name), variant

    def evaluate(self, material: UInt32, wi: Array3f, wo: Array3f,
                 uv: Coordinates | None = None, surface: SurfaceFrame | None = None) -> Array3f:
        """f cos(theta_o) of each lane's material for directions wi, wo (shading frame), at
        surface coordinates ``uv`` (needed where a material is textured or normal-mapped)
        and with the surface's derivatives ``surface`` (needed where one is bump-mapped)."""
        return self._per_kernel("eval", Array3f, material, wi, wo, uv, surface)

    def pdf(self, material: UInt32, wi: Array3f, wo: Array3f, uv: Coordinates | None = None,
            surface: SurfaceFrame | None = None) -> Float:
        """The solid-angle density with which :meth:`sample` picks wo (0 for delta lobes)."""
        return self._per_kernel("pdf", Float, material, wi, wo, uv, surface)

    def _per_kernel(self, method: str, result: type, material: UInt32, wi: Array3f, wo: Array3f,
                    uv: Coordinates | None, surface: SurfaceFrame | None):
        """Each lane's kernel's ``method`` (eval or pdf) on the side wi sees, 0 where that
        side does not reflect."""
        outer = self._tilt(material, wi, uv, surface, outer=True)
        wo_shading = wo
        if outer is not None:
            wi, wo = into(outer[1:], wi), into(outer[1:], wo)
        wo_tilted = wo
        row, flip, lit = self._side(material, wi)
        wi, wo = _flipped(wi, flip), _flipped(wo, flip)
        value = self._blended(row, uv, lambda part: self._kernels(method, result, part, wi, wo, uv,
                                                                  surface))
        value = dr.select(lit, value, 0.0)
        if outer is not None:
            value = self._tilted(outer, value, wo_shading, wo_tilted, shadow=method == "eval")
        return value

    def _kernels(self, method: str, result: type, row: UInt32, wi: Array3f, wo: Array3f,
                 uv: Coordinates | None, surface: SurfaceFrame | None = None):
        """``method`` of each lane's plain row's kernel; in a table with mixes, on the side
        the row itself shows wi (a part's own twosided back), 0 where it does not scatter."""
        lit = Bool(True)
        if self.blends:
            row, flip, lit = self._side(row, wi)
            wi, wo = _flipped(wi, flip), _flipped(wo, flip)
        tilt = self._tilt(row, wi, uv, surface)
        wo_shading = wo
        if tilt is not None:
            wi, wo = into(tilt[1:], wi), into(tilt[1:], wo)
        value = self._per_lane_kernel(
            row, uv, (wi, wo), (result(0.0),),
            lambda lobe, variant, p, wi, wo: (getattr(lobe, method)(p, wi, wo, variant),))[0]
        if tilt is not None:
            value = self._tilted(tilt, value, wo_shading, wo, shadow=method == "eval")
        return dr.select(lit, value, 0.0)

    def _tilt(self, row: UInt32, wi: Array3f, uv: Coordinates | None, surface: SurfaceFrame | None,
              outer: bool = False):
        """(mapped, n, s, options) per lane: whether its row has a normal or bump map (with
        ``outer``: one around the whole material), the tilted frame (n, s) in the row's
        shading frame (the untilted one where none) and the map's options; None in a table
        without such maps."""
        if outer not in self._tilt_arrays:
            return None
        if uv is None or (self.bump_mapped and surface is None):
            raise ValueError("a normal- or bump-mapped material is looked up without surface "
                             "coordinates or derivatives")
        options_of_row, scale_of_row = self._tilt_arrays[outer]
        options = dr.gather(UInt32, options_of_row, row)
        flip = (options & 1) != 0
        mapped = Bool(False)
        n, s = Array3f(0.0, 0.0, 1.0), Array3f(1.0, 0.0, 0.0)
        for key in (NORMAL_MAP, BUMP_MAP):
            name = OUTER[key] if outer else key
            if name not in self.texture_of:
                continue
            texture = dr.gather(UInt32, self.texture_of[name], row)
            mine = texture != NO_TEXTURE
            if key == NORMAL_MAP:
                n_k, s_k = tilted_frame(self.textures.eval(texture, uv, mine), wi, flip)
            else:
                gradient = self.textures.gradient(texture, uv, mine) * dr.gather(Float, scale_of_row, row)
                n_k, s_k = bumped_frame(gradient, surface, wi, flip)
            n, s = dr.select(mine, n_k, n), dr.select(mine, s_k, s)
            mapped |= mine
        return mapped, n, s, options

    @staticmethod
    def _tilted(tilt, value, wo_shading: Array3f, wo_tilted: Array3f, shadow: bool):
        """A value of the tilted frame's BSDF at a direction given in both frames: 0 where
        they put it on opposite sides, times the shadowing term (``shadow``) where the map
        asks for it."""
        mapped, n, _, options = tilt
        value = dr.select(wo_shading.z * wo_tilted.z > 0.0, value, 0.0)
        if shadow:
            value = value * dr.select(mapped & ((options & 2) != 0), shadowing(n, wo_shading), 1.0)
        return value

    def _route(self, row: UInt32, uv: Coordinates | None) -> tuple[Bool, Float, UInt32, UInt32]:
        """Per lane: whether its row is a mix (blend or mask), the mix's weight of its
        second part (clipped to [0, 1]), and the rows of its two parts (the row itself
        where it is no mix)."""
        first, second = (dr.gather(UInt32, parts, row) for parts in self.parts_of_row)
        mixed = first != NO_BACK
        weight = Float(0.0)
        for k, lobe in enumerate(self.mixes):
            own = self._parameters(lobe, row, uv)[lobe.weight_key]
            weight = own if k == 0 else dr.select(dr.gather(UInt32, self.mix_of_row, row) == k,
                                                  own, weight)
        return mixed, dr.select(mixed, dr.clip(weight, 0.0, 1.0), 0.0), \
            dr.select(mixed, first, row), dr.select(mixed, second, row)

    def _blended(self, row: UInt32, uv: Coordinates | None, value):
        """``value(rows)`` of each lane's BSDF: of its row, or for a mix the sum
        (1 - weight) value(first) + weight value(second) of its parts."""
        if not self.blends:
            return value(row)
        blend, weight, first, second = self._route(row, uv)
        a = value(first)
        return dr.select(blend, dr.fma(value(second) - a, weight, a), a)

    def sample(self, material: UInt32, wi: Array3f, sampler, uv: Coordinates | None = None,
               surface: SurfaceFrame | None = None) -> BSDFSample:
        """A direction wo drawn from each lane's material (two random numbers, three where
        some material chooses between lobes)."""
        u0 = sampler.next_float32() if self.chooses_lobe else Float(0.0)
        return self.sample_from(material, wi, (u0, *sampler.next_pair()), uv, surface)

    def sample_from(self, material: UInt32, wi: Array3f, u: tuple[Float, Float, Float],
                    uv: Coordinates | None = None, surface: SurfaceFrame | None = None,
                    inside: bool = False) -> BSDFSample:
        """:meth:`sample` with the random numbers ``u`` given (e.g. to redo a sample with
        derivatives: those of the materials' parameters reach its weight)."""
        outer = None if inside else self._tilt(material, wi, uv, surface, outer=True)
        if outer is not None:
            # In the frame a map around the whole material tilts (``inside``: already there).
            sample = self.sample_from(material, into(outer[1:], wi), u, uv, surface, inside=True)
            wo = out_of(outer[1:], sample.wo)
            valid = sample.valid & (wo.z * sample.wo.z > 0.0)
            weight = self._tilted(outer, sample.weight, wo, sample.wo, shadow=True)
            return BSDFSample(wo, dr.select(valid, weight, 0.0), dr.select(valid, sample.pdf, 0.0),
                              sample.delta, valid, u, sample.null & valid, sample.eta)
        row, flip, lit = self._side(material, wi)
        wi = _flipped(wi, flip)
        part, drawn, own_wi, own_flip = row, u, wi, Bool(False)
        if self.blends:
            # A mix draws one of its parts by its weight (u[0] rescaled for that part),
            # which shows wi its own side.
            blend, w, first, second = self._route(row, uv)
            take_second = blend & (u[0] < w)
            drawn = (dr.select(blend, dr.select(take_second, u[0] / w, (u[0] - w) / (1.0 - w)),
                               u[0]), u[1], u[2])
            part, own_flip, own_lit = self._side(dr.select(take_second, second, first), wi)
            own_wi = _flipped(wi, own_flip)
            lit &= own_lit
        tilt = self._tilt(part, own_wi, uv, surface)
        if tilt is not None:
            own_wi = into(tilt[1:], own_wi)
        def drawn_by(lobe, variant, p, own_wi, *drawn):
            wo, weight, pdf, valid, delta = lobe.sample(p, own_wi, drawn, variant)
            # A pass-through lobe's is the direction that goes on unchanged.
            null = dr.all(wo == -own_wi) if _passes(lobe) else Bool(False)
            eta = Float(1.0)
            if getattr(lobe, "refracts", False):
                ior = p["relative_ior"]
                eta = dr.select(wo.z * own_wi.z < 0, dr.select(own_wi.z > 0, ior, dr.rcp(ior)), 1.0)
            return wo, weight, pdf, valid, delta, null, eta

        wo, weight, pdf, valid, delta, null, eta = self._per_lane_kernel(
            part, uv, (own_wi,) + tuple(drawn),
            (Array3f(0.0), Array3f(0.0), Float(0.0), Bool(False), Bool(False), Bool(False), Float(1.0)),
            drawn_by)
        if tilt is not None:
            # The direction back in the shading frame; it counts on the side of both frames.
            tilted_wo, wo = wo, out_of(tilt[1:], wo)
            valid &= wo.z * tilted_wo.z > 0.0
            pdf = dr.select(valid, pdf, 0.0)
            weight = self._tilted(tilt, weight, wo, tilted_wo, shadow=True)
        wo = _flipped(wo, own_flip)
        if self.blends:
            # The direction weighed by the mixture: f / p of both parts' weighted sums; a
            # delta lobe keeps its part's weight (the other part has no density there),
            # times share / detach(share): the derivative of the choice.
            other = dr.select(take_second, first, second)
            share = dr.select(take_second, w, 1.0 - w)
            mixed = blend & ~delta
            f_other = self._kernels("eval", Array3f, other, wi, wo, uv, surface)
            p_other = self._kernels("pdf", Float, other, wi, wo, uv, surface)
            p_mix = share * pdf + (1.0 - share) * p_other
            f_mix = share * weight * pdf + (1.0 - share) * f_other
            weight = dr.select(mixed, dr.select(p_mix > 0, f_mix / p_mix, 0.0),
                               dr.select(blend & delta & (share > 0), weight * chosen(share), weight))
            pdf = dr.select(mixed, p_mix, pdf)
        valid &= lit
        return BSDFSample(_flipped(wo, flip), dr.select(valid, weight, 0.0), pdf, delta, valid, u,
                          null & valid, dr.select(valid, eta, 1.0))


def _column(lobe, key: str) -> str:
    """The table column that holds parameter ``key`` of BSDF type ``lobe``: its name, or the
    parameter's own ``column`` (a name another type gives a value of another kind)."""
    parameter = lobe.parameters.get(key)
    return key if parameter is None or parameter.column is None else parameter.column


def _passes(lobe) -> bool:
    """Whether a BSDF kernel has a pass-through lobe (it says how much light passes)."""
    return hasattr(lobe, "null_transmission")


def _flipped(w: Array3f, flip: Bool) -> Array3f:
    """w mirrored through the tangent plane where ``flip``."""
    return Array3f(w.x, w.y, dr.select(flip, -w.z, w.z))
