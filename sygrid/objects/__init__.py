"""Object models: built-in procedural parts and CAD meshes in metres, with symmetries and grasp annotations.

The public API, one explicit re-export per line (``name as name`` marks it as a re-export for linters).
"""

from sygrid.objects.cad import load_cad as load_cad
from sygrid.objects.collision.build import build_collision_model as build_collision_model
from sygrid.objects.collision.build import select_collision_model as select_collision_model
from sygrid.objects.collision.geometry import CollisionModel as CollisionModel
from sygrid.objects.collision.params import CollisionTier as CollisionTier
from sygrid.objects.model import ContinuousSymmetry as ContinuousSymmetry
from sygrid.objects.model import GraspAnnotation as GraspAnnotation
from sygrid.objects.model import ObjectModel as ObjectModel
from sygrid.objects.parts import BUILTIN_PARTS as BUILTIN_PARTS
from sygrid.objects.parts import builtin_part as builtin_part
from sygrid.objects.symmetry import check_symmetries as check_symmetries
from sygrid.objects.symmetry import symmetry_error_m as symmetry_error_m
