"""Rendering of SyGRID data items with Mitsuba: variant choice, camera poses, materials, the scene, the renderer."""

from sygrid.render.camera_pose import look_at_T_world_camera as look_at_T_world_camera
from sygrid.render.camera_pose import sample_T_world_camera as sample_T_world_camera
from sygrid.render.materials import MATERIALS as MATERIALS
from sygrid.render.materials import material_bsdf as material_bsdf
from sygrid.render.renderer import RenderResult as RenderResult
from sygrid.render.renderer import render_item as render_item
from sygrid.render.variant import VARIANTS as VARIANTS
from sygrid.render.variant import RenderBackendError as RenderBackendError
from sygrid.render.variant import choose_variant as choose_variant
