"""The skeleton embedding's fallback for blob-like characters: the guess moved and scaled whole
(a similarity, no turn) so that the first joints of its widest pair of limbs sit at the bases of
the mesh's two protrusions farthest apart along that pair's side (a cartoon's arm stubs).

Used by :func:`dqskin.embedding.embed_skeleton` when its limb-by-limb embedding leaves more than
a third of the deforming joints outside the mesh, and kept when fewer are outside.
"""

import numpy as np

from .metrics import mesh_edges

__all__ = ["protrusion_fit"]

_STEP = 0.01  # section planes every this share of the mesh's height
_JUMP = 1.5  # a section this many times wider (up or across) than the one before: the limb ends
_BOTH = 1.2  # and the joint is where the section is this much wider than the limb's both ways
_MIN_REACH = 0.05  # no base nearer the extremity than this share of the height (its tip)


def protrusion_fit(P: np.ndarray, faces: np.ndarray, X: np.ndarray, tips: np.ndarray,
                   groups: list[list[int]], chains: list[list[int]], height: float
                   ) -> np.ndarray | None:
    """The guess's joints moved and scaled whole onto the mesh's widest pair of protrusions.

    Parameters
    ----------
    P : (V, 3) float64
        The mesh's points, Y up.
    faces : (T, 3) int
        Its triangles.
    X : (J, 3) float64
        Every joint of the guess, in the mesh's axes (any size and place).
    tips : (N, 3) float64
        The guess's leaf tips, in ``X``'s frame.
    groups : list of list of int
        Tip indices per limb.
    chains : list of list of int
        Each group's limb joints, parents first (the first one the limb's base: a shoulder,
        a hip, a cartoon's hand).
    height : float
        The mesh's height (along Y).

    Returns
    -------
    (J, 3) float64 or None
        ``s · X + t`` (``s > 0``), the first joints of the two limbs whose tips lie farthest
        apart horizontally at the bases of the mesh's two protrusions on their sides; None when
        there is no such pair or a base is not found.
    """
    best, pair = 0.0, None
    for g in range(len(groups)):
        for h in range(g + 1, len(groups)):
            if not chains[g] or not chains[h]:
                continue
            off = tips[groups[g]].mean(0) - tips[groups[h]].mean(0)
            off[1] = 0.0
            if np.linalg.norm(off) > best:
                best, pair = float(np.linalg.norm(off)), (g, h)
    if pair is None:
        return None
    a, b = chains[pair[0]][0], chains[pair[1]][0]
    side = X[a] - X[b]
    side[1] = 0.0
    if np.linalg.norm(side) <= 1e-9 * height:
        side = tips[groups[pair[0]]].mean(0) - tips[groups[pair[1]]].mean(0)
        side[1] = 0.0
    side /= np.linalg.norm(side)
    edges = mesh_edges(np.asarray(faces, np.int64).reshape(-1, 3))
    bases = [_base(P, edges, side, height), _base(P, edges, -side, height)]
    if bases[0] is None or bases[1] is None:
        return None
    span = float((X[a] - X[b]) @ side)
    if span <= 1e-9 * height:
        return None
    s = float((bases[0] - bases[1]) @ side) / span
    if s <= 0:
        return None
    t = 0.5 * (bases[0] + bases[1]) - s * 0.5 * (X[a] + X[b])
    return s * X + t


def _section(P: np.ndarray, edges: np.ndarray, axis: np.ndarray, d: float) -> np.ndarray:
    """The points where the mesh's edges cross the plane ``x·axis = d``."""
    u = P[edges[:, 0]] @ axis - d
    v = P[edges[:, 1]] @ axis - d
    m = u * v < 0
    w = u[m] / (u[m] - v[m])
    return P[edges[m, 0]] + w[:, None] * (P[edges[m, 1]] - P[edges[m, 0]])


def _base(P: np.ndarray, edges: np.ndarray, axis: np.ndarray, height: float
          ) -> np.ndarray | None:
    """(3,) the base of the mesh's protrusion farthest along ``axis`` (unit), by sections normal
    to ``axis`` from the extremity inwards: the limb ends at the first section wider (up or
    across) by ``_JUMP`` times than the one before; the base is the limb's last section's centre
    carried on to where the sections are ``_BOTH`` times the limb's width both up and across
    (inside the body, where the limb's joint sits); None when there is none within half the
    mesh's extent along ``axis``."""
    proj = P @ axis
    top, bottom = float(proj.max()), float(proj.min())
    step = _STEP * height
    e1 = np.array([0.0, 1.0, 0.0]) - axis[1] * axis  # the section's up and across
    e1 = e1 / np.linalg.norm(e1) if np.linalg.norm(e1) > 1e-6 else np.array([1.0, 0.0, 0.0])
    across = np.stack([e1, np.cross(axis, e1)], axis=1)
    last, limb = None, None
    k = 1
    while top - k * step > 0.5 * (top + bottom):
        q = _section(P, edges, axis, top - k * step)
        if len(q):
            width = np.ptp(q @ across, axis=0)
            if limb is None and last is not None and k * step > _MIN_REACH * height:
                if (width > _JUMP * last[0]).any():
                    limb = last  # the limb's last section: the body begins
            if limb is not None and (width > _BOTH * limb[0]).all():
                return limb[1] + ((top - k * step) - limb[1] @ axis) * axis
            if limb is None:
                last = (width, q.mean(0))
        k += 1
    return None
