"""Force models as composable effects: `Param`, `Effect`, `Model`, the catalogue, plugins."""

from rig.models.catalogue import CATALOGUE, NAMED_MODELS, build_model
from rig.models.core import Effect, Model, Motion, Param
from rig.models.plugins import effect, load_plugin

__all__ = ["CATALOGUE", "NAMED_MODELS", "Effect", "Model", "Motion", "Param", "build_model", "effect",
           "load_plugin"]
