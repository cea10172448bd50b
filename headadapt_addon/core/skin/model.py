"""Three-layer skin (paper sec 6.1) driven by muscles, jaw and lids, solved quasi-statically.

Layers: epidermis (the skin mesh), dermis and hypodermis below it along the inward normal, at
fractions of the local soft-tissue depth to the skull. Springs within each layer (along mesh
edges), between layers (vertical and diagonal) and from the hypodermis to the bone under it
(cranium fixed, mandible turning about the jaw pivot). The dermis is the most deformable layer.
Springs are linearised about the rest shape (energy sum k |(x_i - x_j) - (X_i - X_j)|^2), so the
equilibrium for any set of controls is one solve with the same sparse factorisation: fast and
stable, no time steps.

After the solve the skin is kept out of the bone (cranium, mandible where the jaw put it): points
that may be near it (a 1-Lipschitz bound on their distance) are pushed out along the way out, a
point at one of the bone's openings (judged by the winding number) that no push gets out gives up
part of its displacement, and a local relaxation undoes folded triangles.

Controls, each with an activation (0 = rest, 1 = full):
- linear muscles (Waters-style angular and radial fall-off) and sphincters (on their ellipse)
  pull the hypodermis inside their regions;
- `jaw_open` turns the mandible about the jaw pivot, `jaw_thrust` / `jaw_shift` slide it; the
  skin follows through its springs to the bone;
- `upper_lid_l/r`, `lower_lid_l/r` turn the lids about the eyeball's centre (the tarsal plate
  riding on the eye); at 1 the upper margin covers the eyeball down to the lower all along the
  fissure, as seen from the front (controls.seen_opening), the lower rises LOWER_LID_SHARE of the
  opening (the upper then stops on it). The plate is held to its turned place by springs, and its skin is then
  put there (the solve alone shears the lid's thin rim), the correction eased into the skin around;
- `cheek_puff_l/r` push the cheeks out (air pressure in the mouth);
- sheet muscles (controls.SHEET_MUSCLES: cheek raiser, levator alaeque nasi, depressor
  supercilii, each _l/_r) pull a patch of the hypodermis along the skin, placed from the FDPs;
- `lip_push_upper/lower` push the lips forward (the lip's own protrusion).
Template frame (or the adapted head's, same axes), metres.
"""

from __future__ import annotations

import copy
import dataclasses

import numpy as np

from ..mesh import geometry
from .contact import Contact, ContactMixin
from .controls import (
    LID_EASE,
    LID_EASE_STEPS,
    LID_KINEMATIC,
    LID_PIN,
    LID_RETRIES,
    LID_RETRY,
    LID_ZONE_RINGS,
    LOWER_LID_SHARE,
)
from .jaw import JawMixin
from .unfold import UnfoldMixin


@dataclasses.dataclass
class SkinModel(JawMixin, ContactMixin, UnfoldMixin):
    """The assembled mass-spring model: rest positions (3n,3), factorised stiffness, controls."""
    n: int
    rest: np.ndarray
    solve: object
    matrix: object                # the (3n,3n) sparse stiffness the solve factorised
    forces: dict                  # control -> (dof index (k,), force (k,3) at activation 1)
    bone_k: np.ndarray            # (n,) hypodermis-to-bone stiffness
    on_mandible: np.ndarray       # (n,) hypodermis vertex rides on the mandible
    jaw_pivot: np.ndarray
    jaw_axis: np.ndarray
    lids: dict                    # control -> (dofs (k,), stiffness (k,), eye centre, angle scale rad, weight (k,),
                                  # axis)
    bone_dist: np.ndarray         # (n,2) rest distance of each skin vertex to the cranium, the mandible
    bone_normal: np.ndarray       # (n,3) outward bone normal there
    free: np.ndarray              # (n,) vertices the non-penetration applies to
    clearance: np.ndarray         # (n,) least gap kept to the bone
    tris: np.ndarray              # (t,3) skin triangles
    folds: geometry.FoldCheck     # folded skin triangles against their rest orientation (slivers: SLIVER)
    adjacency: object             # (n,n) sparse, row-normalised vertex neighbours
    bone: tuple                   # (cranium, mandible) each (query, face normals, faces by an opening),
                                  # then cranium verts, mandible verts (rest), skull triangles
    mirror: np.ndarray = None     # (n,) the template's left/right partner of each vertex (None: a scanned head)

    @property
    def controls(self):
        """Names of every control this model takes an activation for."""
        return (*self.forces, "jaw_open", "jaw_thrust", "jaw_shift", *self.lids)

    def equilibrium(self, activations=None):
        """Skin (epidermis) positions (n,3) at equilibrium for {control: activation}, metres."""
        activations = {k: float(v) for k, v in (activations or {}).items() if v}
        unknown = set(activations) - set(self.controls)
        if unknown:
            raise KeyError(f"unknown control(s): {', '.join(sorted(unknown))}")
        return self._equilibrium(activations, 1.0)

    def _equilibrium(self, activations, lid_scale):
        """equilibrium, the lids' activations times lid_scale."""
        asked = activations
        activations = {k: v * lid_scale if k in self.lids else v for k, v in asked.items()}
        f = np.zeros_like(self.rest)
        for name, (idx, force) in self.forces.items():
            if name in activations:
                np.add.at(f, idx, activations[name] * force)
        rot, t = self.mandible_transform(activations)
        jaw_moves = bool(activations.keys() & {"jaw_open", "jaw_thrust", "jaw_shift"})
        if jaw_moves:
            hyp = slice(2 * self.n, 3 * self.n)
            rest_h = self.rest[hyp]
            target = self.on_jaw(rest_h, rot, t)
            f[hyp] += np.where(self.on_mandible[:, None], self.bone_k[:, None] * (target - rest_h), 0.0)
        placed = []
        pinned = np.zeros(self.n, bool)        # the lid skin turned all the way: held where its plate put it
        zone = np.zeros(self.n, bool)          # the turned lids' skin
        for name, (idx, k, centre, full, weight, axis) in self.lids.items():
            if name in activations:
                sign, act = (1.0 if name.startswith("upper") else -1.0), activations[name]
                if sign > 0:                   # the upper margin stops where the risen lower one is
                    act = min(act, 1.0 - LOWER_LID_SHARE * max(activations.get(name.replace("upper", "lower"), 0.0), 0.0))
                angle = (sign * full * act * weight)[:, None]
                rel = self.rest[idx] - centre                 # Rodrigues, one angle per dof
                turned = (rel * np.cos(angle) + np.cross(axis, rel) * np.sin(angle)
                          + np.outer(rel @ axis, axis) * (1 - np.cos(angle)))
                f[idx] += k[:, None] * (turned - rel)
                skin = idx < self.n                # the lid's skin is put on its plate's target
                placed.append((idx[skin], (centre + turned)[skin], np.clip(weight[skin] / LID_KINEMATIC, 0, 1)))
                if act > 0:                    # a closing lid's margin is held (an opening one's is not)
                    pinned[idx[skin][weight[skin] >= LID_PIN]] = True
                zone[idx[skin][weight[skin] > 0]] = True
        u = self.solve(f)
        x = self.rest[: self.n] + u[: self.n]
        if placed:                             # the lid skin on its plate, the skin around it eased after
            fix = np.zeros((self.n, 3))
            on = np.zeros(self.n, bool)
            for v, target, c in placed:
                fix[v] += c[:, None] * (target - x[v])
                on[v] = True
            for _ in range(LID_EASE_STEPS):
                fix = np.where(on[:, None], fix, LID_EASE * (self.adjacency @ fix))
            x += fix
        # skull non-penetration, on the true bone (the mandible moved)
        bn = np.where(self.on_mandible[:, None], self.bone_normal @ rot.T, self.bone_normal)
        contact = Contact(bn, (rot, t), symmetric=self._symmetric(x))
        x = self._retract_from_bone(self._keep_out_of_bone(x, contact), contact)
        if pinned.any():                       # the closed margin held while the folds round it relax,
            near = self._grown(zone, LID_ZONE_RINGS)
            held = self._unfold(x.copy(), copy.deepcopy(contact), pinned, near)
            left = self.flipped(held)
            if not len(left):                  # unless that leaves a fold (Fran's eyes, shut in the scan:
                return held                    # her crumpled lid folds by the held middle): then, a fold by
            # the closing lids (only a closing lid's margin is pinned):
            if near[self.tris[left]].any() and lid_scale > LID_RETRY ** LID_RETRIES * (1 + 1e-9):
                return self._equilibrium(asked, lid_scale * LID_RETRY)    # the lids a little less far,
        free = self._unfold(x, contact)        # and at last (or a fold elsewhere) as free skin,
        if pinned.any() and not len(self.flipped(free)):      # whose closing lids then go back down
            free = self._given_back(free, x, contact)         # as far as they fold nothing
        return free

    def _symmetric(self, x):
        """Whether skin x (n,3) is the template's mirror image of itself (to rounding): then the
        contact pushes it symmetrically (a midline point at a crease of the bone has two nearest
        points; either one would push it sideways)."""
        return self.mirror is not None and float(np.abs(x[self.mirror] * [-1.0, 1.0, 1.0] - x).max()) < 1e-7

    def flipped(self, x):
        """Indices of skin triangles whose normal turned against its rest normal at positions x (n,3)."""
        return self.folds(x)
