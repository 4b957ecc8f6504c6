"""Readers of label formats published by others, converted to ``sygrid.annotations`` objects."""

from sygrid.readers.sygrid_pickle import load_sygrid_pickle as load_sygrid_pickle
from sygrid.readers.sygrid_pickle import safe_load_pickle as safe_load_pickle
