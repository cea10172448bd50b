"""Skin against bone during an equilibrium (paper sec 6.1 and beyond): the skin is kept out of the
cranium and of the mandible where the jaw put it; a point at an opening of the bone that no push gets
out gives up part of its displacement (the relaxation of folded triangles: unfold.py)."""

from __future__ import annotations

import dataclasses

import numpy as np
from scipy.spatial import cKDTree

from ..mesh import geometry
from ..mesh.winding import FastWinding
from ..tol import TINY
from .recall import closest_on_bone

CONTACT_ROUNDS = 4                    # pushes per contact step (a point at a bone opening may need more)
OPENING_REACH = 0.01                  # bone faces this close to a hole of the bone are 'by an opening', m
RETRACT_STEPS = 8                     # bisection steps of the last guard against penetration
NON_PENETRATION = 0.001               # skin stays at least this far outside the bone, m
JAW_SLACK = 0.002                     # the bone's winding grid is rebuilt once the jaw moved this far, m


class ContactMixin:
    """SkinModel's contact with the bone (its fields n, rest, bone, bone_dist, free, clearance,
    adjacency, on_mandible, tris and folds; the jaw from JawMixin)."""

    def _bone_gap(self, pts, outward, rot, t, known, idx=None):
        """Signed gap (k,) of skin points (k,3) above the bone with the mandible at (rot, t), the
        unit direction (k,3) that leads out, (k,) bools at an opening (odd) and inside, and how far
        each point may move and keep its side (k,), signed like the gap, NaN where `known` gave the
        side: metres. `known` (k,) is +1/-1 where the side is already known, 0 where not; `idx` (k,)
        the points' skin vertices, if they are (their closest points on the bone are then recall's).

        Inside is a winding number over 1/2 (it sees the bone's openings right); it is computed
        only where the nearest face leaves a doubt, or by a hole in the bone (there the winding
        number's 1/2 level spans the hole, off the bone). A point in front of its nearest face that
        is inside sits at an opening: its way out is `outward`, its gap counts as 0."""
        (_, n_cr, open_cr), (_, n_md, open_md), *_ = self.bone
        local = self._jaw_local(pts, rot, t)
        (c_cr, f_cr, d_cr), (c_md, f_md, d_md) = closest_on_bone(self, pts, local, idx)
        use_md = d_md < d_cr
        dist = np.minimum(d_md, d_cr)
        closest = np.where(use_md[:, None], self.on_jaw(c_md, rot, t), c_cr)
        away = (pts - closest) / np.maximum(dist, TINY)[:, None]
        side = np.where(use_md, np.einsum("ij,ij->i", local - c_md, n_md[f_md]),
                        np.einsum("ij,ij->i", pts - c_cr, n_cr[f_cr]))
        face_out = side >= 0.999 * dist
        by_opening = open_cr[f_cr] | open_md[f_md]
        inside = known < 0
        keeps = np.where(known == 0, dist, np.nan)              # a plain face answer holds within the gap
        ask = (~face_out | by_opening | (dist < 2 * NON_PENETRATION)) & (known == 0)
        if ask.any():
            w = self._winding(pts[ask], rot, t)
            inside[ask] = w > 0.5
            # w is harmonic off the bone and within [-1/4, 5/4]: |grad w| <= 3 * 3/4 / dist, so w
            # stays on its side of 1/2 while the point moves less than this
            keeps[ask] = dist[ask] * -np.expm1(-np.abs(w - 0.5) / 2.25)
        odd = inside & face_out
        gap = np.where(inside, np.where(odd, 0.0, -dist), dist)
        way_out = np.where(odd[:, None], outward, np.where(inside[:, None], -away, away))
        return gap, way_out, odd, inside, np.where(inside, -keeps, keeps)

    def _winding(self, pts, rot, t):
        """Winding number (k,) of skin points (k,3) in the bone (cranium, mandible at (rot, t))."""
        _, _, v_cr, v_md, bone_t = self.bone
        # exact fast winding numbers (core/mesh/winding.py, the brute force's up to rounding), the
        # bone closed once per model and refit when the jaw moved (the same jaw: the same bone, as is)
        fast, made_for, jaw = (self.__dict__.get(k) for k in ("_bone_winding", "_bone_winding_tris", "_bone_jaw"))
        if fast is None or made_for is not bone_t:
            fast = FastWinding(np.vstack([v_cr, self.on_jaw(v_md, rot, t)]), bone_t, slack=JAW_SLACK)
            self.__dict__.update(_bone_winding=fast, _bone_winding_tris=bone_t)
        elif not (np.array_equal(jaw[0], rot) and np.array_equal(jaw[1], t)):
            fast.refit(np.vstack([v_cr, self.on_jaw(v_md, rot, t)]))
        self.__dict__["_bone_jaw"] = (np.array(rot), np.array(t))
        return fast(pts)

    def _inside(self, pts, rot, t):
        """Whether skin points (k,3) are inside the bone (cranium and the mandible at (rot, t))."""
        return self._winding(pts, rot, t) > 0.5

    def _keep_out_of_bone(self, x, contact, only=None):
        """Skin x (n,3) pushed out to the clearance above the (moved) bone, metres: a few rounds of
        pushes along the way out, each shared with the neighbours so it shears no triangle. `only`
        (n,) bool limits the look to vertices that moved since the last look."""
        rot, t = contact.jaw
        for _ in range(CONTACT_ROUNDS):
            near = self._near_bone(x, contact, only)
            if not len(near):
                break
            gap, way_out, odd, _, keeps = self._bone_gap(x[near], contact.outward[near], rot, t,
                                                         contact.known_side(x, near), near)
            fresh = ~np.isnan(keeps)
            contact.sided_at[near[fresh]], contact.sided_keep[near[fresh]] = x[near[fresh]], keeps[fresh]
            contact.normal[near] = way_out
            deficit = np.zeros(self.n)
            deficit[near] = np.maximum(self.clearance[near] - gap, 0.0)
            for _ in range(3):          # neighbours share part of a push, so it shears no triangle
                deficit = np.maximum(deficit, 0.6 * (self.adjacency @ deficit)) * self.free
            push = deficit[:, None] * contact.normal
            if contact.symmetric:           # a symmetric state stays symmetric (Contact.symmetric)
                push = 0.5 * (push + push[self.mirror] * [-1.0, 1.0, 1.0])
            x = x + push
            if not odd.any():
                break
        return x

    def _near_bone(self, x, contact, only=None):
        """Indices of free skin vertices at x (n,3) that may be within their clearance of the bone:
        the rest distance to each bone, less how far the vertex moved relative to that bone, bounds
        its distance now (distance is 1-Lipschitz)."""
        rot, t = contact.jaw
        rest = self.rest[: self.n]
        local = self._jaw_local(x, rot, t)
        bound = np.minimum(self.bone_dist[:, 0] - np.linalg.norm(x - rest, axis=1),
                           self.bone_dist[:, 1] - np.linalg.norm(local - rest, axis=1))
        near = self.free & (bound < self.clearance)
        return np.flatnonzero(near if only is None else near & only)

    def _retract_from_bone(self, x, contact, only=None):
        """Skin x (n,3) with each vertex still inside the bone drawn back toward its rest place on
        its bone (moved with the mandible) until it is out by its clearance, metres.

        The last guard, for a point at a bone opening that no push along a normal gets out (the
        lower lip's inner roll behind the maxilla's rim): it gives up part of its displacement.
        `only` (n,) bool limits the look to vertices that moved since the last look."""
        rot, t = contact.jaw
        near = self._near_bone(x, contact, only)
        if not len(near):
            return x
        inside = self._bone_gap(x[near], contact.outward[near], rot, t, contact.known_side(x, near), near)[3]
        bad = near[inside]
        if not len(bad):
            return x
        rest = self.rest[: self.n]
        home = np.where(self.on_mandible[:, None], self.on_jaw(rest, rot, t), rest)
        home[bad] = np.where(self._inside(home[bad], rot, t)[:, None], rest[bad], home[bad])
        lo, hi = np.zeros(len(bad)), np.ones(len(bad))                 # fraction of the way home
        for _ in range(RETRACT_STEPS):
            mid = 0.5 * (lo + hi)
            ins = self._inside(x[bad] + mid[:, None] * (home[bad] - x[bad]), rot, t)
            lo, hi = np.where(ins, mid, lo), np.where(ins, hi, mid)
        span = np.maximum(np.linalg.norm(home[bad] - x[bad], axis=1), TINY)
        frac = np.zeros(self.n)
        frac[bad] = np.minimum(hi + self.clearance[bad] / span, 1.0)
        for _ in range(3):                     # neighbours give up part of theirs too
            frac = np.maximum(frac, 0.6 * (self.adjacency @ frac)) * self.free
        y = x + frac[:, None] * (home - x)
        # ... unless their way home crosses the bone (skin lying on a curved bone; Fran's lip corner
        # put 2 vertices 0.1 mm from the cranium 1 mm into it): those stay where they were, outside
        given = frac > 0
        given[bad] = False
        spread = np.flatnonzero(given)
        if len(spread):
            crossed = spread[self._inside(y[spread], rot, t)]
            y[crossed] = x[crossed]
        return y

    def _grown(self, mask, rings):
        """The skin vertices (n,) bools within `rings` edge rings of `mask`."""
        for _ in range(int(rings)):
            mask = mask | ((self.adjacency @ mask.astype(float)) > 0)
        return mask

@dataclasses.dataclass
class Contact:
    """Skin-bone contact during one equilibrium: per skin vertex its outward rest bone direction
    (moved with the mandible), the mandible's (rot, t), the direction a push moves it (out of the
    bone), and where its side of the bone was last decided with how far it may move and keep it,
    signed: + outside, - inside (0: never). symmetric: the skin is the template's mirror image of itself
    (SkinModel._symmetric), so every push is made symmetric too."""
    outward: np.ndarray
    jaw: tuple
    symmetric: bool = False
    normal: np.ndarray = None
    sided_at: np.ndarray = None
    sided_keep: np.ndarray = None

    def __post_init__(self):
        self.normal = self.outward.copy()
        self.sided_at = np.zeros_like(self.outward)
        self.sided_keep = np.zeros(len(self.outward))

    def known_side(self, x, idx):
        """+1 / -1 where vertices idx of skin x (n,3) are known outside / inside the bone, 0 where
        not: a point keeps its side while it moves less than its distance to the bone."""
        moved = np.linalg.norm(x[idx] - self.sided_at[idx], axis=1)
        old = self.sided_keep[idx]
        return np.where(moved < np.abs(old), np.sign(old), 0.0)


def near_opening(verts, tris):
    """(f,) bool: faces with a vertex within OPENING_REACH of the mesh's open boundary (metres)."""
    rim = np.flatnonzero(geometry.boundary_vertices(tris, len(verts)))
    if not len(rim):
        return np.zeros(len(tris), bool)
    d, _ = cKDTree(np.asarray(verts)[rim]).query(np.asarray(verts))
    return (d < OPENING_REACH)[tris].any(axis=1)
