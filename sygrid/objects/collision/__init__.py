"""Collision models of parts in three tiers, each with a measured fidelity, and the rule that picks the cheapest
good one.

Modules: ``params`` (the tiers' names and knobs), ``geometry`` (what a collision model is: convex pieces or
primitives, its ``Fidelity``, MuJoCo-ready arrays), ``solid`` (the part's repaired solid: the mesh itself when it
is one closed volume, else a union of its bodies or a voxel-based closed manifold with thin walls thickened),
``tiers`` (hull / CoACD / V-HACD), ``worker`` (the native decomposers, in this process or in a child process
stopped at a time limit), ``fidelity`` (the Monte-Carlo measurement against the solid), ``cache`` (the disk
cache, keyed by mesh content hash, tier, parameters and the repair, so each decomposition and each repair is
computed once per machine) and ``build`` (``build_collision_model``, ``select_collision_model``). The public names
are also in ``sygrid.objects``.
"""
