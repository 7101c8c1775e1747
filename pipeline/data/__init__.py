"""Dataset readers, splits, target manifolds and the generated default scene."""
