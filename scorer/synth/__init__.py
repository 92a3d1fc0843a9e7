"""Synthetic splits of `navsim-lb/scene` v1 files that exercise every PDMS metric (`navsim-lb synth`)."""

from scorer.synth.split import GENERATOR_VERSION, scene_token, synthesize_scene, synthesize_split

__all__ = ["GENERATOR_VERSION", "scene_token", "synthesize_scene", "synthesize_split"]
