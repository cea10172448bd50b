"""Folded skin triangles undone after an equilibrium (paper sec 6.1 and beyond): the displacement
round a fold relaxed, the fold's corners smoothed in place by a closed lid, a closing lid relaxed free
given back toward where the controls put it as far as nothing folds."""

from __future__ import annotations

import numpy as np

UNFOLD_STEPS = 80                     # most local relaxation steps against folded triangles
UNFOLD_RINGS = 8                      # rings relaxed around a fold: one more per step it stays folded, up
                                      # to this many; then the patch also gives back its displacement
UNFOLD_SMOOTH = 10                    # a fold's corners' positions first take this many steps to their
                                      # neighbours' mean, kept if no fold is left (a canthus's tiny
                                      # triangles; relaxed as displacement, the patch grew over the lid
                                      # margin and opened a blinking eye 3.6 mm)
UNFOLD_GIVE = 0.99                    # share of the displacement kept per Jacobi step, to the power of the
                                      # steps a fold has outlasted UNFOLD_RINGS (the rest shape has no fold)
GIVE_BACK_SHARES = (0.2, 0.4, 0.6, 0.8, 1.0)   # skin relaxed free goes back toward where the controls
                                      # put it in these steps (shares of the way), each vertex as far as
                                      # no triangle folds (a closing lid relaxed free went back up: a
                                      # blink left up to 74% of the eyeball seen at rest on scan-like heads)
GIVE_BACK_ROUNDS = 30                 # a step's vertices by a folded triangle are held back, at most this often


class UnfoldMixin:
    """SkinModel's relaxation of folded triangles (its fields n, rest, tris, folds, adjacency; the
    bone's contact from ContactMixin)."""

    def _unfold(self, x, contact, pinned=None, zone=None):
        """Relax the displacement around folded triangles (Jacobi steps toward the neighbours' mean).

        Springs that only resist stretch let tiny triangles (lip corners, lid margins) fold under
        concentrated pulls; a few local smoothing steps of the displacement field undo that. Only
        the skin around the triangles still folded is relaxed, one ring more per step a fold
        persists, up to UNFOLD_RINGS, after which the patch also gives back displacement
        (UNFOLD_GIVE). Relaxing the whole patch ever touched, grown every step, spread a last
        stubborn fold's relaxation over the whole face and flattened the key (a smile on a
        generated head to 0.4 of its size). Each step first smooths the folded triangles' corners'
        positions (UNFOLD_SMOOTH), kept if that leaves no fold; else the displacement is relaxed.
        `pinned` (n,) bools: skin held where it is (a closed lid's margin, controls.LID_PIN), unless a
        fold at it outlasts UNFOLD_RINGS steps (relaxed with the rest, the lid's margin opened again).
        `zone` (n,) bools: skin by a turned lid, where a smoothing in place that leaves fewer folds is
        kept (and the rest smoothed next step) instead of relaxing the displacement.
        """
        rest = self.rest[: self.n]
        age = np.zeros(self.n)
        changed = np.zeros(self.n, bool)          # skin the relaxation moved since its last full look
        flipped = _FoldWatch(self.folds, self.tris, x)
        for _ in range(UNFOLD_STEPS):
            bad = flipped(x)
            if not len(bad):
                if not changed.any():
                    break
                # the pushes and give-backs reach a few rings past the patch they looked at: one
                # look over all the skin the relaxation moved (Fran's lip corner left 2 vertices
                # 0.1 mm inside the cranium), then again round only if that look folded a triangle
                # (looked at again and again, the pushes need not settle: under numpy 2 Fran's
                # mouthSmileLeft spent its last 65 steps so, now and then folding a triangle and
                # relaxing it, and the last look folded a cheek triangle no step was left to see)
                before = x.copy()
                x = self._retract_from_bone(self._keep_out_of_bone(x, contact, changed), contact, changed)
                changed = (x != before).any(axis=1)
                if not len(flipped(x)):
                    break
                continue
            corners = np.unique(self.tris[bad])
            age[corners] += 1
            patch = np.zeros(self.n, bool)
            patch[corners] = True
            stuck = age[corners].max()
            patch = self._grown(patch, min(stuck, UNFOLD_RINGS))
            if pinned is not None:                 # a fold that outlasts the rings frees its pinned corners
                pinned[corners[age[corners] > UNFOLD_RINGS]] = False
            keep = UNFOLD_GIVE ** max(stuck - UNFOLD_RINGS, 0.0)
            before = x.copy()
            rows = self.adjacency[corners]         # the corners' rows: each the whole product's row, to the bit
            for _ in range(UNFOLD_SMOOTH):
                x[corners] = rows @ x
            if pinned is not None:
                x[pinned] = before[pinned]
            left = len(flipped(x))
            # by a closed lid a smoothing that leaves fewer folds is kept, the rest smoothed next step
            # (relaxing the displacement there pulls the lid back up; controls.LID_ZONE_RINGS)
            fewer = zone is not None and left < len(bad) and zone[corners].all()
            if left and not fewer:                 # not unfolded in place: relax the patch's displacement
                x = before.copy()
                rows = self.adjacency[patch]
                for _ in range(10):
                    x[patch] = rest[patch] + keep * (rows @ (x - rest))
                    if pinned is not None:
                        x[pinned] = before[pinned]
            else:
                patch = np.zeros(self.n, bool)
                patch[corners] = True
            moved = patch | (self.adjacency @ patch.astype(float) > 0)
            x = self._retract_from_bone(self._keep_out_of_bone(x, contact, moved), contact, moved)
            changed |= (x != before).any(axis=1)
        return x


    def _given_back(self, y, x, contact):
        """Fold-free skin y (n,3), relaxed from x, with each vertex the relaxation moved taken back
        toward x by GIVE_BACK_SHARES of the way, step by step, as far as no triangle folds with the
        skin kept out of the bone: at each step the corners of a triangle that would fold stay where
        the last step left them. Relaxed free, a closing lid whose held margin kept a fold went back
        up; given back, head 105's left blink shows 11% of the eyeball seen at rest, not 74%."""
        moved = (y != x).any(axis=1)
        z = y
        for share in GIVE_BACK_SHARES:
            step = z.copy()
            step[moved] = y[moved] + share * (x[moved] - y[moved])
            for _ in range(GIVE_BACK_ROUNDS):
                out = self._retract_from_bone(self._keep_out_of_bone(step, contact, moved), contact, moved)
                bad = self.flipped(out)
                if not len(bad):
                    z = out
                    break
                held = np.unique(self.tris[bad])
                step[held] = z[held]
        return z


class _FoldWatch:
    """The folded triangles (FoldCheck's answer, to the bit) of a skin that moves a few vertices at a
    time: only the triangles at a vertex that moved since the last look are tested again."""

    def __init__(self, folds, tris, x):
        self.folds, self.tris, self.x = folds, tris, x.copy()
        self.folded = np.zeros(len(tris), bool)
        self.folded[folds(x)] = True

    def __call__(self, x):
        moved = (x != self.x).any(axis=1)
        if moved.any():
            at = np.flatnonzero(moved[self.tris].any(axis=1))
            self.folded[at] = self.folds.among(x, at)
            self.x[moved] = x[moved]
        return np.flatnonzero(self.folded)
