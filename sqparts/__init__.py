"""sqparts: recover the part structure of objects from range images.

An implementation of A. Pentland, "Recognition by Parts" (SRI, 1987) in JAX. The public
API is exactly what this module re-exports, in pipeline order.
"""

from ._part import (
    BEND_RANGE,
    SQUARENESS_RANGE,
    TAPER_RANGE,
    Part,
    inside_outside,
    rotation_matrix,
    stack_parts,
    surface_point,
)
from ._camera import OrthographicCamera, PinholeCamera, ScannerCamera, camera_from_json
from ._render import cast_batch, cast_part, cast_ray, cast_scene, render_each, render_range_image
from ._fit import Encoding, encoding_for, gamma, gamma_terms, smooth_gamma
from ._grid import PRESETS, Grid, grid_preset
from ._search import (
    RangeData,
    RegionFit,
    SearchSettings,
    convex_width,
    expanding_grid,
    fit_image,
    fit_region,
    gamma_profile,
    make_settings,
    polish_part,
    prepare,
    region_centers,
    score_region,
)
from ._select import (
    Costs,
    SelectionProblem,
    area_matrix,
    description_length,
    select_best_first,
    select_brute_force,
    select_exact,
    select_parts,
)
from ._refine import EncodingCost, encoding_cost, refine_parts
from ._recover import Recovery, recover
from ._scenes import BUILTIN_SCENES, BuiltinScene, builtin_scene
from ._io import (
    load_camera,
    load_scene,
    read_range_image,
    save_camera,
    save_scene,
    scene_from_dict,
    scene_to_dict,
    write_range_image,
)
from ._mesh import load_mesh, part_mesh, render_mesh, save_mesh, scene_mesh

__version__ = "0.1.0"

__all__ = [
    "BEND_RANGE",
    "SQUARENESS_RANGE",
    "TAPER_RANGE",
    "Part",
    "inside_outside",
    "rotation_matrix",
    "stack_parts",
    "surface_point",
    "OrthographicCamera",
    "PinholeCamera",
    "ScannerCamera",
    "camera_from_json",
    "cast_batch",
    "cast_part",
    "cast_ray",
    "cast_scene",
    "render_each",
    "render_range_image",
    "Encoding",
    "encoding_for",
    "gamma",
    "gamma_terms",
    "smooth_gamma",
    "PRESETS",
    "Grid",
    "grid_preset",
    "RangeData",
    "RegionFit",
    "SearchSettings",
    "convex_width",
    "expanding_grid",
    "fit_image",
    "fit_region",
    "gamma_profile",
    "make_settings",
    "polish_part",
    "prepare",
    "region_centers",
    "score_region",
    "Costs",
    "SelectionProblem",
    "area_matrix",
    "description_length",
    "select_best_first",
    "select_brute_force",
    "select_exact",
    "select_parts",
    "EncodingCost",
    "encoding_cost",
    "refine_parts",
    "Recovery",
    "recover",
    "BUILTIN_SCENES",
    "BuiltinScene",
    "builtin_scene",
    "load_camera",
    "load_scene",
    "read_range_image",
    "save_camera",
    "save_scene",
    "scene_from_dict",
    "scene_to_dict",
    "write_range_image",
    "load_mesh",
    "part_mesh",
    "render_mesh",
    "save_mesh",
    "scene_mesh",
]
