"""Compensator geometry from markers followed over a joint-2 sweep (Klimchik §IV).

The gravity compensator of a heavy robot is a planar mechanism of three pivots
(K Fig. 2, 4): ``P2`` on the joint-2 axis, ``P1`` where the compensator rod
attaches to link 2 and ``P0`` where the cylinder attaches to link 1. Its
geometry is ``L = |P2 P1|`` and the vector ``a = P2 - P0`` (``a_x``, ``a_y``).

A tracker follows a marker at ``P1`` and two or more markers ``P0i`` on the
cylinder while joint 2 moves through known angles ``q2``:

* ``P1`` turns about ``P2`` by exactly ``q2``: its points fit an arc with the
  angle known, ``p_i = mu R u_i + t``, ``u_i = (cos q_i, sin q_i)`` (K10). ``R``
  comes from the SVD of ``sum u_i p_i^T`` (orthogonal Procrustes, K17-19); it
  may be a reflection, because the marker turns against ``q2`` when the
  tracker's axis points the other way. ``mu`` is ``L``, ``t`` is ``P2``.
* The cylinder turns about ``P0`` by an angle nobody measures, so its markers
  fit concentric arcs with a common centre (K20-29): a linear least-squares
  problem in the centre.

The model is planar. Points are first projected on the plane of the arcs (its
normal is the direction the centred point sets do not spread in); ``a_x`` and
``a_y`` are the components of ``a`` along the two measurement axes that lie
nearest that plane (x and y for a tracker whose z is the joint-2 axis, as in
Klimchik's setup), orthogonalised within it.

Standard deviations come from the residuals: each fit's residual variance
(residual sum of squares over its degrees of freedom) times ``(J^T J)^-1`` of
its geometric residuals at the solution. The two fits use different markers,
so their errors are independent and add in ``a = P2 - P0``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np

from elastocal.errors import InputError

#: parameter names of the geometry result, in the order of ``values``/``covariance``
GEOMETRY_PARAMS = ("L", "a_x", "a_y")
AXIS_NAMES = ("x", "y", "z")


@dataclass(frozen=True, eq=False)
class ArcFit:
    """A circle arc fitted with its angles known (K10-19), in plane coordinates."""

    radius: float             # mu [m]
    center: np.ndarray        # (2,) t [m]
    rotation: np.ndarray      # (2, 2) R, orthogonal; det -1 when reflected
    residuals: np.ndarray     # (m, 2) p_i - (mu R u_i + t) [m]
    covariance: np.ndarray    # (4, 4) of (radius, phase, center x, center y); NaN without redundancy

    @property
    def reflected(self) -> bool:
        """True when the points turn against the angle (``det R = -1``)."""
        return bool(np.linalg.det(self.rotation) < 0.0)

    @property
    def rms(self) -> float:
        return float(np.sqrt(np.mean(np.sum(self.residuals ** 2, axis=1))))


@dataclass(frozen=True, eq=False)
class ConcentricFit:
    """Concentric circle arcs with one common centre (K20-29), in plane coordinates."""

    center: np.ndarray        # (2,) [m]
    radii: np.ndarray         # (k,) R_j [m]
    residuals: np.ndarray     # (N,) radial residuals |p - c| - R_j of every point [m]
    covariance: np.ndarray    # (2 + k, 2 + k) of (center x, center y, R_1..R_k)

    @property
    def rms(self) -> float:
        return float(np.sqrt(np.mean(self.residuals ** 2)))


@dataclass(frozen=True, eq=False)
class PlaneFrame:
    """The plane of the arcs in measurement coordinates."""

    origin: np.ndarray        # (3,) centroid of the points [m]
    axes: np.ndarray          # (3, 3) rows: in-plane x', in-plane y', normal n' (right-handed)
    axis_names: tuple[str, str]  # measurement axes x', y' are closest to, e.g. ("x", "y")

    def to_plane(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(in-plane coordinates (m, 2), out-of-plane offsets (m,)) of points (m, 3)."""
        rel = np.asarray(points, dtype=float) - self.origin
        return rel @ self.axes[:2].T, rel @ self.axes[2]

    def to_space(self, xy: np.ndarray, normal_offset: float = 0.0) -> np.ndarray:
        return self.origin + np.asarray(xy) @ self.axes[:2] + normal_offset * self.axes[2]


@dataclass(frozen=True, eq=False)
class CompensatorGeometry:
    """Identified compensator geometry (K Table II) with its uncertainty."""

    values: np.ndarray        # (3,) L, a_x, a_y [m]
    covariance: np.ndarray    # (3, 3) [m^2]
    pivot: ArcFit             # arc of P1 about P2
    cylinder: ConcentricFit   # arcs of the cylinder markers about P0
    plane: PlaneFrame
    p2: np.ndarray            # (3,) centre of the P1 arc, measurement frame [m]
    p0: np.ndarray            # (3,) common centre of the cylinder arcs [m]
    out_of_plane: np.ndarray  # (N,) distance of every point from the plane [m]
    names: tuple[str, ...] = GEOMETRY_PARAMS

    @property
    def L(self) -> float:  # noqa: N802 - the paper's name
        return float(self.values[0])

    @property
    def a_x(self) -> float:
        return float(self.values[1])

    @property
    def a_y(self) -> float:
        return float(self.values[2])

    @property
    def a(self) -> float:
        """|P2 - P0| [m]."""
        return float(np.hypot(self.values[1], self.values[2]))

    @property
    def std(self) -> np.ndarray:
        return np.sqrt(np.diag(self.covariance))

    @property
    def residual_rms(self) -> float:
        """In-plane residual rms over every point of both fits [m]: the P1 arc's
        residual distances and the cylinder markers' radial residuals."""
        d = np.concatenate([np.linalg.norm(self.pivot.residuals, axis=1), self.cylinder.residuals])
        return float(np.sqrt(np.mean(d ** 2)))


# ------------------------------------------------------------------ fits
def _rotation2(phase: float, reflected: bool) -> np.ndarray:
    c, s = np.cos(phase), np.sin(phase)
    if reflected:
        return np.array([[c, s], [s, -c]])
    return np.array([[c, -s], [s, c]])


def fit_arc(points: np.ndarray, angles: np.ndarray) -> ArcFit:
    """Fit ``p_i = mu R u_i + t`` to planar points (m, 2) at known angles (m,) [rad].

    ``R`` is the orthogonal matrix (rotation or reflection) maximising
    ``trace(R sum u_i p_i^T)``: ``R = V U^T`` from the SVD ``sum u_i p_i^T = U S V^T``
    (K17-19). Needs at least 3 points at distinct angles.
    """
    p = np.asarray(points, dtype=float)
    q = np.asarray(angles, dtype=float).reshape(-1)
    if p.ndim != 2 or p.shape[1] != 2 or len(p) != len(q):
        raise ValueError("fit_arc: points must be (m, 2) and angles (m,)")
    u = np.column_stack([np.cos(q), np.sin(q)])
    u_hat = u - u.mean(axis=0)
    p_hat = p - p.mean(axis=0)
    if len(p) < 3 or np.linalg.matrix_rank(u_hat, tol=1e-9) < 2:
        raise InputError("an arc fit needs at least 3 points at distinct joint angles")
    left, _, right_t = np.linalg.svd(u_hat.T @ p_hat)
    rot = right_t.T @ left.T
    mu = float(np.sum(p_hat * (u_hat @ rot.T)) / np.sum(u_hat * u_hat))
    if mu < 0.0:  # a point reflection is an orthogonal R as well; keep the radius positive
        mu, rot = -mu, -rot
    t = p.mean(axis=0) - mu * rot @ u.mean(axis=0)
    residuals = p - (mu * (u @ rot.T) + t)
    reflected = bool(np.linalg.det(rot) < 0.0)
    phase = float(np.arctan2(rot[1, 0], rot[0, 0]))
    # Jacobian of the residuals with respect to (mu, phase, tx, ty)
    m = len(p)
    jac = np.zeros((2 * m, 4))
    d_rot = _rotation2(phase + np.pi / 2, reflected)  # dR/dphase
    jac[:, 0] = -(u @ rot.T).reshape(-1)
    jac[:, 1] = -(mu * (u @ d_rot.T)).reshape(-1)
    jac[0::2, 2] = -1.0
    jac[1::2, 3] = -1.0
    covariance = _covariance(jac, residuals.reshape(-1))
    return ArcFit(radius=mu, center=t, rotation=rot, residuals=residuals, covariance=covariance)


def fit_concentric_arcs(point_sets: Sequence[np.ndarray]) -> ConcentricFit:
    """Common centre of k planar point sets (each (m_j, 2)) lying on concentric circles.

    Minimises ``sum_j sum_i (R_j^2 - |p_i^j - c|^2)^2`` (K20): with ``R_j^2`` at its
    optimum (K21) this is linear in ``c`` (K22-24); in the plane it has a
    unique solution once the points of one set are not collinear.
    """
    sets = [np.asarray(s, dtype=float) for s in point_sets]
    if not sets or any(s.ndim != 2 or s.shape[1] != 2 for s in sets):
        raise ValueError("fit_concentric_arcs: point sets must be (m_j, 2)")
    if any(len(s) < 3 for s in sets):
        raise InputError("each cylinder marker needs at least 3 points for the concentric arc fit")
    a = np.zeros((2, 2))
    b = np.zeros(2)
    for s in sets:
        p_hat = s - s.mean(axis=0)
        sq = np.sum(s * s, axis=1)
        s_hat = sq - sq.mean()
        a += p_hat.T @ p_hat
        b += 0.5 * p_hat.T @ s_hat
    if np.linalg.cond(a) > 1e12:
        raise InputError("the cylinder markers do not move along arcs (their points are collinear)")
    center = np.linalg.solve(a, b)
    radii = np.array([np.sqrt(np.mean(np.sum((s - center) ** 2, axis=1))) for s in sets])
    residuals = np.concatenate([np.linalg.norm(s - center, axis=1) - r for s, r in zip(sets, radii)])
    k = len(sets)
    rows = []
    for j, s in enumerate(sets):
        d = s - center
        n = d / np.linalg.norm(d, axis=1, keepdims=True)
        block = np.zeros((len(s), 2 + k))
        block[:, :2] = -n
        block[:, 2 + j] = -1.0
        rows.append(block)
    covariance = _covariance(np.vstack(rows), residuals)
    return ConcentricFit(center=center, radii=radii, residuals=residuals, covariance=covariance)


def _covariance(jac: np.ndarray, residuals: np.ndarray) -> np.ndarray:
    """``s^2 (J^T J)^-1`` with ``s^2 = RSS / (n - p)``; NaN without redundancy."""
    n, p = jac.shape
    if n <= p:
        return np.full((p, p), np.nan)
    s2 = float(residuals @ residuals) / (n - p)
    return s2 * np.linalg.pinv(jac.T @ jac)


def arc_plane(point_sets: Sequence[np.ndarray]) -> PlaneFrame:
    """The plane the (m_j, 3) point sets move in.

    Its normal is the direction in which the point sets, each centred on its own
    mean, spread least. The in-plane axes follow the two measurement axes most
    nearly parallel to the plane (ties keep x before y before z).
    """
    sets = [np.asarray(s, dtype=float) for s in point_sets]
    centred = np.vstack([s - s.mean(axis=0) for s in sets])
    _, _, vt = np.linalg.svd(centred, full_matrices=True)
    normal = vt[2]
    order = np.argsort(np.abs(normal), kind="stable")
    first, second = sorted(order[:2].tolist())
    eye = np.eye(3)
    x_axis = eye[first] - normal * normal[first]
    x_axis /= np.linalg.norm(x_axis)
    y_axis = eye[second] - normal * normal[second] - x_axis * (eye[second] @ x_axis)
    y_axis /= np.linalg.norm(y_axis)
    axes = np.array([x_axis, y_axis, np.cross(x_axis, y_axis)])
    origin = np.vstack(sets).mean(axis=0)
    return PlaneFrame(origin=origin, axes=axes, axis_names=(AXIS_NAMES[first], AXIS_NAMES[second]))


def identify_compensator_geometry(q2: np.ndarray, pivot_xyz: np.ndarray,
                                  cylinder_xyz: Sequence[np.ndarray]) -> CompensatorGeometry:
    """Compensator geometry ``L, a_x, a_y`` from a joint-2 sweep (K §IV).

    ``q2`` (m,) [rad]: joint-2 angle at each reading of the pivot marker P1;
    ``pivot_xyz`` (m, 3) [m]: its positions; ``cylinder_xyz``: one (m_j, 3)
    array per marker on the compensator cylinder (two or more markers; their
    readings need not be paired with the angles).
    """
    q2 = np.asarray(q2, dtype=float).reshape(-1)
    pivot = np.asarray(pivot_xyz, dtype=float)
    cylinders = [np.asarray(c, dtype=float) for c in cylinder_xyz]
    if pivot.ndim != 2 or pivot.shape[1] != 3 or len(pivot) != len(q2):
        raise ValueError("pivot_xyz must be (m, 3) with one q2 per row")
    if any(c.ndim != 2 or c.shape[1] != 3 for c in cylinders):
        raise ValueError("cylinder_xyz: each marker's points must be (m_j, 3)")
    if not cylinders:
        raise InputError("the concentric arc fit needs at least one cylinder marker")
    for arr in (q2, pivot, *cylinders):
        if not np.all(np.isfinite(arr)):
            raise InputError("marker positions and joint angles must be finite")
    plane = arc_plane([pivot, *cylinders])
    pivot_2d, pivot_off = plane.to_plane(pivot)
    cyl_2d = [plane.to_plane(c) for c in cylinders]
    arc = fit_arc(pivot_2d, q2)
    conc = fit_concentric_arcs([c[0] for c in cyl_2d])
    a_vec = arc.center - conc.center
    values = np.array([arc.radius, a_vec[0], a_vec[1]])
    # covariance of (L, a_x, a_y): arc (mu, tx, ty) and the independent centre (cx, cy)
    cov = np.zeros((3, 3))
    arc_idx = [0, 2, 3]
    cov += arc.covariance[np.ix_(arc_idx, arc_idx)]
    cov[1:, 1:] += conc.covariance[:2, :2]
    p2 = plane.to_space(arc.center, float(np.mean(pivot_off)))
    p0 = plane.to_space(conc.center, float(np.mean(np.concatenate([c[1] for c in cyl_2d]))))
    out_of_plane = np.concatenate([pivot_off, *[c[1] for c in cyl_2d]])
    out_of_plane = out_of_plane - np.concatenate(
        [np.full(len(pivot_off), np.mean(pivot_off)), *[np.full(len(c[1]), np.mean(c[1])) for c in cyl_2d]])
    return CompensatorGeometry(values=values, covariance=cov, pivot=arc, cylinder=conc, plane=plane,
                               p2=p2, p0=p0, out_of_plane=out_of_plane)


def geometry_from_run_table(table, *, pivot: str, cylinder: Sequence[str], joint: int = 2) -> CompensatorGeometry:
    """:func:`identify_compensator_geometry` on a run table (docs/formats.md §3): the
    rows of marker ``pivot`` with their ``q<joint>``, and the rows of each
    ``cylinder`` marker."""
    def rows(name: str) -> np.ndarray:
        mask = table.marker == name
        if not np.any(mask):
            present = sorted(set(table.marker.tolist()) - {""})
            raise InputError(f"marker {name!r} does not appear in the table; it has "
                             f"{', '.join(present) or 'no markers'}", source=table.source, column="marker")
        if not np.all(np.isfinite(table.xyz[mask])):
            line = int(table.line[mask][np.flatnonzero(~np.all(np.isfinite(table.xyz[mask]), axis=1))[0]])
            raise InputError(f"marker {name} has no position", source=table.source, row=line, column="x")
        return mask

    if len(set(cylinder)) != len(cylinder) or pivot in cylinder:
        raise InputError("the pivot and cylinder markers must be distinct", argument="cylinder")
    pm = rows(pivot)
    masks = [rows(c) for c in cylinder]
    return identify_compensator_geometry(table.q[pm, joint - 1], table.xyz[pm], [table.xyz[m] for m in masks])
