"""NAVSIM v2.2's two-stage ("pseudo-simulation") EPDMS around the per-token scores: the split's stage mapping,
the Gaussian weights of the synthetic scenes, the per-group aggregation and the official result CSV
(docs/engine.md, "Two-stage EPDMS"). Scoring a token (with reactive traffic) is not done here.
"""
