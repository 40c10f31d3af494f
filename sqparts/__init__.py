"""sqparts: recover the part structure of objects from range images.

An implementation of A. Pentland, "Recognition by Parts" (SRI, 1987) in JAX. The public
API is exactly what this module re-exports, in pipeline order. The names are
imported on first use (PEP 562), so that ``import sqparts.cli`` and ``sqparts --help``
start without loading JAX.
"""

from __future__ import annotations

import importlib
import importlib.metadata

_EXPORTS = {
    "_part": (
        "BEND_RANGE",
        "SQUARENESS_RANGE",
        "TAPER_RANGE",
        "Part",
        "inside_outside",
        "rotation_matrix",
        "stack_parts",
        "surface_distance",
        "normal_distance",
        "surface_point",
    ),
    "_camera": (
        "OrthographicCamera",
        "PinholeCamera",
        "ScannerCamera",
        "camera_from_json",
    ),
    "_preprocess": (
        "CleanedRange",
        "FigureGround",
        "Plane",
        "clean_range_image",
        "downsample",
        "estimate_noise",
        "figure_ground",
        "fit_plane",
        "flying_pixels",
        "joined_pieces",
        "missing_returns",
        "torn_components",
    ),
    "_render": (
        "cast_batch",
        "cast_part",
        "cast_ray",
        "cast_scene",
        "render_each",
        "render_range_image",
    ),
    "_encoding": (
        "Costs",
        "Edit",
        "Encoding",
        "EncodingCost",
        "area_matrix",
        "commission_mask",
        "description_length",
        "edit_costs",
        "edit_totals",
        "encoding_cost",
        "encoding_for",
        "gamma",
        "gamma_terms",
        "smooth_gamma",
    ),
    "_data": (
        "RangeData",
        "prepare",
    ),
    "_grid": (
        "PRESETS",
        "Grid",
        "grid_preset",
    ),
    "_polish": (
        "grow_parts",
        "polish_part",
        "ray_penetration",
    ),
    "_search": (
        "RegionFit",
        "SEARCH_PRESETS",
        "SearchSettings",
        "convex_width",
        "expanding_grid",
        "fit_image",
        "fit_region",
        "fit_regions",
        "gamma_profile",
        "make_settings",
        "region_centers",
        "score_region",
        "score_regions",
        "search_preset",
    ),
    "_select": (
        "SelectSettings",
        "SelectionProblem",
        "select_best_first",
        "select_brute_force",
        "select_exact",
        "select_parts",
        "select_rendered",
        "select_tabu",
    ),
    "_refine": (
        "AbsorbParts",
        "DropParts",
        "FillGaps",
        "GrowParts",
        "MergeParts",
        "Move",
        "OnGain",
        "RefineSettings",
        "SettleFaces",
        "SettleParts",
        "SplitParts",
        "StraightenParts",
        "StretchParts",
        "UnpinchParts",
        "accept_edits",
        "refine_moves",
        "refine_parts",
        "run_moves",
    ),
    "_recover": (
        "SCENE_PRESETS",
        "MultiscaleRecovery",
        "Recovery",
        "SceneRecovery",
        "SceneSettings",
        "recover",
        "recover_multiscale",
        "recover_scene",
        "scene_preset",
    ),
    "_postprocess": (
        "FractalSurface",
        "ResidualModel",
        "fit_fractal",
        "prettify",
        "residual_model",
        "snap_rotation",
        "snap_to_gravity",
    ),
    "_describe": (
        "ATTRIBUTES",
        "RELATIONS",
        "Description",
        "describe",
        "describe_figures",
        "part_volume",
        "surface_cloud",
    ),
    "_recognize": (
        "Alignment",
        "Match",
        "MatchSettings",
        "Observation",
        "align_candidates",
        "align_descriptions",
        "calibrate_threshold",
        "estimate_pose",
        "fit_pose",
        "lead",
        "match_descriptions",
        "propose_poses",
        "verify_poses",
    ),
    "_scenes": (
        "BUILTIN_SCENES",
        "BuiltinScene",
        "HUMAN_POSES",
        "builtin_scene",
        "posed_human",
    ),
    "_io": (
        "PARTS_SCHEMA_PATH",
        "camera_from_realsense",
        "camera_depth_scale",
        "load_camera",
        "load_scene",
        "parts_schema",
        "read_range_image",
        "save_camera",
        "save_scene",
        "scene_from_dict",
        "scene_to_dict",
        "write_range_image",
    ),
    "_database": (
        "ModelDatabase",
        "Recognition",
        "RecognitionMatch",
        "learn",
        "recognize",
    ),
    "_mesh": (
        "load_mesh",
        "part_colors",
        "part_mesh",
        "render_mesh",
        "save_mesh",
        "scene_mesh",
        "scene_open3d",
        "scene_trimesh",
    ),
    "_batch": ("recover_many",),
}
"""Each module's public names, in pipeline order."""

__all__ = [name for names in _EXPORTS.values() for name in names]
_MODULE = {name: module for module, names in _EXPORTS.items() for name in names}

try:
    __version__ = importlib.metadata.version("sqparts")
except importlib.metadata.PackageNotFoundError:  # run from a source tree without installing
    __version__ = "0+unknown"


def __getattr__(name: str):
    module = _MODULE.get(name)
    if module is None:
        raise AttributeError(f"module 'sqparts' has no attribute {name!r}")
    value = getattr(importlib.import_module(f".{module}", __name__), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))
