"""Generate a fresh evaluation set of synthetic range images with ground truth.

    JAX_PLATFORMS=cpu python benchmarks/unseen/make.py [--out DIR]

Each scene goes to OUT/NAME/: depth.npy (float32 z-depth, NaN = no return), camera.json
(the camera's to_json), truth.json (scene JSON via sqparts.save_scene; per-part
annotations "name" and "figure" = which object the part belongs to) and meta.json
(description, objects, draws, coverage).  OUT/index.json lists them all.

Modelled on benchmarks/bench_objects.py: parts are built in an object frame
(x right, y down, z away), the object turned (yaw about y, then a tilt about x so the
camera looks down on it), centred at distance z, rendered with
sqparts.render_range_image, then optionally noised / quantised.  A draw is rejected and
re-drawn unless the figure covers 3%..60% of the image, stays 2 px clear of the border,
every part shows >= 6 pixels, each object is one connected blob, and the objects of a
two-object scene are apart (2 px) in the image.
"""

from __future__ import annotations

import argparse
import json
import os
from pathlib import Path

import numpy as np
from scipy import ndimage
from scipy.spatial.transform import Rotation as R

import sqparts

SEED = 7070
HERE = Path(__file__).resolve().parent

VERT = [("x", 90)]  # local z points up (-y)
ALONGX = [("y", 90)]  # local z along x


def P(size, eps, pos, rot=(), bend=None, taper=None, obj=0, name=None):
    return dict(
        size=list(map(float, size)),
        eps=list(map(float, eps)),
        pos=list(map(float, pos)),
        rot=rot,
        bend=bend,
        taper=taper,
        obj=obj,
        name=name,
    )


def along(d):
    """Rotation matrix whose third column (local z) is the unit vector along d."""
    z = np.asarray(d, float)
    z = z / np.linalg.norm(z)
    helper = np.array([1.0, 0, 0]) if abs(z[0]) < 0.9 else np.array([0, 0, 1.0])
    x = np.cross(helper, z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return np.stack([x, y, z], 1)


def rod(p0, p1, r, eps=(0.3, 1.0), obj=0, name=None, overlap=0.0):
    """A part from point p0 to p1 (radius r); lengthened by `overlap` at each end."""
    p0, p1 = np.asarray(p0, float), np.asarray(p1, float)
    half = np.linalg.norm(p1 - p0) / 2 + overlap
    return P([r, r, half], eps, (p0 + p1) / 2, along(p1 - p0), obj=obj, name=name)


def S(name, desc, parts, z, cam, wh, noise=0.0, step=0.0, pitch=(10, 35), yaw=(-60, 60), share=(0.55, 0.95), thin=None):
    return dict(
        name=name,
        desc=desc,
        parts=parts,
        z=float(z),
        cam=cam,
        wh=wh,
        noise=noise,
        step=step,
        pitch=pitch,
        yaw=yaw,
        share=share,
        thin=thin,
    )


def shifted(parts, dx=0.0, dy=0.0, dz=0.0, obj=0):
    out = []
    for p in parts:
        q = dict(p)
        q["pos"] = [p["pos"][0] + dx, p["pos"][1] + dy, p["pos"][2] + dz]
        q["obj"] = obj
        out.append(q)
    return out


def mug(dx=0.0, obj=0):
    return shifted(
        [
            P([0.045, 0.045, 0.055], [0.1, 1], [0, 0, 0], VERT, name="body"),
            P([0.02, 0.035, 0.01], [0.3, 0.3], [0.06, 0, 0], name="handle"),
        ],
        dx=dx,
        obj=obj,
    )


def snowman(r=(0.2, 0.14, 0.09), dx=0.0, obj=0):
    y0 = 0.3
    y1 = y0 - r[0] - r[1] + 0.03
    y2 = y1 - r[1] - r[2] + 0.02
    return shifted(
        [
            P([r[0]] * 3, [1, 1], [0, y0, 0], name="bottom"),
            P([r[1]] * 3, [1, 1], [0, y1, 0], name="middle"),
            P([r[2]] * 3, [1, 1], [0, y2, 0], name="head"),
        ],
        dx=dx,
        obj=obj,
    )


def stick_person(walk=False):
    s = 1 if walk else 0
    parts = [
        P([0.13, 0.2, 0.08], [0.6, 0.6], [0, -0.05, 0], name="torso"),
        P([0.08, 0.08, 0.08], [1, 1], [0, -0.33, 0], name="head"),
    ]
    for side in (-1, 1):
        parts.append(
            rod(
                [side * 0.15, -0.22, 0],
                [side * (0.2 if walk else 0.24), 0.14, side * 0.15 * s],
                0.03,
                (0.5, 1),
                name="arm",
            )
        )
    for side in (-1, 1):
        parts.append(rod([side * 0.07, 0.1, 0], [side * 0.085, 0.7, -side * 0.2 * s], 0.045, (0.5, 1), name="leg"))
    return parts


def robot_arm():
    base = P([0.1, 0.1, 0.05], [0.2, 1], [0, 0.3, 0], VERT, name="base")
    a = np.array([0, 0.27, 0.0])
    d1 = np.array([np.sin(np.radians(20)), -np.cos(np.radians(20)), 0])
    b = a + 0.36 * d1
    d2 = np.array([np.cos(np.radians(15)), -np.sin(np.radians(15)), 0])
    c = b + 0.30 * d2
    return [
        base,
        rod(a, b, 0.03, (0.3, 1), name="link1", overlap=0.01),
        rod(b - 0.02 * d2, c, 0.025, (0.3, 1), name="link2"),
    ]


def lamp(dx=0.0, obj=0, pole=0.015):
    return shifted(
        [
            P([0.12, 0.12, 0.02], [0.3, 1], [0, 0.38, 0], VERT, name="base"),
            P([pole, pole, 0.37], [1, 1], [0, 0.0, 0], VERT, name="pole"),
            P([0.12, 0.12, 0.10], [0.4, 1], [0, -0.44, 0], VERT, taper=-0.5, name="shade"),
        ],
        dx=dx,
        obj=obj,
    )


def four(x, zz):
    return [(sx * x, sz * zz) for sx in (-1, 1) for sz in (-1, 1)]


SCENES = [
    # --- single parts
    S("box", "flat box with sharp corners", [P([0.18, 0.06, 0.12], [0.1, 0.1], [0, 0, 0])], 2.2, "pinhole", (120, 100)),
    S(
        "cube_noisy",
        "small rounded cube, 2 mm noise",
        [P([0.08, 0.08, 0.08], [0.2, 0.2], [0, 0, 0], [("z", 15)])],
        1.3,
        "orthographic",
        (80, 80),
        noise=0.002,
    ),
    S(
        "cylinder_upright",
        "upright cylinder",
        [P([0.07, 0.07, 0.20], [0.15, 1.0], [0, 0, 0], VERT)],
        1.6,
        "pinhole",
        (100, 140),
    ),
    S(
        "cylinder_lying_q",
        "cylinder lying along x, 3 mm steps",
        [P([0.05, 0.05, 0.22], [0.2, 1], [0, 0, 0], ALONGX)],
        2.5,
        "orthographic",
        (160, 96),
        step=0.003,
    ),
    S(
        "ellipsoid_oblate",
        "oblate ellipsoid tilted 60 deg",
        [P([0.20, 0.20, 0.07], [1, 1], [0, 0, 0], [("x", 60)])],
        3.5,
        "pinhole",
        (96, 96),
    ),
    S(
        "ellipsoid_noisy",
        "small ellipsoid rolled 25 deg, 1.5 mm noise",
        [P([0.06, 0.10, 0.14], [1, 1], [0, 0, 0], [("z", -25)])],
        1.1,
        "pinhole",
        (80, 64),
        noise=0.0015,
    ),
    S(
        "bent_rod",
        "rod along x bent in the image plane (bend -0.6)",
        [P([0.03, 0.03, 0.30], [0.25, 1], [0, 0, 0], [("z", 90), ("y", 90)], bend=[-0.6, 0])],
        1.4,
        "pinhole",
        (160, 120),
    ),
    S(
        "bent_board",
        "upright board bent sideways (bend 0.4)",
        [P([0.12, 0.025, 0.25], [0.2, 0.2], [0, 0, 0], VERT, bend=[0.4, 0])],
        2.0,
        "orthographic",
        (140, 100),
    ),
    S(
        "tapered_column",
        "round column widening upward (taper 0.7)",
        [P([0.09, 0.09, 0.35], [0.3, 1], [0, 0, 0], VERT, taper=0.7)],
        4.2,
        "pinhole",
        (90, 150),
    ),
    S(
        "tapered_box_q",
        "tapered box turned 60 deg, 2 mm steps",
        [P([0.12, 0.08, 0.2], [0.2, 0.2], [0, 0, 0], [("y", 60)], taper=-0.5)],
        1.9,
        "pinhole",
        (128, 96),
        step=0.002,
    ),
    S(
        "plate_edge_on",
        "thin plate seen nearly edge-on (tilt 4-9 deg)",
        [P([0.20, 0.01, 0.25], [0.15, 0.15], [0, 0, 0])],
        1.5,
        "pinhole",
        (160, 120),
        pitch=(4, 9),
        yaw=(-40, 40),
        share=(0.6, 0.85),
    ),
    S(
        "block_far",
        "rounded block, 6 m away, 64x64",
        [P([0.10, 0.09, 0.11], [0.5, 0.5], [0, 0, 0])],
        6.0,
        "pinhole",
        (64, 64),
        share=(0.3, 0.5),
    ),
    S(
        "capsule_noisy",
        "capsule turned obliquely, 1 mm noise",
        [P([0.04, 0.04, 0.18], [0.6, 1], [0, 0, 0], [("z", 40), ("y", 30)])],
        1.0,
        "orthographic",
        (96, 128),
        noise=0.001,
    ),
    # --- two parts
    S(
        "T_noisy",
        "T: bar on a post, 2.5 mm noise",
        [
            P([0.25, 0.03, 0.03], [0.2, 0.2], [0, -0.25, 0], name="bar"),
            P([0.03, 0.03, 0.22], [0.2, 0.2], [0, 0, 0], VERT, name="post"),
        ],
        1.6,
        "orthographic",
        (140, 110),
        noise=0.0025,
    ),
    S(
        "L_noisy",
        "L bracket of two boxes, 2 mm noise",
        [
            P([0.035, 0.22, 0.05], [0.1, 0.1], [-0.1, 0, 0], name="upright"),
            P([0.18, 0.035, 0.05], [0.1, 0.1], [0.045, 0.185, 0], name="foot"),
        ],
        1.8,
        "pinhole",
        (128, 128),
        noise=0.002,
    ),
    S(
        "mallet",
        "mallet: thin round handle, cylindrical head",
        [
            P([0.012, 0.012, 0.18], [1, 1], [0, 0, 0], VERT, name="handle"),
            P([0.04, 0.04, 0.09], [0.2, 1], [0, -0.2, 0], ALONGX, name="head"),
        ],
        0.8,
        "pinhole",
        (200, 160),
    ),
    S(
        "hammer_q",
        "hammer: flat handle, boxy head off-centre, 2 mm steps",
        [
            P([0.015, 0.02, 0.16], [0.5, 0.5], [0, 0, 0], VERT, name="handle"),
            P([0.022, 0.025, 0.08], [0.15, 0.15], [0.02, -0.175, 0], ALONGX, name="head"),
        ],
        1.0,
        "orthographic",
        (120, 120),
        step=0.002,
    ),
    S("mug", "mug: cylinder with a bar handle", mug(), 0.9, "pinhole", (128, 96)),
    S(
        "lollipop_thin",
        "lollipop: ball on a stick 2-4 px wide",
        [
            P([0.005, 0.005, 0.09], [1, 1], [0, 0.05, 0], VERT, name="stick"),
            P([0.035, 0.035, 0.035], [1, 1], [0, -0.07, 0], name="ball"),
        ],
        1.2,
        "pinhole",
        (160, 160),
        thin=(0, (2, 4)),
    ),
    S(
        "cross_q",
        "plus-shaped cross of two flat bars, 2.5 mm steps",
        [
            P([0.22, 0.03, 0.025], [0.2, 0.2], [0, 0, 0], name="h"),
            P([0.03, 0.22, 0.025], [0.2, 0.2], [0, 0, 0], name="v"),
        ],
        3.0,
        "orthographic",
        (128, 128),
        yaw=(-40, 40),
        step=0.0025,
    ),
    S(
        "bottle_noisy",
        "bottle: body cylinder and neck, 1 mm noise",
        [
            P([0.05, 0.05, 0.12], [0.2, 1], [0, 0.05, 0], VERT, name="body"),
            P([0.018, 0.018, 0.05], [0.3, 1], [0, -0.11, 0], VERT, name="neck"),
        ],
        1.3,
        "pinhole",
        (100, 150),
        noise=0.001,
    ),
    S(
        "mushroom_noisy",
        "mushroom: stem and flattened cap, 1.5 mm noise",
        [
            P([0.025, 0.025, 0.06], [0.5, 1], [0, 0.03, 0], VERT, name="stem"),
            P([0.08, 0.08, 0.035], [0.6, 1], [0, -0.04, 0], VERT, name="cap"),
        ],
        1.7,
        "pinhole",
        (96, 96),
        noise=0.0015,
    ),
    S(
        "signpost",
        "signpost: post with a board in front of its top",
        [
            P([0.02, 0.02, 0.3], [0.2, 1], [0, 0.05, 0], VERT, name="post"),
            P([0.15, 0.08, 0.01], [0.1, 0.1], [0, -0.28, -0.028], name="board"),
        ],
        5.0,
        "orthographic",
        (120, 160),
        yaw=(-45, 45),
    ),
    # --- three to six parts
    S(
        "table",
        "table, 4 legs, seen from above-front",
        [P([0.45, 0.025, 0.3], [0.1, 0.1], [0, -0.35, 0], name="top")]
        + [P([0.025, 0.025, 0.33], [0.2, 0.2], [x, 0.0, zz], VERT, name="leg") for x, zz in four(0.4, 0.25)],
        3.2,
        "pinhole",
        (200, 160),
        pitch=(30, 50),
    ),
    S(
        "coffee_table_q",
        "low square table, 4 stubby legs, 4 mm steps",
        [P([0.35, 0.02, 0.35], [0.2, 0.2], [0, -0.18, 0], name="top")]
        + [P([0.03, 0.03, 0.16], [0.2, 1], [x, 0.0, zz], VERT, name="leg") for x, zz in four(0.28, 0.28)],
        2.4,
        "orthographic",
        (160, 120),
        pitch=(25, 45),
        step=0.004,
    ),
    S(
        "stool3_noisy",
        "round stool, 3 legs, 2 mm noise",
        [P([0.16, 0.16, 0.025], [0.5, 1], [0, -0.2, 0], VERT, name="seat")]
        + [
            P(
                [0.018, 0.018, 0.18],
                [0.3, 1],
                [0.1 * np.cos(np.radians(a)), 0.0, 0.1 * np.sin(np.radians(a))],
                VERT,
                name="leg",
            )
            for a in (90, 210, 330)
        ],
        1.9,
        "pinhole",
        (128, 128),
        noise=0.002,
    ),
    S(
        "stool4_thin",
        "square stool, 4 legs 2-4 px wide",
        [P([0.15, 0.02, 0.15], [0.2, 0.2], [0, -0.24, 0], name="seat")]
        + [P([0.012, 0.012, 0.22], [1, 1], [x, 0.0, zz], VERT, name="leg") for x, zz in four(0.12, 0.12)],
        2.0,
        "orthographic",
        (128, 128),
        thin=(1, (2, 4)),
    ),
    S(
        "chair_noisy",
        "chair: seat, back to the floor, 2 front legs, 2 mm noise",
        [
            P([0.21, 0.025, 0.2], [0.15, 0.15], [0, 0, 0], name="seat"),
            P([0.21, 0.47, 0.02], [0.15, 0.15], [0, -0.02, 0.18], name="back"),
        ]
        + [P([0.02, 0.02, 0.215], [0.2, 0.2], [x, 0.235, -0.17], VERT, name="leg") for x in (-0.18, 0.18)],
        1.9,
        "pinhole",
        (160, 160),
        yaw=(-50, 50),
        noise=0.002,
    ),
    S(
        "lamp_thin",
        "lamp: base disc, pole 2-4 px wide, tapered shade",
        lamp(),
        2.6,
        "pinhole",
        (120, 160),
        thin=(1, (2, 4)),
    ),
    S(
        "lamp_ortho",
        "lamp: box base, pole, ellipsoid shade",
        [
            P([0.1, 0.03, 0.08], [0.1, 0.1], [0, 0.33, 0], name="base"),
            P([0.02, 0.02, 0.3], [0.3, 1], [0, 0, 0], VERT, name="pole"),
            P([0.11, 0.11, 0.08], [1, 1], [0, -0.36, 0], name="shade"),
        ],
        3.8,
        "orthographic",
        (100, 140),
    ),
    S(
        "robot_arm_noisy",
        "robot arm: base disc, two links, 2.5 mm noise",
        robot_arm(),
        1.7,
        "pinhole",
        (160, 120),
        noise=0.0025,
    ),
    S(
        "robot_arm_q",
        "robot arm: box base, upright link, slanted link, gripper, 3 mm steps",
        [
            P([0.12, 0.04, 0.12], [0.1, 0.1], [0, 0.3, 0], name="base"),
            rod([0, 0.27, 0], [0, -0.05, 0], 0.035, (0.2, 0.2), name="link1", overlap=0.01),
            rod([0, -0.05, 0], [0.25, 0.05, 0.05], 0.03, (0.3, 1), name="link2", overlap=0.01),
            P([0.03, 0.05, 0.03], [0.2, 0.2], [0.28, 0.065, 0.06], name="gripper"),
        ],
        1.5,
        "orthographic",
        (160, 120),
        step=0.003,
    ),
    S("stick_person", "stick figure standing: torso, head, 2 arms, 2 legs", stick_person(), 4.5, "pinhole", (120, 160)),
    S(
        "person_walking",
        "stick figure walking: arms and legs swung",
        stick_person(True),
        3.0,
        "orthographic",
        (128, 160),
    ),
    S(
        "dumbbell_noisy",
        "dumbbell: bar and two disc weights, 1 mm noise",
        [rod([-0.17, 0, 0], [0.17, 0, 0], 0.015, (0.3, 1), name="bar")]
        + [P([0.055, 0.055, 0.025], [0.2, 1], [x, 0, 0], ALONGX, name="weight") for x in (-0.14, 0.14)],
        1.0,
        "pinhole",
        (160, 100),
        noise=0.001,
    ),
    S(
        "dumbbell_round",
        "dumbbell with ball weights",
        [rod([-0.2, 0, 0], [0.2, 0, 0], 0.02, (0.3, 1), name="bar")]
        + [P([0.07, 0.07, 0.07], [1, 1], [x, 0, 0], name="ball") for x in (-0.22, 0.22)],
        2.2,
        "orthographic",
        (128, 80),
    ),
    S(
        "bench_back",
        "bench: seat, two end panels, backrest",
        [P([0.5, 0.03, 0.14], [0.15, 0.15], [0, -0.2, 0], name="seat")]
        + [P([0.03, 0.2, 0.12], [0.15, 0.15], [x, 0.0, 0], name="end") for x in (-0.42, 0.42)]
        + [P([0.5, 0.12, 0.02], [0.15, 0.15], [0, -0.34, 0.13], name="back")],
        3.6,
        "pinhole",
        (200, 120),
    ),
    S("snowman", "snowman of 3 spheres", snowman(), 2.9, "pinhole", (100, 150)),
    S(
        "snowman_q",
        "snowman of 3 squashed ellipsoids, 5 mm steps",
        [
            P([0.18, 0.15, 0.18], [1, 1], [0, 0.25, 0], name="bottom"),
            P([0.13, 0.11, 0.13], [1, 1], [0, 0.01, 0], name="middle"),
            P([0.08, 0.08, 0.08], [1, 1], [0, -0.165, 0], name="head"),
        ],
        1.8,
        "orthographic",
        (96, 128),
        step=0.005,
    ),
    S(
        "table_thin",
        "far table, 4 rod legs 2-3 px wide",
        [P([0.3, 0.02, 0.2], [0.1, 0.1], [0, -0.25, 0], name="top")]
        + [rod([x, -0.24, zz], [x, 0.25, zz], 0.012, (1, 1), name="leg") for x, zz in four(0.26, 0.16)],
        5.5,
        "pinhole",
        (160, 120),
        pitch=(25, 40),
        thin=(1, (2, 3)),
    ),
    S(
        "goalpost",
        "goalpost: two posts and a crossbar",
        [rod([x, 0.3, 0], [x, -0.3, 0], 0.04, (0.3, 1), name="post") for x in (-0.35, 0.35)]
        + [rod([-0.39, -0.3, 0], [0.39, -0.3, 0], 0.035, (0.3, 1), name="bar")],
        4.0,
        "pinhole",
        (180, 120),
        yaw=(-45, 45),
    ),
    S(
        "mailbox",
        "mailbox: post, box, side flag",
        [
            P([0.03, 0.03, 0.25], [0.15, 0.15], [0, 0.12, 0], VERT, name="post"),
            P([0.08, 0.08, 0.18], [0.2, 0.2], [0, -0.2, 0], name="box"),
            P([0.01, 0.06, 0.02], [0.2, 0.2], [0.09, -0.25, 0.08], name="flag"),
        ],
        2.4,
        "pinhole",
        (96, 128),
    ),
    # --- two objects side by side
    S(
        "pair_box_cylinder",
        "two objects: box and upright cylinder",
        [
            P([0.1, 0.08, 0.1], [0.15, 0.15], [-0.2, 0, 0], obj=0, name="box"),
            P([0.06, 0.06, 0.13], [0.2, 1], [0.2, -0.05, 0], VERT, obj=1, name="cylinder"),
        ],
        2.0,
        "pinhole",
        (160, 100),
        yaw=(-30, 30),
    ),
    S(
        "pair_mug_egg_noisy",
        "two objects: mug (2 parts) and egg, 2 mm noise",
        mug(-0.1, 0) + [P([0.04, 0.06, 0.04], [1, 1], [0.12, 0, 0], obj=1, name="egg")],
        1.5,
        "orthographic",
        (160, 96),
        yaw=(-30, 30),
        noise=0.002,
    ),
    S(
        "pair_stool_lamp",
        "two objects: pedestal stool (3) and lamp (3)",
        shifted(
            [
                P([0.15, 0.15, 0.03], [0.3, 1], [0, -0.2, 0], VERT, name="seat"),
                P([0.03, 0.03, 0.19], [0.3, 1], [0, 0.0, 0], VERT, name="column"),
                P([0.1, 0.1, 0.02], [0.3, 1], [0, 0.2, 0], VERT, name="foot"),
            ],
            dx=-0.4,
            dy=0.12,
            obj=0,
        )
        + lamp(0.35, 1, pole=0.02),
        4.5,
        "pinhole",
        (200, 140),
        yaw=(-30, 30),
    ),
    S(
        "pair_snowman_box_q",
        "two objects: snowman (3) and box, 3 mm steps",
        snowman((0.15, 0.11, 0.07), -0.3, 0) + [P([0.12, 0.12, 0.12], [0.1, 0.1], [0.3, 0.15, 0], obj=1, name="box")],
        3.2,
        "pinhole",
        (180, 120),
        yaw=(-30, 30),
        step=0.003,
    ),
    S(
        "pair_depth",
        "two objects at different depths: T (2) in front, ellipsoid behind",
        shifted(
            [
                P([0.15, 0.025, 0.025], [0.2, 0.2], [0, -0.15, 0], name="bar"),
                P([0.025, 0.025, 0.13], [0.2, 0.2], [0, 0.0, 0], VERT, name="post"),
            ],
            dx=-0.25,
            dz=-0.3,
            obj=0,
        )
        + [P([0.12, 0.08, 0.1], [1, 1], [0.25, 0, 0.3], obj=1, name="ellipsoid")],
        2.5,
        "pinhole",
        (160, 120),
        yaw=(-20, 20),
    ),
]


def build(spec, turn, z, centre):
    parts = []
    for p in spec["parts"]:
        rot = p["rot"]
        if isinstance(rot, np.ndarray):
            local = R.from_matrix(rot)
        else:
            local = R.identity()
            for axis, deg in rot:
                local = R.from_euler(axis, deg, degrees=True) * local
        extra = {}
        if p["bend"] is not None:
            extra["bend"] = p["bend"]
        if p["taper"] is not None:
            extra["taper"] = p["taper"]
        pos = turn.apply(np.asarray(p["pos"]) - centre) + [0, 0, z]
        parts.append(
            sqparts.Part(
                size=p["size"], squareness=p["eps"], position=pos, orientation=(turn * local).as_rotvec(), **extra
            )
        )
    return sqparts.stack_parts(parts)


def bounds(spec):
    pts = []
    for p in spec["parts"]:
        r = max(p["size"]) * (1 + abs(p["taper"] or 0))
        pts.append(np.asarray(p["pos"]) - r)
        pts.append(np.asarray(p["pos"]) + r)
    pts = np.array(pts)
    lo, hi = pts.min(0), pts.max(0)
    centre = (lo + hi) / 2
    extent = 2 * max(np.linalg.norm(np.asarray(p["pos"]) - centre) + max(p["size"]) for p in spec["parts"])
    return centre, extent


def check(depth, labels, spec):
    h, w = depth.shape
    mask = np.isfinite(depth)
    cover = mask.mean()
    if not 0.03 <= cover <= 0.60:
        return f"coverage {cover:.3f}"
    if mask[:2].any() or mask[-2:].any() or mask[:, :2].any() or mask[:, -2:].any():
        return "touches border"
    n = len(spec["parts"])
    counts = np.bincount(labels[labels >= 0].ravel(), minlength=n)
    if counts.min() < 6:
        return f"part {int(counts.argmin())} shows {int(counts.min())} px"
    objs = np.array([p["obj"] for p in spec["parts"]])
    nobj = objs.max() + 1
    masks = []
    for k in range(nobj):
        m = mask & np.isin(labels, np.flatnonzero(objs == k))
        _, ncomp = ndimage.label(m, structure=np.ones((3, 3)))
        if ncomp != 1:
            return f"object {k} in {ncomp} pieces"
        masks.append(m)
    if nobj == 2 and (ndimage.binary_dilation(masks[0], iterations=2) & masks[1]).any():
        return "objects touch in the image"
    return None


def make_scene(spec, rng, out: Path):
    w, h = spec["wh"]
    z = spec["z"]
    centre, extent = bounds(spec)
    for attempt in range(1, 101):  # noqa: B007 (the count is recorded after the loop)
        yaw, pitch = rng.uniform(*spec["yaw"]), rng.uniform(*spec["pitch"])
        share = rng.uniform(*spec["share"])
        cx = (w - 1) / 2 + rng.uniform(-0.12, 0.12) * w
        cy = (h - 1) / 2 + rng.uniform(-0.12, 0.12) * h
        thin_px = None
        if spec["thin"] is not None:
            idx, (lo, hi) = spec["thin"]
            thin_px = rng.uniform(lo, hi)
            diam = 2 * min(spec["parts"][idx]["size"][:2])
            scale = thin_px / diam  # pixels per metre at the object
        else:
            scale = share * min(w, h) / extent
        turn = R.from_euler("x", pitch, degrees=True) * R.from_euler("y", yaw, degrees=True)
        parts = build(spec, turn, z, centre)
        if spec["cam"] == "pinhole":
            cam = sqparts.PinholeCamera(w, h, scale * z, scale * z, cx, cy)
        else:
            cam = sqparts.OrthographicCamera(w, h, 1.0 / scale, cx, cy)
        depth, labels = sqparts.render_range_image(parts, cam, return_labels=True)
        depth, labels = np.asarray(depth, np.float32), np.asarray(labels)
        why = check(depth, labels, spec)
        if why is None:
            break
    else:
        raise RuntimeError(f"{spec['name']}: no acceptable draw in 100 tries (last: {why})")
    clean = depth.copy()
    if spec["noise"]:
        depth = depth + rng.normal(0, spec["noise"], depth.shape).astype(np.float32)
    if spec["step"]:
        depth = (np.round(depth / spec["step"]) * spec["step"]).astype(np.float32)
    depth = depth.astype(np.float32)
    d = out / spec["name"]
    d.mkdir(parents=True, exist_ok=True)
    np.save(d / "depth.npy", depth)
    sqparts.save_camera(d / "camera.json", cam)
    ann = [{"name": p["name"] or f"part{i}", "figure": int(p["obj"])} for i, p in enumerate(spec["parts"])]
    sqparts.save_scene(d / "truth.json", parts, ann)
    objs = [p["obj"] for p in spec["parts"]]
    meta = dict(
        name=spec["name"],
        description=spec["desc"],
        objects=max(objs) + 1,
        parts_per_object=[objs.count(k) for k in range(max(objs) + 1)],
        parts=len(objs),
        camera=spec["cam"],
        width=w,
        height=h,
        distance=z,
        yaw=yaw,
        pitch=pitch,
        noise=spec["noise"],
        step=spec["step"],
        thin_px=thin_px,
        coverage=float(np.isfinite(clean).mean()),
        pixels=int(np.isfinite(clean).sum()),
        attempts=attempt,
        seed=SEED,
    )
    with open(d / "meta.json", "w") as f:
        json.dump(meta, f, indent=1)
    return meta


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--out", type=Path, default=HERE / "scenes")
    args = ap.parse_args()
    names = [s["name"] for s in SCENES]
    assert len(set(names)) == len(names)
    rng = np.random.default_rng(SEED)
    index = []
    for spec in SCENES:
        sub = np.random.default_rng(rng.integers(2**63))  # one stream per scene: edits elsewhere don't move it
        m = make_scene(spec, sub, args.out)
        index.append(m)
        print(
            f"{m['name']:22s} {m['parts']} parts/{m['objects']} obj {m['camera'][:5]} {m['width']}x{m['height']} "
            f"z {m['distance']:.1f} yaw {m['yaw']:+.0f} tilt {m['pitch']:.0f} cover {m['coverage']:.1%} "
            f"tries {m['attempts']}"
            + (f" thin {m['thin_px']:.1f}px" if m["thin_px"] else "")
            + (f" noise {m['noise'] * 1e3:.1f}mm" if m["noise"] else "")
            + (f" step {m['step'] * 1e3:.1f}mm" if m["step"] else ""),
            flush=True,
        )
    tmp = args.out / "index.json.tmp"
    with open(tmp, "w") as f:
        json.dump(index, f, indent=1)
    os.replace(tmp, args.out / "index.json")
    print(f"{len(index)} scenes in {args.out}")


if __name__ == "__main__":
    main()
