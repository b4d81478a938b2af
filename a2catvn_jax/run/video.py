"""Videos of agents: frames side by side, episodes with a top-down map, GIF and MP4 files."""

from __future__ import annotations

import importlib.util
from pathlib import Path
from typing import Sequence

import imageio.v2 as imageio
import imageio.v3 as iio
import numpy as np

from a2catvn_jax.errors import UserError
from a2catvn_jax.run.topdown import TopdownMap

VIDEO_PANEL = 128  # video images are upscaled by an integer factor to at least this height
VIDEO_FPS = 10
END_FRAMES = 5  # video frames holding an episode's outcome
FORMATS = (".gif", ".mp4")


class VideoError(UserError, RuntimeError):
    """A video cannot be written as asked (e.g. no writer for the format)."""


def check_video_path(path) -> None:
    """`ValueError` for a file name of another format; `VideoError` when MP4 has no writer."""
    suffix = Path(path).suffix.lower()
    if suffix not in FORMATS:
        raise ValueError(f"video file must end in .gif or .mp4, got {str(path)!r}")
    if suffix == ".mp4" and importlib.util.find_spec("imageio_ffmpeg") is None:
        raise VideoError("writing .mp4 needs imageio-ffmpeg (pip install imageio-ffmpeg); or write a .gif")


def write_video(path, frames: Sequence[np.ndarray], fps: int = VIDEO_FPS) -> None:
    """Write RGB frames as a GIF or (with imageio-ffmpeg) an MP4."""
    check_video_path(path)
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    if Path(path).suffix.lower() == ".gif":
        iio.imwrite(path, np.stack(frames), duration=1000 // fps, loop=0)
    else:
        imageio.mimsave(path, frames, fps=fps)


def depth_image(depth: np.ndarray, far: float = 8.0) -> np.ndarray:
    """Depth [H, W] in metres as a grey uint8 image [H, W, 3], near is bright."""
    d = np.clip(depth / far, 0.0, 1.0)
    return (np.stack([1 - d] * 3, -1) * 255).astype(np.uint8)


def tile_frame(obs, i: int = 0) -> np.ndarray:
    """[h, 4w, 3] uint8: observation | target | depth | segmentation of agent i (of an
    `Observation`)."""
    parts = [
        np.asarray(obs.rgb[i]),
        np.asarray(obs.target_rgb[i]),
        depth_image(np.asarray(obs.depth[i])),
        np.asarray(obs.segmentation_rgb[i]),
    ]
    return np.concatenate(parts, axis=1)


def episode_frames(env, steps: list[dict], episodes: int) -> list[np.ndarray]:
    """observation | target | map frames of one agent's first `episodes` episodes.

    `steps` holds, per step, that agent's rgb, target_rgb, pose, target_pose, scene,
    goal, and the step's done and success."""
    size = steps[0]["rgb"].shape[0]
    scale = -(-VIDEO_PANEL // size)
    target_scene = np.asarray(env.world.arrays.target_scene)
    maps: dict[int, TopdownMap] = {}
    frames, path, episode = [], [], 0
    for s in steps:
        scene, goal = int(s["scene"]), int(s["goal"])
        if scene not in maps:
            maps[scene] = TopdownMap(env.world.scenes[scene], size * scale)
        path.append(s["pose"][:2])
        target = s["target_pose"] if target_scene[scene, goal] == scene else None
        images = [np.asarray(s[k]).repeat(scale, 0).repeat(scale, 1) for k in ("rgb", "target_rgb")]

        def frame(text):
            return np.concatenate(images + [maps[scene].render(path, s["pose"], target, text)], axis=1)

        frames.append(frame(f"episode {episode + 1}, step {len(path) - 1}"))
        if s["done"]:
            frames += [frame(f"episode {episode + 1}: " + ("success" if s["success"] else "failed"))] * END_FRAMES
            episode, path = episode + 1, []
            if episode == episodes:
                break
    return frames
