"""Sim-to-real gap diagnosis: candidate effects library, residual analysis, attribution, benchmark."""

from .effects import (EFFECTS, ETA_TRANS_BASE, Effect, EffectParam, apply_effects, check_effects, effect_names,
                      get_effect, post_effects)

__all__ = ["EFFECTS", "ETA_TRANS_BASE", "Effect", "EffectParam", "apply_effects", "check_effects",
           "effect_names", "get_effect", "post_effects"]
