"""One episode of a policy trained on a Gymnasium task, as a GIF (``safenav render`` on a
non-SafeNav checkpoint): the task's own ``rgb_array`` frames, the running return and cost written
on each, and a red frame around every frame whose steps (since the previous frame) include one
that costs (Safety-Gymnasium's velocity tasks: a step over the speed threshold)."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np
import torch

from safenav.errors import SafenavError

BORDER = 6  # pixels of the red frame around a costly step


def _headless_gl() -> None:
    """MuJoCo renders off-screen through EGL where there is no display (set before it loads);
    pygame (classic control, Box2D) draws on its dummy video driver there, which spares a
    headless machine SDL's "XDG_RUNTIME_DIR is invalid" line."""
    if not os.environ.get("DISPLAY"):
        os.environ.setdefault("MUJOCO_GL", "egl")
        os.environ.setdefault("SDL_VIDEODRIVER", "dummy")


def _follow_the_body(env: Any) -> None:
    """Film a MuJoCo task with its model's ``track`` camera, which follows the body: Gymnasium
    renders with a free camera whose ``trackbodyid`` takes no effect, so a hopper that moves
    leaves the picture."""
    renderer = getattr(env.unwrapped, "mujoco_renderer", None)
    if renderer is None:
        return
    import mujoco

    track = mujoco.mj_name2id(renderer.model, mujoco.mjtObj.mjOBJ_CAMERA, "track")
    if track != -1:
        renderer.camera_id = track


def _annotate(frame: np.ndarray, text: str, costly: bool) -> np.ndarray:
    from PIL import Image, ImageDraw

    if costly:
        frame = frame.copy()
        frame[:BORDER], frame[-BORDER:] = (220, 30, 30), (220, 30, 30)
        frame[:, :BORDER], frame[:, -BORDER:] = (220, 30, 30), (220, 30, 30)
    img = Image.fromarray(frame)
    draw = ImageDraw.Draw(img)
    draw.rectangle((BORDER, BORDER, BORDER + 7 * len(text) + 6, BORDER + 16), fill=(255, 255, 255))
    draw.text((BORDER + 3, BORDER + 2), text, fill=(0, 0, 0))
    return np.asarray(img)


def _frame(env: Any, env_id: str) -> np.ndarray:
    frame = env.render()
    if not isinstance(frame, np.ndarray) or frame.ndim != 3 or frame.shape[2] != 3:
        raise SafenavError(f"{env_id}: render() gave "
                           f"{getattr(frame, 'shape', type(frame).__name__)}, not an RGB image")  # fmt: skip
    return frame.astype(np.uint8, copy=False)


@torch.no_grad()
def render_gym_episode(out: Path, policy: Any, seed: int = 1, episode: int = 0, fps: int = 25,
                       cost_fn: str | None = None, size: int = 240, max_steps: int = 100_000,
                       max_frames: int = 1500) -> dict[str, Any]:  # fmt: skip
    """Fly episode ``episode`` (from 0) after ``reset(seed=seed)`` of ``policy.meta["env_id"]``
    (with the run's ``--cost-fn`` if it had one) with the deterministic ``policy`` (a
    :class:`safenav.algos.policy.Policy`) and write ``out`` at ``fps``, one frame per
    ``round(render_fps / fps)`` env steps (real time where the task declares its
    ``render_fps``); returns the episode's return, cost and length. An episode that has not
    ended by ``max_frames`` frames (a task without a time limit, CliffWalking-v1, and a policy
    that walks in circles) is filmed that far (``"ended": False``): its frames would otherwise
    fill the memory. One that is not filmed must end within ``max_steps``."""
    import gymnasium as gym

    import safenav  # noqa: F401  (registers the velocity tasks)
    from safenav.common.costs import CostFn
    from safenav.envs.render import write_gif
    from safenav.envs.vector import flat_observations, policy_action_to_env

    env_id = str(policy.meta.get("env_id", ""))
    _headless_gl()
    try:
        try:
            env = gym.make(env_id, render_mode="rgb_array", width=size, height=size)
        except TypeError:  # a task whose renderer takes no size
            env = gym.make(env_id, render_mode="rgb_array")
    except (TypeError, gym.error.Error) as err:
        raise SafenavError(f"{env_id} does not render to images (render_mode='rgb_array'): "
                           f"{err}") from None  # fmt: skip
    if "rgb_array" not in env.metadata.get("render_modes", []):  # Gymnasium only warns
        env.close()
        raise SafenavError(f"{env_id} does not render to images: its render modes are "
                           f"{env.metadata.get('render_modes', [])}, not 'rgb_array'")  # fmt: skip
    _follow_the_body(env)
    if cost_fn is not None:
        env = CostFn(env, cost_fn)
    env = flat_observations(env)  # as training saw it (a one-hot Discrete observation, ...)
    stride = max(1, round(env.metadata.get("render_fps", fps) / fps))
    obs, _ = env.reset(seed=seed)
    frames: list[np.ndarray] = []
    try:
        for k in range(episode + 1):
            ret, cost, steps, done = 0.0, 0.0, 0, False
            filmed, costly = k == episode, False  # costly: a step since the last frame cost
            while not done and steps < max_steps and not (filmed and len(frames) >= max_frames):
                action = policy_action_to_env(policy(obs), policy.meta)  # a dict of Boxes too
                obs, reward, terminated, truncated, info = env.step(action)
                c = float(info.get("cost", 0.0))
                ret, cost, steps = ret + float(reward), cost + c, steps + 1
                done, costly = terminated or truncated, costly or c > 0
                if filmed and (steps % stride == 0 or done):
                    text = f"step {steps}  return {ret:.0f}  cost {cost:g}"
                    frames.append(_annotate(_frame(env, env_id), text, costly))
                    costly = False
            if not done and not filmed:
                raise SafenavError(f"episode {k} of {env_id} did not end in {max_steps} steps")
            if not filmed:
                obs, _ = env.reset()
    finally:
        env.close()
    frames += [frames[-1]] * fps  # hold the last frame a second: the outcome stays visible
    Path(out).parent.mkdir(parents=True, exist_ok=True)
    write_gif(out, frames, fps)
    return {"env": env_id, "episode": episode, "return": round(ret, 2), "cost": cost,
            "length": steps, "ended": done, "frames": len(frames) - fps,
            "steps_per_frame": stride}  # fmt: skip


__all__ = ["render_gym_episode"]
