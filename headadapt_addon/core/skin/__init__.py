"""The skin simulation (paper sec 6): a three-layer mass-spring skin on the skull, driven by muscles,
jaw and lids (build -> SkinModel.equilibrium), MPEG-4 FAPs and expressions as activations (drive),
baked to shape keys (bake).

build: assembly; model: the model and its quasi-static solve; controls: muscles, pressure, lids;
contact: skin against bone; unfold: folded triangles undone; sight: what a person facing the head sees
of an eyeball; jaw: the mandible's turn and slide.
"""

from .build import build
from .model import SkinModel

__all__ = ["SkinModel", "build"]
