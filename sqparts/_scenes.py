"""Built-in scenes for the demo, tests, benchmarks and docs (paper Figures 2, 7, 8, 10).

Each is a :class:`BuiltinScene`: a batched :class:`~sqparts.Part`, the camera that views
it and a short description. Units are metres, camera frame OpenCV (y down, z forward).
"""

from __future__ import annotations

import dataclasses
import types

import numpy as np

from ._camera import Camera, OrthographicCamera, PinholeCamera, ScannerCamera
from ._part import Part, stack_parts


@dataclasses.dataclass(frozen=True)
class BuiltinScene:
    name: str
    parts: Part
    camera: Camera
    part_names: tuple[str, ...]
    description: str


def _frame_from_z(axis) -> np.ndarray:
    """Rotation vector turning local +z onto ``axis``."""
    a = np.asarray(axis, float)
    a = a / np.linalg.norm(a)
    z = np.array([0.0, 0.0, 1.0])
    c = np.cross(z, a)
    s, cos = np.linalg.norm(c), float(z @ a)
    if s < 1e-12:
        return np.array([np.pi, 0.0, 0.0]) if cos < 0 else np.zeros(3)
    return c / s * np.arctan2(s, cos)


def _compose(rv_outer, rv_inner) -> np.ndarray:
    """Rotation vector of R(rv_outer) @ R(rv_inner)."""
    from ._part import rotation_matrix, rotation_vector

    return rotation_vector(np.asarray(rotation_matrix(rv_outer)) @ np.asarray(rotation_matrix(rv_inner)))


def limb(start, end, width, depth=None, squareness=(1.0, 1.0), *, roll=0.0, bend=(0.0, 0.0), taper=0.0) -> Part:
    """A part whose local z runs from ``start`` to ``end`` (camera frame), semi-axes
    ``width`` (local x) and ``depth`` (local y, default ``width``), turned by ``roll``
    radians about its own axis."""
    start, end = np.asarray(start, float), np.asarray(end, float)
    axis = end - start
    orientation = _compose(_frame_from_z(axis), np.array([0.0, 0.0, roll]))
    return Part(
        size=np.array([width, width if depth is None else depth, np.linalg.norm(axis) / 2], np.float32),
        squareness=np.asarray(squareness, np.float32),
        position=((start + end) / 2).astype(np.float32),
        orientation=orientation.astype(np.float32),
        bend=np.asarray(bend, np.float32),
        taper=np.float32(taper),
    )


def human(resolution: int = 128) -> BuiltinScene:
    """An articulated person like Figure 7: 16 parts, the left arm raised with its
    forearm pointing at the camera, 4 m away."""
    z = 4.0
    named = {
        "head": limb([0, -0.90, z], [0, -0.66, z], 0.095, 0.105, (0.9, 1.0)),
        "neck": limb([0, -0.67, z], [0, -0.57, z], 0.05),
        "torso": limb([0, -0.58, z], [0, -0.08, z], 0.17, 0.10, (0.5, 0.6)),
        "pelvis": limb([0, -0.10, z], [0, 0.06, z], 0.15, 0.10, (0.6, 0.6)),
        "right upper arm": limb([-0.22, -0.54, z], [-0.27, -0.26, z], 0.05),
        "right forearm": limb([-0.27, -0.26, z], [-0.29, -0.02, z], 0.042, taper=-0.25),
        "right hand": limb([-0.29, -0.02, z], [-0.30, 0.08, z], 0.04, 0.02, (0.6, 0.8)),
        "left upper arm": limb([0.22, -0.54, z], [0.42, -0.76, z], 0.05),
        "left forearm": limb([0.43, -0.76, z - 0.02], [0.43, -0.76, z - 0.28], 0.042),
        "left hand": limb([0.43, -0.76, z - 0.28], [0.43, -0.76, z - 0.38], 0.045, 0.03, (0.6, 0.8)),
        "right thigh": limb([-0.09, 0.04, z], [-0.11, 0.46, z], 0.075, taper=-0.2),
        "left thigh": limb([0.09, 0.04, z], [0.11, 0.46, z], 0.075, taper=-0.2),
        "right calf": limb([-0.11, 0.46, z], [-0.11, 0.86, z], 0.055, taper=-0.2),
        "left calf": limb([0.11, 0.46, z], [0.11, 0.86, z], 0.055, taper=-0.2),
        "right foot": limb([-0.11, 0.89, z + 0.04], [-0.11, 0.89, z - 0.18], 0.045, 0.03, (0.6, 0.8)),
        "left foot": limb([0.11, 0.89, z + 0.04], [0.11, 0.89, z - 0.18], 0.045, 0.03, (0.6, 0.8)),
    }
    f = resolution * z / 2.2
    c = (resolution - 1) / 2
    cam = PinholeCamera(resolution, resolution, f, f, c, c)
    return BuiltinScene(
        "human",
        stack_parts(named.values()),
        cam,
        tuple(named),
        "an articulated person (Figure 7), 16 parts, 4 m from a pinhole camera",
    )


def chair(resolution: int = 96, *, leg_width: float = 0.025, tilt: float = 2.4, turn: float = 0.6) -> BuiltinScene:
    """A chair as in Figure 2(c): seat, bent back, four legs of semi-axis ``leg_width``
    metres (4 pixels across at 96x96 by default), 3 m away, turned by ``turn`` radians
    about its own vertical and tilted by ``tilt`` about the camera's x axis (pi/2: seen
    from the side; more: from above). The default view is from above at an angle, and
    hides one leg behind the seat; :func:`thin_chair` sees all four."""
    if not (isinstance(leg_width, (int, float)) and 0 < leg_width <= 0.1):
        raise ValueError(f"leg_width: got {leg_width!r}, expected metres in (0, 0.1]")
    parts = {
        "seat": limb([0, 0, -0.03], [0, 0, 0.03], 0.24, 0.22, (0.2, 0.3), roll=0.0),
        "back": Part(
            size=np.array([0.03, 0.24, 0.25], np.float32),
            squareness=np.array([0.3, 0.3], np.float32),
            position=np.array([-0.23, 0, 0.28], np.float32),
            bend=np.array([-0.25, 0.0], np.float32),
        ),
    }
    for i, (x, y) in enumerate([(-0.2, -0.18), (-0.2, 0.18), (0.2, -0.18), (0.2, 0.18)]):
        parts[f"leg {i + 1}"] = limb([x, y, -0.03], [x, y, -0.45], leg_width, squareness=(0.3, 0.3))
    # Chair frame: z up. Pose it in the camera frame: seen from above and from the side.
    pose = _compose(np.array([float(tilt), 0.0, 0.0]), np.array([0.0, 0.0, float(turn)]))
    rot = np.asarray(_rot(pose))
    posed = []
    for p in parts.values():
        pos = rot @ np.asarray(p.position, float) + np.array([0.0, 0.0, 3.0])
        posed.append(
            Part(
                size=p.size,
                squareness=p.squareness,
                position=pos.astype(np.float32),
                orientation=_compose(pose, np.asarray(p.orientation, float)).astype(np.float32),
                bend=p.bend,
                taper=p.taper,
            )
        )
    f = resolution * 3.0 / 1.2
    c = (resolution - 1) / 2
    return BuiltinScene(
        "chair",
        stack_parts(posed),
        PinholeCamera(resolution, resolution, f, f, c, c),
        tuple(parts),
        "a chair (Figure 2c): square seat, bent back, four legs, seen from above at an angle",
    )


def thin_chair(resolution: int = 96) -> BuiltinScene:
    """The chair of :func:`chair` with legs 2.4 pixels across (``leg_width=0.015``), seen
    from 19 degrees above the seat's plane so that all four legs show (47-97 pixels each)."""
    s = chair(resolution, leg_width=0.015, tilt=1.9, turn=-0.6)
    return dataclasses.replace(
        s, name="thin-chair", description="the chair with legs 2.4 pixels across, all four in view"
    )


def _rot(rv):
    from ._part import rotation_matrix

    return rotation_matrix(np.asarray(rv, np.float32))


def castings(resolution: int = 96, *, seed: int = 3) -> BuiltinScene:
    """Jumbled industrial castings (Figure 8): blocks and cylinders in a heap, viewed from
    above by an orthographic (light-striping) sensor."""
    rng = np.random.default_rng(seed)
    parts, names = [], []
    for i in range(6):
        cylinder = i % 2 == 0
        size = rng.uniform([0.05, 0.05, 0.12], [0.08, 0.08, 0.22])
        if not cylinder:
            size[1] *= 0.6
        xy = rng.uniform(-0.22, 0.22, 2)
        rv = _compose(np.array([np.pi / 2 + rng.uniform(-0.4, 0.4), 0, 0]), np.array([0, rng.uniform(0, np.pi), 0]))
        parts.append(
            Part(
                size=size.astype(np.float32),
                squareness=np.array([0.2, 1.0 if cylinder else 0.2], np.float32),
                position=np.array([xy[0], xy[1], 1.0 - 0.03 * i], np.float32),
                orientation=np.asarray(rv, np.float32),
            )
        )
        names.append(f"{'cylinder' if cylinder else 'block'} {i + 1}")
    c = (resolution - 1) / 2
    cam = OrthographicCamera(resolution, resolution, 0.7 / resolution, c, c)
    return BuiltinScene(
        "castings",
        stack_parts(parts),
        cam,
        tuple(names),
        "six jumbled castings (Figure 8) under an orthographic sensor",
    )


def gate(
    width: int = 128,
    height: int = 48,
    *,
    distance: float = 20.0,
    rails=(-0.8, 0.05, 0.9),
    brace=(0.9, -0.8),
    pinhole: bool = False,
) -> BuiltinScene:
    """A field gate (Figure 10) ``distance`` metres away seen by a wide-angle scanner like
    the ERIM range finder (0.25 degrees a pixel; ``pinhole``: a pinhole camera of the same
    focal length): two posts, a rail at each height in ``rails`` and a brace from the
    left post's side at height ``brace[0]`` to the right post's at ``brace[1]`` (camera y,
    down). Its members are 17.5 cm across, about two pixels at 20 m."""
    step = np.radians(0.25)
    w = 20.0 * step  # one pixel at 20 m
    d = float(distance)
    parts, names = [], []
    for i, x in enumerate((-2.4, 2.4)):
        parts.append(limb([x, -1.0, d], [x, 1.2, d], w, w, (0.2, 0.2)))
        names.append(f"post {i + 1}")
    for i, y in enumerate(rails):
        parts.append(limb([-2.4, y, d], [2.4, y, d], w, w, (0.2, 0.2)))
        names.append(f"bar {i + 1}")
    parts.append(limb([-2.3, brace[0], d], [2.3, brace[1], d], w, w, (0.2, 0.2)))
    names.append("brace")
    c = ((width - 1) / 2, (height - 1) / 2)
    cam = (
        PinholeCamera(width, height, 1 / step, 1 / step, *c)
        if pinhole
        else ScannerCamera(width, height, step, step, *c)
    )
    return BuiltinScene(
        "gate",
        stack_parts(parts),
        cam,
        tuple(names),
        f"a gate {d:g} m away (Figure 10), members about {40 / d:.1f} pixels wide, {'pinhole' if pinhole else 'scanner'} camera",
    )


HUMAN_POSES = types.MappingProxyType(
    {
        # name: (right arm, left arm, right leg, left leg), each limb (upper, lower) as
        # (abduction, swing) in degrees: abduction away from the body in the frontal plane,
        # swing towards the camera; 0, 0 hangs straight down.
        "standing": (((8, 0), (6, 0)), ((8, 0), (6, 0)), ((2, 0), (2, 0)), ((2, 0), (2, 0))),
        "arms up": (((160, 0), (170, 0)), ((160, 0), (170, 0)), ((3, 0), (3, 0)), ((3, 0), (3, 0))),
        "t-pose": (((90, 0), (90, 0)), ((90, 0), (90, 0)), ((6, 0), (6, 0)), ((6, 0), (6, 0))),
        "walking": (((5, -25), (5, 0)), ((5, 25), (5, 50)), ((2, 28), (2, 0)), ((2, -22), (2, -45))),
        "waving": (((130, 0), (170, 0)), ((8, 0), (6, 0)), ((2, 0), (2, 0)), ((2, 0), (2, 0))),
        "pointing": (((8, 0), (6, 0)), ((50, 0), (0, 90)), ((2, 0), (2, 0)), ((2, 0), (2, 0))),
        "straddle": (((30, 0), (20, 0)), ((30, 0), (20, 0)), ((25, 0), (5, 0)), ((25, 0), (5, 0))),
    }
)
"""Joint angles of :func:`posed_human`'s poses (configuration stability, section 1)."""


def _limb_direction(abduction_deg: float, swing_deg: float, side: float) -> np.ndarray:
    a, s = np.radians(abduction_deg), np.radians(swing_deg)
    return np.array([side * np.sin(a) * np.cos(s), np.cos(a) * np.cos(s), -np.sin(s)])


def posed_human(pose: str = "standing", resolution: int = 128) -> BuiltinScene:
    """The built-in person's 16 parts in one of :data:`HUMAN_POSES`, 4 m from the camera
    as :func:`human`: the same limbs (sizes, squareness, taper), the joints moved."""
    if pose not in HUMAN_POSES:
        raise ValueError(f"pose: got {pose!r}, expected one of {sorted(HUMAN_POSES)}")
    z = 4.0
    right_arm, left_arm, right_leg, left_leg = HUMAN_POSES[pose]
    named = {
        "head": limb([0, -0.90, z], [0, -0.66, z], 0.095, 0.105, (0.9, 1.0)),
        "neck": limb([0, -0.67, z], [0, -0.57, z], 0.05),
        "torso": limb([0, -0.58, z], [0, -0.08, z], 0.17, 0.10, (0.5, 0.6)),
        "pelvis": limb([0, -0.10, z], [0, 0.06, z], 0.15, 0.10, (0.6, 0.6)),
    }
    for side, label, (upper, lower) in ((-1.0, "right", right_arm), (1.0, "left", left_arm)):
        shoulder = np.array([0.22 * side, -0.54, z])
        elbow = shoulder + 0.29 * _limb_direction(*upper, side)
        wrist = elbow + 0.24 * _limb_direction(*lower, side)
        hand = wrist + 0.10 * _limb_direction(*lower, side)
        named[f"{label} upper arm"] = limb(shoulder, elbow, 0.05)
        named[f"{label} forearm"] = limb(elbow, wrist, 0.042, taper=-0.25)
        named[f"{label} hand"] = limb(wrist, hand, 0.04, 0.02, (0.6, 0.8))
    for side, label, (upper, lower) in ((-1.0, "right", right_leg), (1.0, "left", left_leg)):
        hip = np.array([0.09 * side, 0.04, z])
        knee = hip + 0.42 * _limb_direction(*upper, side)
        ankle = knee + 0.40 * _limb_direction(*lower, side)
        named[f"{label} thigh"] = limb(hip, knee, 0.075, taper=-0.2)
        named[f"{label} calf"] = limb(knee, ankle, 0.055, taper=-0.2)
        heel = ankle + np.array([0.0, 0.03, 0.04])
        named[f"{label} foot"] = limb(heel, heel + np.array([0.0, 0.0, -0.22]), 0.045, 0.03, (0.6, 0.8))
    order = [
        "head",
        "neck",
        "torso",
        "pelvis",
        "right upper arm",
        "right forearm",
        "right hand",
        "left upper arm",
        "left forearm",
        "left hand",
        "right thigh",
        "left thigh",
        "right calf",
        "left calf",
        "right foot",
        "left foot",
    ]
    f = resolution * z / 2.6
    c = (resolution - 1) / 2
    cam = PinholeCamera(resolution, resolution, f, f, c, c)
    return BuiltinScene(
        f"human ({pose})",
        stack_parts([named[k] for k in order]),
        cam,
        tuple(order),
        f"the articulated person in pose {pose!r}, 16 parts, 4 m from a pinhole camera",
    )


BUILTIN_SCENES = types.MappingProxyType(
    {"human": human, "chair": chair, "castings": castings, "gate": gate, "thin-chair": thin_chair}
)


def builtin_scene(name: str, **kwargs) -> BuiltinScene:
    """One of :data:`BUILTIN_SCENES` by name."""
    if name not in BUILTIN_SCENES:
        raise ValueError(f"scene: got {name!r}, expected one of {sorted(BUILTIN_SCENES)}")
    return BUILTIN_SCENES[name](**kwargs)
