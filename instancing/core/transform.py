"""Affine transforms in homogeneous coordinates (lecture: "Affine Transformations").

A :class:`Transform` is an immutable value that holds a 4x4 matrix together
with its inverse, so that ``inverse()`` is free and the inverse of a
composition is assembled from the parts' inverses in reverse order
(``(A B)^-1 = B^-1 A^-1``, lecture slide "Inverse Transformations") instead
of by a general matrix inversion.

Two flavours share one implementation:

* *scalar* transforms (``drjit.scalar.Matrix4f64``, float64) built from
  Python numbers, used for scene set-up, where float64 keeps long chains of
  compositions exact to ~1e-15 before they are rounded once to float32;
* *per-lane* transforms (the backend's ``Matrix4f``, float32, one matrix per
  ray or per instance) built when any argument is a Dr.Jit array. These are
  differentiable: gradients flow through both the matrix and its inverse,
  because the inverse is built from the same parameters.

Transform chains compose like Mitsuba's ``T().translate(a).rotate(b).scale(c)``:
``A @ B`` applies ``B`` first. Names read destination-from-source, e.g.
``world_from_object = translate(...) @ rotate(...) @ scale(...)``.
"""

from __future__ import annotations

import math
from typing import Any, Sequence

import drjit.scalar as ds
import numpy as np

from .backend import Array3f, Array4f, Matrix4f, dr
from .errors import TransformError

#: Largest sensitivity of a linear part's determinant to rounding its entries
#: (:func:`determinant_sensitivity`) accepted for float32 storage: rounding every entry
#: to float32 (relative 2^-24) then moves the determinant by at most 1 % of itself (to
#: first order). The measure ignores scaling of rows and columns, so a rotated
#: 1e-6 : 1 : 1e5 scale (condition number 1e11) passes; only axes collapsing onto each
#: other fail it.
MAX_DETERMINANT_SENSITIVITY = 0.01 * 2.0 ** 24


def _is_jit(value: Any) -> bool:
    return dr.is_jit_v(value) or (
        isinstance(value, (tuple, list)) and any(dr.is_jit_v(v) for v in value))


def _matrix_type(*args: Any) -> type:
    """Per-lane float32 matrices when any argument is a Dr.Jit array, else scalar float64."""
    return Matrix4f if any(_is_jit(a) for a in args) else ds.Matrix4f64


def _vec3(value: Any, name: str) -> tuple:
    """A 3-vector argument as a tuple of three components (scalars or Dr.Jit arrays)."""
    if value is None:
        raise TransformError(f"{name}: expected a number or 3 numbers, got None")
    if dr.is_jit_v(value) and dr.size_v(value) == 3:
        return (value.x, value.y, value.z)
    if dr.is_jit_v(value):
        return (value, value, value)
    if isinstance(value, (int, float, np.floating, np.integer)):
        return (float(value),) * 3
    try:
        comps = tuple(value)
    except TypeError:
        raise TransformError(f"{name}: expected a number or 3 numbers, got {value!r}") from None
    if len(comps) != 3:
        raise TransformError(f"{name}: expected 3 components, got {len(comps)} ({value!r})")
    return tuple(c if dr.is_jit_v(c) else _number(c, name, value) for c in comps)


def _number(value: Any, name: str, given: Any = None) -> float:
    """A scalar builder argument as a float (a bool or a string is no number)."""
    if isinstance(value, (bool, str, bytes)) or not isinstance(value, (int, float, np.floating, np.integer)):
        raise TransformError(f"{name}: expected numbers, got {value if given is None else given!r}")
    return float(value)


def _check_finite(name: str, *values: Any) -> None:
    """Reject NaN and infinity in scalar builder arguments (per-lane ones are checked by the scene)."""
    for v in values:
        if not dr.is_jit_v(v) and not math.isfinite(_number(v, name)):
            raise TransformError(f"{name}: non-finite value {v!r}")


def _from_rows(mtype: type, rows: Sequence[Sequence[Any]]) -> Any:
    return mtype(*[entry for row in rows for entry in row])


class Transform:
    """An affine map with its inverse: ``matrix`` maps source to destination.

    Attributes:
        matrix: ``Matrix4f64`` (scalar) or backend ``Matrix4f`` (per lane).
        inverse_matrix: the inverse of ``matrix``, same type.

    Build transforms with the module's builders (``translate``, ``scale``,
    ``rotate``, ``reflect``, ``look_at``, ``from_matrix``); the constructor
    trusts that the two matrices are inverses of each other.
    """

    __slots__ = ("matrix", "inverse_matrix")

    def __init__(self, matrix: Any, inverse_matrix: Any):
        object.__setattr__(self, "matrix", matrix)
        object.__setattr__(self, "inverse_matrix", inverse_matrix)

    def __setattr__(self, name: str, value: Any) -> None:
        raise AttributeError("Transform is immutable")

    @property
    def is_scalar(self) -> bool:
        """True for a float64 set-up transform, False for per-lane Dr.Jit matrices."""
        return not dr.is_jit_v(self.matrix)

    def inverse(self) -> "Transform":
        """The inverse transform (swaps the stored matrices; no arithmetic)."""
        return Transform(self.inverse_matrix, self.matrix)

    def to_lanes(self) -> "Transform":
        """This transform as per-lane float32 Dr.Jit matrices (rounded once from float64)."""
        if not self.is_scalar:
            return self
        return Transform(Matrix4f(self.matrix), Matrix4f(self.inverse_matrix))

    def __matmul__(self, other: "Transform") -> "Transform":
        """Composition ``self @ other``: apply ``other`` first, then ``self``.

        The inverse is ``other^-1 @ self^-1`` (lecture: reverse order of the parts).
        """
        if not isinstance(other, Transform):
            return NotImplemented
        a, b = self, other
        if a.is_scalar != b.is_scalar:
            a, b = a.to_lanes(), b.to_lanes()
        return Transform(a.matrix @ b.matrix, b.inverse_matrix @ a.inverse_matrix)

    # -- application (lecture: points w=1, vectors w=0, normals by the inverse transpose)

    def apply_point(self, p: Any) -> Any:
        """Map a point (w = 1): ``A p + b``, the translation added last."""
        return _affine(self.matrix, p, translate=True)

    def apply_vector(self, v: Any) -> Any:
        """Map a vector (w = 0): ``A v``; translation does not act on directions."""
        return _affine(self.matrix, v, translate=False)

    def apply_normal(self, n: Any) -> Any:
        """Map a normal by the inverse transpose ``(A^-1)^T n`` and normalize it.

        Outward normals stay outward under reflections, because the inverse
        transpose is the gradient of the implicit surface ``f(M^-1 x) = 0``.
        """
        return dr.normalize(_linear_transposed(self.inverse_matrix, n))

    def apply_homogeneous(self, v: Any) -> Any:
        """Map a homogeneous 4-vector and return it normalized to w in {0, 1}.

        A vector with w != 0 is divided by w (a point); w = 0 is a point at
        infinity and is mapped as a direction. Returns an ``Array4f`` (or scalar
        ``Array4f64``) whose w is 1 for points and 0 for directions.
        """
        xyz, at_infinity = homogeneous_to_cartesian(v)
        mapped = dr.select(at_infinity, self.apply_vector(xyz), self.apply_point(xyz))
        array4 = Array4f if dr.is_jit_v(mapped) else ds.Array4f64
        return array4(mapped.x, mapped.y, mapped.z, dr.select(at_infinity, 0.0, 1.0))

    def to_numpy(self) -> tuple[np.ndarray, np.ndarray]:
        """(matrix, inverse) as float64 NumPy arrays: (4, 4), or (N, 4, 4) per lane."""
        return _matrix_to_numpy(self.matrix), _matrix_to_numpy(self.inverse_matrix)

    def __repr__(self) -> str:
        return f"Transform(\n{self.matrix})"


def _affine(m: Any, v: Any, translate: bool) -> Any:
    """Rows of the affine part applied to v, accumulated with fused multiply-adds."""
    array3 = Array3f if (dr.is_jit_v(m) or dr.is_jit_v(v)) else ds.Array3f64
    if not dr.is_jit_v(v) and (not hasattr(v, "__len__") or len(v) != 3):
        raise TransformError(f"expected a point or vector of 3 numbers, got {v!r}")
    rows = []
    for i in range(3):
        # Sum the linear terms first and add the translation last (pbrt-v4's point transform).
        lin = dr.fma(m[i][2], v[2], dr.fma(m[i][1], v[1], m[i][0] * v[0]))
        rows.append(lin + m[i][3] if translate else lin)
    return array3(*rows)


def _linear_transposed(m: Any, v: Any) -> Any:
    """The transpose of the upper 3x3 of m applied to v."""
    array3 = Array3f if (dr.is_jit_v(m) or dr.is_jit_v(v)) else ds.Array3f64
    return array3(*[dr.fma(m[2][j], v[2], dr.fma(m[1][j], v[1], m[0][j] * v[0])) for j in range(3)])


def homogeneous_to_cartesian(v: Any) -> tuple[Any, Any]:
    """Split homogeneous coordinates (x, y, z, w) into Cartesian ones.

    Returns ``(xyz / w, False)`` for points and ``(xyz, True)`` where w = 0
    (a point at infinity, i.e. a direction). Lecture: (X, Y, W) <-> (X/W, Y/W).
    """
    at_infinity = v[3] == 0
    w = dr.select(at_infinity, 1.0, v[3])
    array3 = Array3f if dr.is_jit_v(v) else ds.Array3f64
    return array3(v[0] / w, v[1] / w, v[2] / w), at_infinity


def _matrix_to_numpy(m: Any) -> np.ndarray:
    arr = np.array(m, dtype=np.float64)
    return arr if arr.ndim == 2 else np.moveaxis(arr, -1, 0)


# -- builders ---------------------------------------------------------------------------------


def identity() -> Transform:
    """The identity transform (scalar)."""
    return Transform(ds.Matrix4f64(1.0), ds.Matrix4f64(1.0))


def translate(offset: Any) -> Transform:
    """Translation by ``offset`` (3 numbers, or a Dr.Jit ``Array3f`` per lane).

    Lecture matrix T(dx, dy, dz); its inverse negates the offset.
    """
    x, y, z = _vec3(offset, "translate")
    _check_finite("translate", x, y, z)
    mtype = _matrix_type(x, y, z)
    fwd = _from_rows(mtype, [[1, 0, 0, x], [0, 1, 0, y], [0, 0, 1, z], [0, 0, 0, 1]])
    inv = _from_rows(mtype, [[1, 0, 0, -x], [0, 1, 0, -y], [0, 0, 1, -z], [0, 0, 0, 1]])
    return Transform(fwd, inv)


def scale(factors: Any) -> Transform:
    """Scaling, uniform (one number) or per axis (3 numbers / ``Array3f``).

    Lecture matrix S(a, b, c); its inverse takes reciprocals. A zero factor is
    singular and rejected; negative factors are reflections and allowed.
    """
    x, y, z = _vec3(factors, "scale")
    _check_finite("scale", x, y, z)
    for f in (x, y, z):
        if not dr.is_jit_v(f) and (f == 0.0 or not math.isfinite(1.0 / f)):
            raise TransformError(f"scale: factor {f!r} in {factors!r} makes the transform singular "
                                 "(its inverse is not finite)")
    mtype = _matrix_type(x, y, z)
    fwd = _from_rows(mtype, [[x, 0, 0, 0], [0, y, 0, 0], [0, 0, z, 0], [0, 0, 0, 1]])
    inv = _from_rows(mtype, [[1 / x, 0, 0, 0], [0, 1 / y, 0, 0], [0, 0, 1 / z, 0], [0, 0, 0, 1]])
    return Transform(fwd, inv)


def rotate(axis: Any, angle: Any) -> Transform:
    """Rotation by ``angle`` degrees about ``axis`` (normalized here).

    Counter-clockwise when looking along the negative axis (lecture, "3D
    Rotation"), i.e. right-handed, as Mitsuba's ``Transform4f.rotate``. The
    inverse is the transpose. Any finite angle works: it is reduced modulo 360 degrees
    exactly before its sine and cosine are taken.
    """
    ax = _vec3(axis, "rotate axis")
    _check_finite("rotate", *ax, angle)
    if not any(dr.is_jit_v(a) for a in ax):
        length = math.sqrt(sum(a * a for a in ax))
        if not 1e-150 < length < 1e150:
            # The squares over- or underflowed: the length without them.
            length = math.hypot(*ax)
        if length == 0.0:
            raise TransformError(f"rotate: zero-length axis {axis!r}")
        ax = tuple(a / length for a in ax)
    else:
        n = dr.normalize(Array3f(*ax))
        ax = (n.x, n.y, n.z)
    x, y, z = ax
    # Reduce the angle modulo 360 degrees exactly, in float64: sine and cosine lose all
    # accuracy on huge arguments (1e12 degrees gave a singular matrix).
    if not dr.is_jit_v(angle):
        angle = math.fmod(angle, 360.0)
    else:
        # Per lane, subtract the truncated quotient's multiple of 360 by a fused multiply-add:
        # each step's remainder is exact and at most 2^-53 of the value before (plus 360), so
        # 20 steps bring any float64 below 360. The remainder added to angle - angle (value 0)
        # keeps the derivative 1.
        reduced = dr.float64_array_t(type(angle))(dr.detach(angle))
        for _ in range(20):
            reduced = dr.fma(dr.trunc(reduced / 360.0), -360.0, reduced)
        angle = (angle - dr.detach(angle)) + type(angle)(reduced)
    s, c = dr.sincos(dr.deg2rad(angle))
    rows = rotation_rows(x, y, z, s, c)
    mtype = _matrix_type(x, y, z, angle)
    fwd = _from_rows(mtype, [r + [0] for r in rows] + [[0, 0, 0, 1]])
    inv = _from_rows(mtype, [[rows[j][i] for j in range(3)] + [0] for i in range(3)] + [[0, 0, 0, 1]])
    return Transform(fwd, inv)


def rotation_rows(x: Any, y: Any, z: Any, s: Any, c: Any) -> list[list[Any]]:
    """Rows of the rotation about the unit axis (x, y, z) by the angle of sine ``s`` and
    cosine ``c`` (Rodrigues' formula): numbers, NumPy or Dr.Jit arrays."""
    k = 1 - c
    return [[c + x * x * k, x * y * k - z * s, x * z * k + y * s],
            [y * x * k + z * s, c + y * y * k, y * z * k - x * s],
            [z * x * k - y * s, z * y * k + x * s, c + z * z * k]]


def rotate_x(angle: Any) -> Transform:
    """Rotation about +x by ``angle`` degrees (lecture R_x)."""
    return rotate((1.0, 0.0, 0.0), angle)


def rotate_y(angle: Any) -> Transform:
    """Rotation about +y by ``angle`` degrees (lecture R_y)."""
    return rotate((0.0, 1.0, 0.0), angle)


def rotate_z(angle: Any) -> Transform:
    """Rotation about +z by ``angle`` degrees (lecture R_z)."""
    return rotate((0.0, 0.0, 1.0), angle)


def rotate_quaternion(q: Any) -> Transform:
    """Rotation by the quaternion ``q = (x, y, z, w)``, normalized here.

    The parameter for optimisation: four numbers without the singularities of
    Euler angles, and any step of an optimiser is still a rotation because
    the builder divides by |q|. The inverse is the transpose.
    """
    if q is not None and dr.is_jit_v(q) and dr.size_v(q) == 4:
        comps = (q.x, q.y, q.z, q.w)
    else:
        try:
            comps = tuple(float(c) for c in q)
        except (TypeError, ValueError):
            raise TransformError(f"rotate_quaternion: expected 4 numbers, got {q!r}") from None
        if len(comps) != 4:
            raise TransformError(f"rotate_quaternion: expected 4 components, got {len(comps)}")
        _check_finite("rotate_quaternion", *comps)
        if not any(comps):
            raise TransformError("rotate_quaternion: zero quaternion")
    x, y, z, w = comps
    rows = quaternion_rows(x, y, z, w)
    mtype = _matrix_type(x, y, z, w)
    fwd = _from_rows(mtype, [r + [0] for r in rows] + [[0, 0, 0, 1]])
    inv = _from_rows(mtype, [[rows[j][i] for j in range(3)] + [0] for i in range(3)] + [[0, 0, 0, 1]])
    return Transform(fwd, inv)


def quaternion_rows(x: Any, y: Any, z: Any, w: Any) -> list[list[Any]]:
    """Rows of the rotation matrix of q / |q| for q = (x, y, z, w): numbers, NumPy or
    Dr.Jit arrays (every product carries 2 / |q|^2)."""
    k = 2.0 / (x * x + y * y + z * z + w * w)
    return [[1 - k * (y * y + z * z), k * (x * y - z * w), k * (x * z + y * w)],
            [k * (x * y + z * w), 1 - k * (x * x + z * z), k * (y * z - x * w)],
            [k * (x * z - y * w), k * (y * z + x * w), 1 - k * (x * x + y * y)]]


def quaternion_product(a: Sequence[Any], b: Sequence[Any]) -> tuple:
    """Hamilton product a b of quaternions given as components (x, y, z, w) (numbers, NumPy
    or Dr.Jit arrays): the rotation b, then a. Returns the components (x, y, z, w)."""
    ax, ay, az, aw = a
    bx, by, bz, bw = b
    return (aw * bx + bw * ax + ay * bz - az * by, aw * by + bw * ay + az * bx - ax * bz,
            aw * bz + bw * az + ax * by - ay * bx, aw * bw - ax * bx - ay * by - az * bz)


def quaternion_from_rotation(r: np.ndarray) -> np.ndarray:
    """Unit quaternions (..., 4) as (x, y, z, w) with w >= 0 of rotation matrices (..., 3, 3).

    Shepperd's method: the largest of the four squared components is taken
    from the trace, the others from off-diagonal sums, so no division by a
    small number.
    """
    r = np.asarray(r, np.float64)
    m00, m11, m22 = r[..., 0, 0], r[..., 1, 1], r[..., 2, 2]
    squares = np.stack([1 + m00 - m11 - m22, 1 - m00 + m11 - m22,
                        1 - m00 - m11 + m22, 1 + m00 + m11 + m22], axis=-1)
    big = np.argmax(squares, axis=-1)
    s = 2.0 * np.sqrt(np.take_along_axis(squares, big[..., None], -1)[..., 0])
    # Candidate quaternions, one per choice of the largest component.
    sums = {"xy": r[..., 0, 1] + r[..., 1, 0], "xz": r[..., 0, 2] + r[..., 2, 0],
            "yz": r[..., 1, 2] + r[..., 2, 1], "x": r[..., 2, 1] - r[..., 1, 2],
            "y": r[..., 0, 2] - r[..., 2, 0], "z": r[..., 1, 0] - r[..., 0, 1]}
    cand = np.stack([
        np.stack([s / 4, sums["xy"] / s, sums["xz"] / s, sums["x"] / s], -1),
        np.stack([sums["xy"] / s, s / 4, sums["yz"] / s, sums["y"] / s], -1),
        np.stack([sums["xz"] / s, sums["yz"] / s, s / 4, sums["z"] / s], -1),
        np.stack([sums["x"] / s, sums["y"] / s, sums["z"] / s, s / 4], -1)], axis=-2)
    q = np.take_along_axis(cand, big[..., None, None], -2)[..., 0, :]
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    return np.where(q[..., 3:4] < 0, -q, q)


def decompose(m: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Split affine matrices (..., 4, 4) into translation, rotation, scale and shear.

    ``m = translate(t) @ rotate_quaternion(q) @ scale(s) @ H`` with ``H`` unit
    upper triangular (the shear; the identity for any rotate/scale chain
    without shear). From the QR factorisation ``A = Q U`` with U's diagonal
    made positive; a reflection (det A < 0) goes into a negative z scale so
    that Q is a proper rotation.

    Returns ``(t (..., 3), q (..., 4), s (..., 3), H (..., 3, 3))``, float64.
    """
    m = np.asarray(m, np.float64)
    q_mat, u = np.linalg.qr(m[..., :3, :3])
    signs = np.where(np.diagonal(u, axis1=-2, axis2=-1) < 0, -1.0, 1.0)
    q_mat, u = q_mat * signs[..., None, :], u * signs[..., :, None]
    # A reflection flips the last column of Q and the last row of U.
    flip = np.where(np.linalg.det(q_mat) < 0, -1.0, 1.0)
    q_mat[..., :, 2] *= flip[..., None]
    u[..., 2, :] *= flip[..., None]
    s = np.diagonal(u, axis1=-2, axis2=-1).copy()
    shear = u / s[..., :, None]
    return m[..., :3, 3].copy(), quaternion_from_rotation(q_mat), s, shear


_REFLECT_AXES = {"x": 0, "y": 1, "z": 2}


def reflect(axis: str) -> Transform:
    """Reflection across the plane perpendicular to ``axis`` ('x', 'y' or 'z').

    Lecture matrices R_x, R_y, R_z (one diagonal entry -1); self-inverse.
    """
    if not isinstance(axis, str) or axis not in _REFLECT_AXES:
        raise TransformError(f"reflect: axis must be 'x', 'y' or 'z', got {axis!r}")
    diag = [1.0, 1.0, 1.0]
    diag[_REFLECT_AXES[axis]] = -1.0
    m = _from_rows(ds.Matrix4f64, [[diag[0], 0, 0, 0], [0, diag[1], 0, 0], [0, 0, diag[2], 0], [0, 0, 0, 1]])
    return Transform(m, m)


def look_at(origin: Any, target: Any, up: Any) -> Transform:
    """Camera-to-world frame at ``origin`` looking at ``target`` (+z forward), as Mitsuba.

    Columns: x = normalize(up x z), y = z x x, z = normalize(target - origin).
    The inverse is the transposed rotation with the translation undone.
    """
    o, t, u = (_vec3(v, name) for v, name in ((origin, "look_at origin"),
                                               (target, "look_at target"), (up, "look_at up")))
    _check_finite("look_at", *o, *t, *u)
    if any(_is_jit(v) for v in (o, t, u)):
        array3 = Array3f
    else:
        array3 = ds.Array3f64
    o, t, u = array3(*o), array3(*t), array3(*u)
    forward = t - o
    if not dr.is_jit_v(forward) and dr.norm(forward) == 0:
        raise TransformError(f"look_at: origin and target coincide at {tuple(o)}")
    z = dr.normalize(forward)
    left = dr.cross(u, z)
    if not dr.is_jit_v(left) and dr.norm(left) <= 1e-12:
        raise TransformError(f"look_at: up {tuple(u)} is parallel to the viewing direction")
    x = dr.normalize(left)
    y = dr.cross(z, x)
    mtype = _matrix_type(o.x, t.x, u.x)
    fwd = _from_rows(mtype, [[x[0], y[0], z[0], o[0]], [x[1], y[1], z[1], o[1]],
                             [x[2], y[2], z[2], o[2]], [0, 0, 0, 1]])
    back = [-(x[0] * o[0] + x[1] * o[1] + x[2] * o[2]),
            -(y[0] * o[0] + y[1] * o[1] + y[2] * o[2]),
            -(z[0] * o[0] + z[1] * o[1] + z[2] * o[2])]
    inv = _from_rows(mtype, [[x[0], x[1], x[2], back[0]], [y[0], y[1], y[2], back[1]],
                             [z[0], z[1], z[2], back[2]], [0, 0, 0, 1]])
    return Transform(fwd, inv)


#: Relative tolerance of :func:`is_similarity`: transforms stored in float32 (or written with
#: six digits) keep their Gram matrix's off-diagonal entries within about 1e-7 of its scale.
SIMILARITY_TOLERANCE = 1e-5


def is_similarity(m: np.ndarray) -> bool:
    """Whether a 4x4 (or 3x3) matrix's linear part L is a rotation or reflection times a
    uniform scale: L^T L = s^2 I within SIMILARITY_TOLERANCE of s^2."""
    linear = np.asarray(m, np.float64)[:3, :3]
    gram = linear.T @ linear
    scale = np.trace(gram) / 3.0
    return bool(np.abs(gram - scale * np.eye(3)).max() <= SIMILARITY_TOLERANCE * scale)


def require_rigid(transform: Transform, what: str) -> None:
    """Refuse a frame ``what`` (a camera's or spot light's ``to_world``) that scales or shears."""
    linear = np.asarray(transform.matrix, np.float64)[:3, :3]
    if not np.allclose(linear.T @ linear, np.eye(3), atol=1e-6):
        raise TransformError(f"{what} must be rigid (rotations, reflections and translations only; "
                             "no scale or shear)")


def check_affine_matrix(m: np.ndarray, name: str = "matrix") -> None:
    """Reject non-finite, projective (bottom row != 0 0 0 1), singular (rank below 3 in
    float64) or ill-conditioned (:data:`MAX_DETERMINANT_SENSITIVITY`) 4x4 matrices.

    ``m`` is (4, 4) or (N, 4, 4); the error names the first offending matrix.
    """
    _checked_linear_inverse(m, name)


def checked_affine_inverse(m: np.ndarray, name: str = "matrix") -> np.ndarray:
    """:func:`affine_inverse` of matrices that pass :func:`check_affine_matrix` (which raises
    otherwise), their linear parts inverted once for both."""
    arr = np.asarray(m, dtype=np.float64)
    return _assembled_inverse(arr, _checked_linear_inverse(arr, name))


def _checked_linear_inverse(m: np.ndarray, name: str) -> np.ndarray:
    """The inverse linear parts of matrices that pass :func:`check_affine_matrix`."""
    arr = np.asarray(m, dtype=np.float64)
    batch = arr.reshape(-1, 4, 4)
    bad = ~np.isfinite(batch).all(axis=(1, 2))
    if bad.any():
        raise TransformError(f"{name}{_where(bad, arr)} has non-finite entries")
    bad = np.any(batch[:, 3] != np.array([0.0, 0.0, 0.0, 1.0]), axis=1)
    if bad.any():
        i = int(np.argmax(bad))
        raise TransformError(f"{name}{_where(bad, arr)} is not affine: bottom row "
                             f"{batch[i, 3].tolist()} must be [0, 0, 0, 1]")
    linear = batch[:, :3, :3]
    det = np.linalg.det(linear)
    invertible = det != 0
    if invertible.all():
        inverse = np.linalg.inv(linear)
    else:
        inverse = np.full_like(linear, np.nan)
        inverse[invertible] = np.linalg.inv(linear[invertible])
    sensitivity = np.full(len(batch), np.inf)
    sensitivity[invertible] = determinant_sensitivity(linear[invertible], inverse[invertible])
    bad = ~(sensitivity <= MAX_DETERMINANT_SENSITIVITY)
    if bad.any():
        i = int(np.argmax(bad))
        sigma = np.linalg.svd(linear[i], compute_uv=False)
        if det[i] == 0 or sigma[2] <= 3 * np.finfo(np.float64).eps * sigma[0]:
            raise TransformError(f"{name}{_where(bad, arr)} is singular (determinant "
                                 f"{det[i]:.3g}); it cannot be inverted")
        raise TransformError(
            f"{name}{_where(bad, arr)} is ill-conditioned (condition number "
            f"{sigma[0] / sigma[2]:.3g}): its axes nearly collapse onto each other, so "
            f"float32 storage would change its determinant by up to "
            f"{100 * 2.0 ** -24 * sensitivity[i]:.2g} % (at most 1 % is accepted)")
    bad, message = float32_misfit(batch, inverse)
    if bad.any():
        raise TransformError(f"{name}{_where(bad, arr)} {message}")
    return inverse.reshape(arr.shape[:-2] + (3, 3))


def float32_misfit(matrices: np.ndarray, inverse_linear: np.ndarray) -> tuple[np.ndarray, str]:
    """Which of the affine (N, 4, 4) ``matrices`` (their linear parts' inverses given) float32
    cannot hold: an entry, or an entry of the inverse, at or past float32's largest number (a
    scale below its smallest normal number has an infinite float32 inverse). Returns the mask
    and what the first one overflows, as the end of a sentence."""
    largest = np.finfo(np.float32).max
    for what, values in (("entries", matrices[:, :3, :]), ("inverse's entries", inverse_linear)):
        # (A NaN entry, left by an overflow in a composition, makes the magnitude NaN.)
        magnitude = np.abs(values).max(axis=(1, 2))
        bad = ~(magnitude < largest)
        if bad.any():
            reached = magnitude[np.argmax(bad)]
            text = "overflow to NaN" if np.isnan(reached) else f"reach {reached:.3g}"
            return bad, f"does not fit in float32: its {what} {text} (float32 stops at {largest:.3g})"
    return np.zeros(len(matrices), bool), ""


def determinant_sensitivity(linear: np.ndarray, inverse: np.ndarray | None = None) -> np.ndarray:
    """sum_ij |A_ij (A^-1)_ji| of invertible (N, 3, 3) linear parts (``inverse``: their
    inverses, when known): the first-order bound on |d det / det| per unit relative change of
    every entry (d det = det tr(A^-1 dA)). 3 for a rotation; unchanged by scaling rows or
    columns."""
    inverse = np.linalg.inv(linear) if inverse is None else inverse
    return np.abs(linear * np.swapaxes(inverse, -1, -2)).sum(axis=(-1, -2))


def _where(bad: np.ndarray, arr: np.ndarray) -> str:
    return f" #{int(np.argmax(bad))}" if arr.ndim == 3 else ""


def affine_inverse(m: np.ndarray) -> np.ndarray:
    """Inverse of affine matrices (4, 4) or (N, 4, 4) in float64: [A^-1, -A^-1 b]."""
    arr = np.asarray(m, dtype=np.float64)
    return _assembled_inverse(arr, np.linalg.inv(arr[..., :3, :3]))


def _assembled_inverse(arr: np.ndarray, a_inv: np.ndarray) -> np.ndarray:
    """[A^-1, -A^-1 b] of affine matrices ``arr`` from their inverse linear parts."""
    out = np.zeros_like(arr)
    out[..., :3, :3] = a_inv
    out[..., :3, 3] = -np.einsum("...ij,...j->...i", a_inv, arr[..., :3, 3])
    out[..., 3, 3] = 1.0
    return out


def from_matrix(m: Any, name: str = "matrix") -> Transform:
    """A transform from a raw 4x4 affine matrix, inverted once.

    Args:
        m: nested lists / NumPy (4, 4) (a scalar float64 transform), or a
           backend ``Matrix4f`` (per lane; inverted with ``dr.rcp`` so that
           gradients reach the entries through the inverse too).
        name: how errors refer to the matrix (e.g. the instance id).

    Raises:
        TransformError: non-finite, projective or singular input.
    """
    if dr.is_jit_v(m):
        check_affine_matrix(_matrix_to_numpy(dr.detach(m)), name)
        return Transform(m, dr.rcp(m))
    arr = matrix_array(m, name)
    inv = checked_affine_inverse(arr, name)
    return Transform(ds.Matrix4f64(arr), ds.Matrix4f64(inv))


def matrix_array(m: Any, name: str = "matrix") -> np.ndarray:
    """A 4x4 matrix (nested lists or NumPy) as a float64 (4, 4) array, unchecked otherwise.

    Raises:
        TransformError: ``m`` is not 4x4 numbers.
    """
    try:
        arr = np.asarray(m, dtype=np.float64)
    except (TypeError, ValueError, OverflowError):
        raise TransformError(f"{name}: expected a 4x4 matrix of numbers, got {m!r}") from None
    if arr.shape != (4, 4):
        raise TransformError(f"{name}: expected a 4x4 matrix, got shape {arr.shape}")
    return arr


def matrices_to_lanes(m: np.ndarray) -> Matrix4f:
    """(N, 4, 4) NumPy matrices as one per-lane float32 ``Matrix4f``."""
    return Matrix4f(np.ascontiguousarray(np.moveaxis(np.asarray(m, dtype=np.float32), 0, -1)))


# -- per-lane row maps --------------------------------------------------------------------------
# Affine maps given as three float4 row packets (row i of a 3x3 matrix, then the translation
# b_i), one per lane: the form in which kernels gather an instance's transform. The
# instance table stores its inverse rows (A^-1 row i, b_i) and forward rows (A row i, b_i).


def world_point(rows, p_obj: Array3f) -> Array3f:
    """Map an object-space point to world space: ``A p + b``, the translation added last.

    Adding b last keeps the full relative precision of the small term
    ``A p`` until the one rounding that the world coordinate needs anyway
    (pbrt-v4 transforms points this way).
    """
    return type(p_obj)(*[dr.fma(r.z, p_obj.z, dr.fma(r.y, p_obj.y, r.x * p_obj.x)) + r.w
                         for r in rows])


def world_vector(rows, v_obj: Array3f) -> Array3f:
    """Map an object-space vector to world space: ``A v`` (no translation)."""
    return type(v_obj)(*[dr.fma(r.z, v_obj.z, dr.fma(r.y, v_obj.y, r.x * v_obj.x))
                         for r in rows])


def object_point(rows, p: Array3f) -> Array3f:
    """Map a world point into object space with inverse rows: ``A^-1 (p - b)``.

    The subtraction comes first: it is exact when p lies near the instance (Sterbenz),
    so points near instances far from the world origin keep full relative precision.
    """
    rel = type(p)(p.x - rows[0].w, p.y - rows[1].w, p.z - rows[2].w)
    return world_vector(rows, rel)


def object_ray(rows, o: Array3f, d: Array3f) -> tuple[Array3f, Array3f]:
    """Transform the ray into object space: origin with w=1 (:func:`object_point`),
    direction with w=0. The direction is not renormalized, so t is the same number in
    both spaces."""
    return object_point(rows, o), world_vector(rows, d)


def transposed_vector(rows, w: Array3f) -> Array3f:
    """``A^T w`` for the linear part A of ``rows``: with inverse rows, the inverse transpose
    that maps normals (and gradients) from object to world space; with forward rows, the map
    of a world gradient into object space."""
    r0, r1, r2 = rows
    vector = type(w)
    n = vector(r0.x, r0.y, r0.z) * w.x
    n = dr.fma(vector(r1.x, r1.y, r1.z), w.y, n)
    return dr.fma(vector(r2.x, r2.y, r2.z), w.z, n)


def world_normal(rows, n_obj: Array3f) -> Array3f:
    """Transform an object-space normal by the inverse transpose, then normalize."""
    n = transposed_vector(rows, n_obj)
    # Correctly rounded sqrt and division (dr.normalize's rsqrt approximation costs ~1 ulp).
    return n / dr.sqrt(dr.squared_norm(n))
