"""NAVSIM v2.2's two-stage ("pseudo-simulation") EPDMS: the split's stage mapping, the Gaussian weights of the
synthetic scenes, a submission scored token by token with reactive traffic and two-frame comfort between the
mapping's pairs, the per-group aggregation and the official result CSV (docs/engine.md, "Two-stage EPDMS").
"""
