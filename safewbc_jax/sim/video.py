"""Offscreen MP4 of a run, replayed from the logged simulator states."""

from __future__ import annotations

import numpy as np

from safewbc_jax.model import digit

FPS = 30


def render_video(log: dict, path: str, width: int = 640, height: int = 480) -> None:
    import imageio.v3 as iio
    import mujoco

    from safewbc_jax.base import paths

    m = mujoco.MjModel.from_xml_path(str(paths.scene_xml()))
    d = mujoco.MjData(m)
    cam = mujoco.MjvCamera()
    cam.type = mujoco.mjtCamera.mjCAMERA_TRACKING
    cam.trackbodyid = m.body(digit.BASE).id
    cam.distance, cam.azimuth, cam.elevation = 3.0, 135.0, -15.0
    t = log["t"]
    frames = []
    with mujoco.Renderer(m, height, width) as r:
        for ft in np.arange(0.0, t[-1], 1.0 / FPS):
            k = int(np.searchsorted(t, ft))
            d.qpos[:] = log["qpos"][min(k, len(t) - 1)]
            mujoco.mj_forward(m, d)
            r.update_scene(d, cam)
            frames.append(r.render().copy())
    iio.imwrite(path, np.stack(frames), fps=FPS, codec="libx264")
