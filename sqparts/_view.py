"""Looking at a recovery in 3-D: the browser viewer (``sqparts view``, viser) and Rerun
recordings (``sqparts recover --rerun``), at the edge.

Both show the same things, in the camera frame (OpenCV: x right, y down, z forward): the
measured points coloured by depth (near bright, as in ``report.png``), each part as a
named mesh in its ``report.png`` colour, and the pixels explained (green), omitted (red)
and committed (blue: the model where the data is not), as in the report's panel (f).
What they need besides ``parts.json`` is written by ``sqparts recover`` into its output
folder (:func:`sqparts._io.save_view_data`): ``range.npy``, ``camera.json`` and
``pixels.npz``.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

import numpy as np

STATUS = {"explained": 1, "omitted": 2, "commission": 3}
"""The codes of ``pixels.npz``'s ``status`` (0: not on a figure, no part)."""

STATUS_COLORS = {"explained": (51, 179, 77), "omitted": (217, 51, 51), "commission": (51, 102, 230)}
"""As in ``report.png``'s panel (f)."""


def pixel_status(recovery) -> np.ndarray:
    """uint8 image of :data:`STATUS` codes for a :class:`~sqparts.Recovery` or
    :class:`~sqparts.SceneRecovery` (the figure's pixels explained or omitted; the
    model's pixels off the data, commission)."""
    status = np.zeros(recovery.depth.shape, np.uint8)
    status[np.asarray(recovery.figure)] = STATUS["omitted"]
    status[np.asarray(recovery.cost.explained_mask)] = STATUS["explained"]
    status[np.asarray(recovery.cost.commission_mask)] = STATUS["commission"]
    return status


def _depth_colors(depth: np.ndarray) -> np.ndarray:
    from ._plot import range_image_rgb

    return range_image_rgb(depth)


def view_layers(data: dict, *, resolution: int = 10) -> dict:
    """What both viewers draw, from :func:`sqparts._io.load_view_data`'s dict.

    Returns ``{"points": {name: (points (n, 3), colors (n, 3) uint8)}, "parts": [(name,
    vertices, faces, color (4,) uint8, label)], "point_size": float}``; a part's name is
    ``part_<i>`` (its index in parts.json; the label adds its annotated ``name``, figure,
    Γ and bits saved); ``points`` holds ``measured`` and the :data:`STATUS` layers when the
    range image is there.
    """
    from ._mesh import part_colors, part_mesh

    parts, annotations = data["parts"], data["annotations"]
    n = len(parts)
    colors = part_colors(n)
    layers = {"points": {}, "parts": [], "point_size": 0.01}
    several_figures = len({a.get("figure") for a in annotations}) > 1
    for i in range(n):
        mesh = part_mesh(parts[i], resolution=resolution)
        a = annotations[i]
        name = f"part_{i}"  # the scene node's name; an annotated name goes in the label
        words = (
            [name]
            + ([str(a["name"])] if a.get("name") else [])
            + ([f"figure {a.get('figure')}"] if several_figures else [])
        )
        words += [
            f"{symbol}{a[k]:.0f}{unit}"
            for k, symbol, unit in (("gamma", "Γ ", ""), ("bits_saved", "", " bits"))
            if isinstance(a.get(k), (int, float))
        ]
        label = " · ".join(words)
        layers["parts"].append(
            (name, np.asarray(mesh.vertices, np.float32), np.asarray(mesh.faces, np.uint32), colors[i], label)
        )
    depth, camera = data.get("depth"), data.get("camera")
    if depth is None or camera is None:
        return layers
    xyz = camera.points(depth)
    ok = np.isfinite(depth)
    rgb = _depth_colors(depth)
    layers["points"]["measured"] = (xyz[ok].astype(np.float32), rgb[ok])
    if ok.any():
        layers["point_size"] = float(np.median(np.asarray(camera.pixel_size_at(depth[ok])))) * 0.6
    status, model = data.get("status"), data.get("model")
    if status is not None:
        model_xyz = camera.points(model) if model is not None else xyz
        for name, code in STATUS.items():
            where = (status == code) & np.isfinite(model_xyz if name == "commission" else xyz).all(-1)
            source = model_xyz if name == "commission" else xyz
            layers["points"][name] = (
                source[where].astype(np.float32),
                np.tile(np.asarray(STATUS_COLORS[name], np.uint8), (int(where.sum()), 1)),
            )
    return layers


# --- the browser viewer (viser) -------------------------------------------------------


def _viser():
    try:
        import viser
    except ImportError:
        raise ValueError("view: got no viser, expected it installed (pip install 'sqparts[view]')") from None
    return viser


def _text(value, spec: str) -> str:
    """A number from parts.json formatted, or blank where it is not one."""
    ok = isinstance(value, (int, float)) and not isinstance(value, bool) and (spec != "d" or isinstance(value, int))
    return format(value, spec) if ok else ""


def build_view(server, data: dict) -> dict:
    """Fill a ``viser.ViserServer`` with a recovery: point layers and parts, each with a
    checkbox, the figures and the summary. Returns the scene handles by name."""
    layers = view_layers(data)
    server.scene.set_up_direction("-y")
    handles = {}
    meta = data["meta"]
    bits, explained = _text(meta.get("description_length_bits"), ".0f"), _text(meta.get("fraction_explained"), ".1%")
    server.gui.add_markdown(
        f"**{data['title']}**  \n{len(layers['parts'])} parts"
        + (f", E = {bits} bits" if bits else "")
        + (f", {explained} explained" if explained else "")
    )

    def toggle(checkbox, handle):
        @checkbox.on_update
        def _(_event):
            handle.visible = checkbox.value

    with server.gui.add_folder("Points"):
        for name, (points, colors) in layers["points"].items():
            handle = server.scene.add_point_cloud(
                f"/points/{name}",
                points,
                colors,
                point_size=layers["point_size"],
                point_shape="rounded",
                visible=name == "measured",
            )
            handles[f"points/{name}"] = handle
            toggle(server.gui.add_checkbox(f"{name} ({len(points)})", name == "measured"), handle)
    with server.gui.add_folder("Parts"):
        for name, vertices, faces, color, label in layers["parts"]:
            handle = server.scene.add_mesh_simple(
                f"/parts/{name}",
                vertices,
                faces,
                color=tuple(int(c) for c in color[:3]),
                flat_shading=False,
                side="double",
            )
            handles[f"parts/{name}"] = handle
            toggle(server.gui.add_checkbox(label, True), handle)
    figures = meta.get("figures")
    if isinstance(figures, list) and figures:
        with server.gui.add_folder("Figures"):
            rows = ["| figure | pixels | parts | E (bits) | explained |", "|---|---|---|---|---|"]
            for k, f in enumerate(figures):
                if isinstance(f, dict):
                    rows.append(
                        f"| {k} | {_text(f.get('pixels'), 'd')} | {_text(f.get('parts'), 'd')} | "
                        f"{_text(f.get('description_length_bits'), '.0f')} | "
                        f"{_text(f.get('fraction_explained'), '.0%')} |"
                    )
            server.gui.add_markdown("\n".join(rows))
    if data.get("report") is not None:
        with server.gui.add_folder("Report", expand_by_default=False):
            server.gui.add_image(data["report"], label="report.png")
    # From in front of the scene, a little to the right and above (y is down).
    vertices = np.concatenate([v for _, v, *_ in layers["parts"]])
    low, high = vertices.min(0), vertices.max(0)
    centre, extent = (low + high) / 2, float(np.linalg.norm(high - low))
    server.initial_camera.look_at = tuple(float(x) for x in centre)
    server.initial_camera.position = tuple(float(x) for x in centre + extent * np.array([0.35, -0.3, -0.85]))
    server.initial_camera.up = (0.0, -1.0, 0.0)
    return handles


def serve(folder, *, port: int = 8080, host: str = "127.0.0.1", announce=print):
    """Serve the recovery in ``folder`` at ``http://host:port`` until interrupted."""
    from ._io import load_view_data

    data = load_view_data(folder)
    viser = _viser()
    server = viser.ViserServer(host=host, port=port, verbose=False)
    try:
        build_view(server, data)
        announce(f"viewing {folder} at http://{host}:{server.get_port()} (Ctrl-C to stop)")
        server.sleep_forever()
    finally:
        server.stop()


# --- Rerun -------------------------------------------------------------------------------


def entity_name(text: str) -> str:
    """A Rerun entity path part from any text (letters, digits, ``_`` and ``-``)."""
    return re.sub(r"[^A-Za-z0-9_-]+", "_", str(text)).strip("_") or "recovery"


def _rerun() -> Any:
    """The ``rerun`` module, typed ``Any``: rerun-sdk stops at import below Python 3.11,
    so a type checker set to Python 3.10 sees none of its names."""
    import rerun

    return rerun


def rerun_entries(data: dict, prefix: str) -> list:
    """``(entity path, archetype)`` pairs logging one recovery under ``prefix``: the
    camera (a pinhole's intrinsics), the depth image, the point layers and the parts."""
    from ._camera import PinholeCamera

    rr = _rerun()
    layers = view_layers(data)
    out = [(prefix, rr.ViewCoordinates.RDF)]
    camera, depth = data.get("camera"), data.get("depth")
    if isinstance(camera, PinholeCamera):
        out.append(
            (
                f"{prefix}/camera",
                rr.Pinhole(
                    focal_length=[camera.fx, camera.fy],
                    principal_point=[camera.cx, camera.cy],
                    width=camera.width,
                    height=camera.height,
                ),
            )
        )
        if depth is not None:
            out.append((f"{prefix}/camera/depth", rr.DepthImage(np.nan_to_num(depth, nan=0.0), meter=1.0)))
    for name, (points, colors) in layers["points"].items():
        out.append((f"{prefix}/points/{name}", rr.Points3D(points, colors=colors, radii=layers["point_size"] / 2)))
    for name, vertices, faces, color, _label in layers["parts"]:
        out.append(
            (
                f"{prefix}/parts/{entity_name(name)}",
                rr.Mesh3D(
                    vertex_positions=vertices,
                    triangle_indices=faces,
                    vertex_colors=np.tile(color[:3], (len(vertices), 1)),
                ),
            )
        )
    if data.get("report") is not None:
        out.append((f"{prefix}/report", rr.EncodedImage(path=Path(data["folder"]) / "report.png")))
    return out


def rerun_bytes(entries) -> bytes:
    """One Rerun recording (``.rrd`` bytes) of the entries, all static."""
    rr = _rerun()

    recording = rr.RecordingStream("sqparts")
    stream = recording.binary_stream()
    for path, archetype in entries:
        recording.log(path, archetype, static=True)
    return stream.read(flush=True)
