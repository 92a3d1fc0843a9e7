"""NAVSIM v2.2's reactive traffic: the current frame's vehicles driven by nuPlan's IDM along their lanes, reacting
to the scored trajectory (docs/engine.md, "Reactive traffic")."""
