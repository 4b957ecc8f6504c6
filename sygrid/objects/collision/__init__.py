"""Collision models of parts in three tiers, each with a measured fidelity, and the rule that picks the cheapest
good one.

Modules: ``params`` (the tiers' names and knobs), ``geometry`` (what a collision model is: convex pieces or
primitives, its ``Fidelity``, MuJoCo-ready arrays), ``tiers`` (hull / CoACD / V-HACD), ``fidelity`` (the
Monte-Carlo measurement against the true mesh), ``cache`` (the disk cache, keyed by mesh content hash, tier and
parameters, so each decomposition is computed once per machine) and ``build`` (``build_collision_model``,
``select_collision_model``). The public names are also in ``sygrid.objects``.
"""
