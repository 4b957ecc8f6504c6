"""``sygrid bench stability``: sweeps of one difficulty at a time until each method fails (issue 25)."""
