"""The shipped demo without ROS: dressed, posed bodies at three shapes rendered to one PNG."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from .render import GARMENT_COLORS, SKIN, render_scenes

DEMO_SHAPES = (
    ("slim tall woman", [1.0, 2 / 3, 0.4, 0.2, 0.8, 0.5]),
    ("average adult", [0.5, 2 / 3, 0.5, 0.5, 0.5, 0.5]),
    ("heavy muscular man", [0.0, 0.8, 0.9, 0.9, 0.4, 0.5]),
)


def load_motion(source: str, shape):
    """A procedural motion by name, or a CMU .bvh file retargeted onto `shape`'s skeleton."""
    from ..motion.procedural import make_motion
    from ..motion.retarget import load_cmu_motion

    if source.endswith(".bvh"):
        return load_cmu_motion(source, shape.heads, shape.tails)
    return make_motion(source, fps=30.0, rest=(shape.heads, shape.tails))


def write_demo_png(out="out/dressed_bodies.png", motion: str = "walk", garments=("tshirt", "trousers"),
                   frame_fraction: float = 0.3) -> Path:
    """Render the garments on three body shapes posed at one frame of `motion`; returns the PNG path."""
    from ..body import AnnyBody
    from ..garment import make_garment
    from ..garment.dressing import Dressing

    body = AnnyBody()
    dressing = Dressing(body, [make_garment(name, body) for name in garments], dtype=np.float64)
    scenes, titles = [], []
    for title, beta in DEMO_SHAPES:
        shape = dressing.set_shape(beta)
        clip = load_motion(motion, shape)
        frame = int(frame_fraction * (len(clip.rotvecs) - 1))
        dressing.pose(clip.rotvecs[frame], np.zeros(3))  # root translation left out: keep the agent centred
        meshes = [(dressing.body_vertices.copy(), dressing.body_faces, SKIN)]
        meshes += [(v.copy(), g.faces, GARMENT_COLORS.get(g.name, (0.5, 0.5, 0.5)))
                   for g, v in zip(dressing.garments, dressing.garment_vertices)]
        scenes.append(meshes)
        titles.append(f"{title}\n{Path(motion).name}, frame {frame}")
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    return render_scenes(out, scenes, titles)
