"""Render ``docs/frame.png``: the drone hovering in the target zone, slightly tilted, mid-episode.

Run from the repository root: ``SDL_VIDEODRIVER=dummy python docs/make_frame.py``.
The drone starts in the air, hovers for a while, is then placed in a slightly tilted pose (the
state is set directly, for the picture only) and takes one step with unequal positive thrusts.
"""

from __future__ import annotations

import os
from pathlib import Path

os.environ.setdefault("SDL_VIDEODRIVER", "dummy")

import imageio.v3 as iio  # noqa: E402
import torch  # noqa: E402

from drone_torchrl.envs import DroneEnv  # noqa: E402

HOVER_STEPS = 149
TILTED_STATE = [0.15, 0.0, 2.75, 0.0, 0.2, 0.0]  # x, x_dot, z, z_dot, alpha (rad), alpha_dot
LAST_ACTION = [0.62, 0.41]  # a_l, a_r: unequal positive thrusts
OUTPUT = Path(__file__).with_name("frame.png")


def main() -> None:
    env = DroneEnv(reset_mode="air", render_mode="rgb_array")
    env.set_seed(0)
    td = env.reset()
    hover = torch.full((2,), 0.5)
    for _ in range(HOVER_STEPS):
        td = env.step(td.set("action", hover))["next"]
    env._state = torch.tensor(TILTED_STATE)
    env.step(td.set("action", torch.tensor(LAST_ACTION)))
    frame = env.render()
    env.close()
    iio.imwrite(OUTPUT, frame)
    print(f"wrote {OUTPUT} ({frame.shape[1]}x{frame.shape[0]})")


if __name__ == "__main__":
    main()
