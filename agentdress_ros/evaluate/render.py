"""Headless renders of bodies and garments to PNG (matplotlib, flat-shaded, painter's algorithm)."""
from __future__ import annotations

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from mpl_toolkits.mplot3d.art3d import Poly3DCollection  # noqa: E402

LIGHT = np.array([0.3, -0.8, 0.5]) / np.linalg.norm([0.3, -0.8, 0.5])


def _shaded(vertices, faces, color, view_dir):
    corners = vertices[faces]
    normals = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    normals /= np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-12)
    facing = normals @ view_dir < 0.05  # back-face culling (view_dir points from the camera into the scene)
    intensity = 0.35 + 0.65 * np.abs(normals @ LIGHT)
    colors = np.clip(np.asarray(color)[None, :] * intensity[:, None], 0, 1)
    return corners[facing], colors[facing]


def render_meshes(ax, meshes, azimuth=-90.0, elevation=8.0, offset=(0.0, 0.0, 0.0)):
    """Draw [(vertices (N, 3), faces (F, 3), rgb)] into a 3D axis, shaded, seen from `azimuth` degrees."""
    az, el = np.radians(azimuth), np.radians(elevation)
    view_dir = -np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
    polys, colors = [], []
    for vertices, faces, color in meshes:
        p, c = _shaded(np.asarray(vertices) + np.asarray(offset), np.asarray(faces), color, view_dir)
        polys.append(p)
        colors.append(c)
    polys, colors = np.concatenate(polys), np.concatenate(colors)
    depth = polys.mean(axis=1) @ view_dir
    order = np.argsort(-depth)  # far first
    ax.add_collection3d(Poly3DCollection(polys[order], facecolors=colors[order], edgecolors="none"))
    ax.view_init(elev=elevation, azim=azimuth)


SKIN = (0.87, 0.72, 0.62)
GARMENT_COLORS = {"tshirt": (0.2, 0.45, 0.8), "longsleeve": (0.75, 0.3, 0.25), "trousers": (0.25, 0.25, 0.3)}


def render_scenes(path, scenes, titles, azimuth=-70.0, size=3.2):
    """One panel per scene, all at one scale; a scene is a list of (vertices, faces, rgb). Writes a PNG."""
    fig = plt.figure(figsize=(size * len(scenes), size * 1.6), dpi=120)
    half = 0.5 * max(np.ptp(np.concatenate([m[0] for m in meshes]), axis=0).max() for meshes in scenes)
    for i, (meshes, title) in enumerate(zip(scenes, titles)):
        ax = fig.add_subplot(1, len(scenes), i + 1, projection="3d")
        render_meshes(ax, meshes, azimuth=azimuth)
        allv = np.concatenate([m[0] for m in meshes])
        centre = 0.5 * (allv.min(0) + allv.max(0))
        centre[2] = allv[:, 2].min() + half  # shared ground line: heights compare across panels
        ax.set_xlim(centre[0] - half, centre[0] + half)
        ax.set_ylim(centre[1] - half, centre[1] + half)
        ax.set_zlim(centre[2] - half, centre[2] + half)
        ax.set_box_aspect((1, 1, 1), zoom=1.45)
        ax.set_axis_off()
        ax.set_title(title, fontsize=9)
    fig.subplots_adjust(left=0, right=1, bottom=0, top=0.92, wspace=0)
    fig.savefig(path)
    plt.close(fig)
    return path
