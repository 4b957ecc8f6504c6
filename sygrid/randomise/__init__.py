"""Domain randomisation of a recipe's items: the knobs (``spec``), the named families of textures, finishes and
lights (``families``), the per-item draws (``draws``) and what turns them into pixels (``textures``, ``skies``,
``clutter``, ``camera_effects``; the renderer in ``sygrid.render`` consumes the draws)."""
