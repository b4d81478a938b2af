"""Top-down drawings of scenes (matplotlib, without pyplot), e.g. as the background of path maps."""

from __future__ import annotations

from typing import Optional

import matplotlib.patches as mpatches
import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from a2catvn_jax.env.scenes.mjcf import geom_aabb
from a2catvn_jax.env.scenes.spec import CLASS_ID, Scene, class_colors


def plot_topdown(
    scene: Scene,
    ax=None,
    *,
    color_by: str = "rgba",
    room_labels: bool = True,
    geom_labels: bool = False,
):
    """Draw the scene seen from above on a matplotlib axis and return the axis.

    Ceilings are left out; the other geoms are drawn lowest top first, so what is
    drawn last is what a camera above would see. color_by: "rgba" (geom colours) or
    "class" (semantic class colours from `class_colors`). Boxes and horizontal
    capsules are drawn as their xy bounding boxes, spheres and vertical capsules as
    discs, ellipsoids as ellipses.
    """
    if color_by not in ("rgba", "class"):
        raise ValueError(f"color_by must be 'rgba' or 'class', got {color_by!r}")
    if ax is None:
        ax = Figure(figsize=(8, 8)).subplots()
    table = class_colors() / 255.0
    items = []
    for g in scene.geoms:
        if g.cls == "ceiling":
            continue
        lo, hi = geom_aabb(g)
        items.append((hi[2], g, lo, hi))
    items.sort(key=lambda it: it[0])
    for _, g, lo, hi in items:
        color = g.rgba[:3] if color_by == "rgba" else table[CLASS_ID[g.cls]]
        edge = (0, 0, 0, 0.35)
        cx, cy = (lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2
        w, h = hi[0] - lo[0], hi[1] - lo[1]
        if g.type == "sphere" or (g.type == "capsule" and abs(w - h) < 1e-9):
            patch = mpatches.Circle((cx, cy), w / 2, facecolor=color, edgecolor=edge, lw=0.5)
        elif g.type == "ellipsoid":
            patch = mpatches.Ellipse((cx, cy), w, h, facecolor=color, edgecolor=edge, lw=0.5)
        else:
            patch = mpatches.Rectangle((lo[0], lo[1]), w, h, facecolor=color, edgecolor=edge, lw=0.5)
        ax.add_patch(patch)
        if geom_labels and g.cls not in ("floor", "wall"):
            ax.text(cx, cy, g.name or g.cls, fontsize=5, ha="center", va="center")
    if room_labels:
        for i, room in enumerate(scene.rooms):
            x0, y0, x1, y1 = room.rect
            ax.text(
                (x0 + x1) / 2,
                y1 - 0.15,
                f"{i}: {room.type}",
                fontsize=8,
                ha="center",
                va="top",
                bbox=dict(facecolor="white", alpha=0.7, lw=0),
            )
    x0, y0, x1, y1 = scene.bounds
    pad = 0.3
    ax.set_xlim(x0 - pad, x1 + pad)
    ax.set_ylim(y0 - pad, y1 + pad)
    ax.set_aspect("equal")
    ax.set_title(scene.name)
    return ax


def save_topdown(scene: Scene, path: str, *, color_by: str = "rgba", dpi: int = 120, size: Optional[float] = None):
    """Render `plot_topdown` of a scene to an image file."""
    x0, y0, x1, y1 = scene.bounds
    scale = size or 8.0
    aspect = (y1 - y0 + 0.6) / max(x1 - x0 + 0.6, 1e-6)
    fig = Figure(figsize=(scale, max(2.0, scale * aspect)))
    plot_topdown(scene, fig.subplots(), color_by=color_by)
    fig.tight_layout()
    fig.savefig(path, dpi=dpi)
    return path


class TopdownMap:
    """A scene's top-down map as square RGB images with a path, an agent pose and a target pose.

    The scene is drawn once; `render` only moves the path and the pose markers. Poses
    are (x, y, yaw, ...) with yaw in radians from the x axis.
    """

    def __init__(self, scene: Scene, size: int = 128, *, color_by: str = "rgba"):
        self.size = size
        self.fig = Figure(figsize=(1.0, 1.0), dpi=size)
        self.canvas = FigureCanvasAgg(self.fig)
        ax = self.fig.add_axes((0.0, 0.0, 1.0, 1.0))
        plot_topdown(scene, ax, color_by=color_by, room_labels=False)
        ax.set_title("")
        ax.set_axis_off()
        x0, y0, x1, y1 = scene.bounds
        self._arrow = 0.08 * max(x1 - x0, y1 - y0)
        (self._path,) = ax.plot([], [], "-", color="tab:blue", lw=1.0)
        (self._target,) = ax.plot([], [], "*", color="tab:red", ms=7, mec="black", mew=0.3)
        (self._target_dir,) = ax.plot([], [], "-", color="tab:red", lw=1.2)
        (self._agent,) = ax.plot([], [], "o", color="tab:blue", ms=4, mec="black", mew=0.3)
        (self._agent_dir,) = ax.plot([], [], "-", color="tab:blue", lw=1.2)
        self._text = ax.text(0.03, 0.97, "", transform=ax.transAxes, fontsize=5, ha="left", va="top",
                             bbox=dict(facecolor="white", alpha=0.8, lw=0, pad=1))

    def _pose(self, marker, direction, pose):
        if pose is None:
            marker.set_data([], [])
            direction.set_data([], [])
            return
        x, y, yaw = (float(v) for v in pose[:3])
        marker.set_data([x], [y])
        direction.set_data([x, x + self._arrow * np.cos(yaw)], [y, y + self._arrow * np.sin(yaw)])

    def render(self, path=None, pose=None, target_pose=None, text: str = "") -> np.ndarray:
        """[size, size, 3] uint8: the map with `path` [N, >=2] (xy), `pose` and `target_pose`."""
        path = np.zeros((0, 2)) if path is None or len(path) == 0 else np.asarray(path, float)
        self._path.set_data(path[:, 0], path[:, 1])
        self._pose(self._agent, self._agent_dir, pose)
        self._pose(self._target, self._target_dir, target_pose)
        self._text.set_text(text)
        self._text.set_visible(bool(text))
        self.canvas.draw()
        return np.asarray(self.canvas.buffer_rgba())[..., :3].copy()


__all__ = ["TopdownMap", "plot_topdown", "save_topdown"]


